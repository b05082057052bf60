"""data_modules is the ground floor: no module in it may import tivne (DESIGN.md, Layout).

Parsed, not imported, so imports inside functions and behind ``if TYPE_CHECKING`` count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "data_modules"
FORBIDDEN = "tivne"


def _is_forbidden(module: str | None) -> bool:
    return module is not None and (module == FORBIDDEN or module.startswith(FORBIDDEN + "."))


def upward_imports(source: str, filename: str = "<string>") -> list[str]:
    """``line: statement`` for every import of ``tivne`` anywhere in ``source`` (any nesting depth).

    Covers ``import tivne...``, ``from tivne... import ...`` and ``importlib.import_module("tivne...")``
    / ``__import__("tivne...")`` with a literal name.
    """
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names if _is_forbidden(a.name)]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module] if node.level == 0 and _is_forbidden(node.module) else []
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            arg = node.args[0].value
            names = [arg] if name in ("import_module", "__import__") and isinstance(arg, str) and _is_forbidden(arg) else []
        else:
            continue
        if names:
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def test_detector_sees_every_form():
    src = (
        "import os\nimport tivne\nfrom tivne.geometry import x\nimport tivnex\n"
        "def f():\n    from tivne import metrics\n    import importlib\n    importlib.import_module('tivne.masks')\n"
        "from . import tum\nfrom data_modules.io import tivne_like\n"
    )
    assert [line.split(":")[0] for line in upward_imports(src)] == ["2", "3", "6", "8"]


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_package_found():
    assert (PACKAGE / "frame.py") in MODULES


@pytest.mark.parametrize("path", MODULES, ids=[str(p.relative_to(PACKAGE)) for p in MODULES])
def test_no_tivne_imports(path: Path):
    bad = upward_imports(path.read_text(encoding="utf-8"), str(path))
    assert not bad, f"data_modules/{path.relative_to(PACKAGE)} imports tivne (data_modules is the ground floor): {bad}"
