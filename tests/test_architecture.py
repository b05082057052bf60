"""The layout rules of docs/architecture.md, checked on the source: layers, no import cycles, thin
CLIs, small modules and functions. Imports inside functions count too."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("data_modules", "tivne")
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80

# Bottom-up. A module may import modules of its own layer entry (its package) or of lower entries.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("data_modules",),
    ("tivne", "tivne.settings", "tivne.config", "tivne.utils"),
    ("tivne.geometry",),
    ("tivne.metrics",),
    ("tivne.field",),
    ("tivne.render",),
    ("tivne.meshing",),
    ("tivne.masks",),
    ("tivne.slam",),
    ("tivne.evaluation",),
    ("tivne.reporting",),
    ("tivne.viewer",),  # a run as a rerun recording: above every library part, below the CLIs
    ("tivne.slam.run",),  # the library entry of a run: the loop, driven, watched and evaluated
    ("tivne.cli",),
)
# Command-line entry points: on top of everything, imported by no module.
CLIS = {"tivne.train", "tivne.view", "tivne.mesh", "tivne.evaluate", "tivne.make_masks", "tivne.collect", "tivne.report", "data_modules.inspect"}
# The pure metrics may use nothing of tivne but geometry.
METRICS_MAY_IMPORT = ("tivne.geometry", "tivne.metrics")
# Inside tivne.slam, bottom-up: what a frame's walk hands from stage to stage. The loop is plain
# (no Lightning, no Hydra); the LightningModule only adapts it; run is the library entry on top.
SLAM_LAYERS: tuple[tuple[str, ...], ...] = (
    ("tivne.slam", "tivne.slam.outputs"),
    ("tivne.slam.tracking",),
    ("tivne.slam.objects",),
    ("tivne.slam.keyframes", "tivne.slam.trajectory", "tivne.slam.allocation"),
    ("tivne.slam.backend",),
    ("tivne.slam.mapping",),
    ("tivne.slam.state", "tivne.slam.checkpoint", "tivne.slam.observer"),
    ("tivne.slam.loop",),
    ("tivne.slam.results",),
    ("tivne.slam.system",),
    ("tivne.slam.run",),
)
FRAMEWORKS = ("lightning", "hydra", "omegaconf")
MAX_SYSTEM_LINES = 150


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def imports_of(path: Path, known: set[str]) -> set[str]:
    """Project modules that ``path`` imports anywhere in its body (resolved to known modules)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
    return found


def layer_of(module: str, layers: tuple[tuple[str, ...], ...] = LAYERS) -> int:
    """Index of the entry of ``layers`` whose longest prefix names ``module`` (-1: none)."""
    best, rank = -1, -1
    for i, entry in enumerate(layers):
        for prefix in entry:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, rank = len(prefix), i
    return rank


GRAPH = {m: imports_of(p, set(sources())) - {m} for m, p in sources().items()}


def test_every_module_has_a_layer():
    assert [m for m in GRAPH if m not in CLIS and layer_of(m) < 0] == []


def test_no_module_imports_a_higher_layer():
    bad = [
        f"{m} -> {d}"
        for m, deps in GRAPH.items()
        if m not in CLIS
        for d in deps
        if d not in CLIS and layer_of(d) > layer_of(m)
    ]
    assert bad == []


def test_clis_are_imported_by_nothing():
    assert [f"{m} -> {d}" for m, deps in GRAPH.items() for d in deps if d in CLIS] == []


def test_metrics_import_only_geometry():
    bad = [f"{m} -> {d}" for m, deps in GRAPH.items() if m.startswith("tivne.metrics") for d in deps
           if d.startswith("tivne") and not d.startswith(METRICS_MAY_IMPORT)]
    assert bad == []


def test_no_import_cycles():
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(GRAPH.get(m, ())):
            if d.startswith(m + "."):
                continue  # a package's __init__ re-exporting its own modules
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [m, d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(GRAPH):
        if m not in state:
            visit(m, [m])
    assert cycles == []


@pytest.mark.parametrize("module", sorted(sources()))
def test_module_and_function_size(module):
    path = sources()[module]
    text = path.read_text()
    assert len(text.splitlines()) <= MAX_MODULE_LINES, f"{path.relative_to(REPO)} has {len(text.splitlines())} lines"
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert long == [], f"{path.relative_to(REPO)}: {long}"


def slam_layer_of(module: str) -> int:
    return layer_of(module, SLAM_LAYERS)


def test_slam_modules_import_only_lower_slam_stages():
    slam = [m for m in GRAPH if m.startswith("tivne.slam.")]
    assert [m for m in slam if slam_layer_of(m) < 0] == []
    bad = [f"{m} -> {d}" for m in slam for d in GRAPH[m] if d.startswith("tivne.slam.") and slam_layer_of(d) > slam_layer_of(m)]
    assert bad == []


def framework_imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
        found |= {n.split(".")[0] for n in names if n.split(".")[0] in FRAMEWORKS}
    return found


def test_the_loop_and_everything_below_it_are_plain_python():
    """No Lightning or Hydra under the loop: a Fabric or plain-Python runner can drive it."""
    plain = [m for m in GRAPH if m.startswith("tivne.slam") and slam_layer_of(m) <= slam_layer_of("tivne.slam.results")]
    assert {m: sorted(framework_imports(sources()[m])) for m in plain if framework_imports(sources()[m])} == {}
    assert sorted(framework_imports(sources()["tivne.slam.system"])) == ["lightning"]


def test_the_lightning_module_is_thin():
    lines = len(sources()["tivne.slam.system"].read_text().splitlines())
    assert lines <= MAX_SYSTEM_LINES, f"tivne/slam/system.py has {lines} lines"


def test_benchmarks_import_no_command_line_module():
    known = set(sources())
    bad = {p.name: sorted(imports_of(p, known) & CLIS) for p in sorted((REPO / "bench").glob("*.py")) if imports_of(p, known) & CLIS}
    assert bad == {}


# The object tracking is a component under the per-frame loop (it is ported onto the refactored loop
# as is): of tivne.slam it uses only the odometry, its pyramids and the run directory.
OBJECTS_MAY_USE_OF_SLAM = ("tivne.slam.objects", "tivne.slam.tracking.odometry", "tivne.slam.tracking.pyramid", "tivne.slam.tracking.robust", "tivne.slam.outputs")


def test_objects_package_uses_only_the_odometry_of_the_loop():
    assert any(m.startswith("tivne.slam.objects") for m in GRAPH)
    bad = [f"{m} -> {d}" for m, deps in GRAPH.items() if m.startswith("tivne.slam.objects") for d in deps
           if d.startswith("tivne.slam") and not d.startswith(OBJECTS_MAY_USE_OF_SLAM)]
    assert bad == []


# The pose-graph back end sits beside the loop, not in it: it may use the odometry and the keyframe
# overlap of tivne.slam, never the loop's modules (loop, system, checkpoint, mapping, the tracker), so it can
# be re-wired onto another loop; gtsam (an optional extra) is imported by one module only.
BACKEND = "tivne.slam.backend"
BACKEND_MAY_IMPORT_FROM_SLAM = ("tivne.slam.tracking.odometry", "tivne.slam.tracking.pyramid", "tivne.slam.keyframes", "tivne.slam.tracking.robust",
                                "tivne.slam.tracking.overlap", "tivne.slam.tracking.sensor", BACKEND)
GTSAM_MODULES = {"tivne.slam.backend.graph"}


def test_backend_does_not_import_the_loop():
    bad = [f"{m} -> {d}" for m, deps in GRAPH.items() if m.startswith(BACKEND) for d in deps
           if d.startswith("tivne.slam") and not d.startswith(BACKEND_MAY_IMPORT_FROM_SLAM)]
    assert bad == []


def test_gtsam_is_imported_by_the_graph_module_only():
    importers = set()
    for m, path in sources().items():
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "gtsam" or n.startswith("gtsam.") for n in names):
                importers.add(m)
    assert importers <= GTSAM_MODULES
