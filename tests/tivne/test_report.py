"""python -m tivne.report: the page names only images that exist, built from a real smoke run; the
rasteriser and the per-frame trajectory errors on known inputs; TensorBoard gets meshes and hparams."""

from __future__ import annotations

import html.parser
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_dir
from matplotlib.image import imread
from omegaconf import OmegaConf

from tivne.config import RenderConfig, ReportConfig
from tivne.reporting.events import read_scalars
from tivne.reporting.page import write_report
from tivne.reporting.raster import look_at, pinhole, rasterize
from tivne.reporting.trajectory import plot_axes, trajectory_errors
from tivne.slam.run import run

CONF = Path(__file__).resolve().parents[2] / "conf"
SMOKE = ["experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null"]
SMALL = ReportConfig(frames=2, mesh_width=64)


class ImageSources(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.sources: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.sources.append(dict(attrs)["src"])


def image_sources(page: Path) -> list[str]:
    parser = ImageSources()
    parser.feed(page.read_text())
    return parser.sources


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    """A finished smoke run with the .hydra/ files Hydra would have written."""
    run_dir = tmp_path_factory.mktemp("run")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=SMOKE)
    run(cfg, run_dir)
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    (run_dir / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in SMOKE))
    return run_dir


def test_report_cli_names_only_images_that_exist(smoke_run, capsys):
    from tivne.report import main

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("report", overrides=[f"run_dir={smoke_run}", "report.frames=2", "report.mesh_width=64"])
    main.__wrapped__(cfg)  # the command's body, without Hydra's own run setup
    printed = json.loads(capsys.readouterr().out)
    page = smoke_run / "report.html"
    assert printed["report"] == str(page)
    sources = image_sources(page)
    assert sources and all((smoke_run / s).is_file() for s in sources)
    assert sorted(str(smoke_run / s) for s in sources) == sorted(printed["images"])
    names = {Path(s).name for s in sources}
    assert {"trajectory.png", "trajectory_error.png", "curves.png", "renders.png", "mesh_t0.000.png", "mesh_t0.133.png"} <= names
    snapshot = imread(smoke_run / "report" / "mesh_t0.133.png")
    assert snapshot.ndim == 3 and snapshot[..., :3].std() > 0.05  # a mesh was drawn, not a blank canvas
    text = page.read_text()
    assert "ate_rmse_m" in text and "experiment=smoke" in text


def test_report_without_the_sequence_or_meshes(smoke_run, tmp_path):
    """A dataset not on this machine, an interrupted run: the report says what it lacks."""
    partial = tmp_path / "partial"
    partial.mkdir()
    for name in ("trajectory.txt", "metrics.json"):
        (partial / name).write_bytes((smoke_run / name).read_bytes())
    page, images = write_report(partial, None, RenderConfig(), SMALL)
    assert [p.name for p in images] == ["trajectory.png"]
    assert image_sources(page) == ["report/trajectory.png"]
    text = page.read_text()
    assert "no ground-truth poses" in text and "no meshes" in text and "no scalars" in text
    with pytest.raises(FileNotFoundError):
        write_report(tmp_path / "missing", None, RenderConfig(), SMALL)


def test_tensorboard_gets_meshes_and_final_metrics(smoke_run):
    scalars = read_scalars(smoke_run / "tb")
    assert len(scalars["perf/s_per_frame"][0]) == 5
    metrics = json.loads((smoke_run / "metrics.json").read_text())
    assert scalars["final/ate_rmse_m"][1][-1] == pytest.approx(metrics["ate_rmse_m"])
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tensors = set()
    for path in (smoke_run / "tb").glob("events.*"):
        events = EventAccumulator(str(path))
        events.Reload()
        tensors |= set(events.Tags()["tensors"])
    assert {"mesh/t0.000_VERTEX", "mesh/t0.000_FACE"} <= tensors


# ---- the pieces ----------------------------------------------------------------------------------


def square(z: float, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A square at depth z facing a camera at the origin looking along +z (faces wound towards it)."""
    v = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def test_rasteriser_nearest_face_wins_and_back_faces_are_culled():
    K = pinhole(40, 30)
    near_v, near_f = square(2.0, 0.2)
    far_v, far_f = square(3.0, 2.0)
    vertices = np.concatenate([near_v, far_v])
    faces = np.concatenate([near_f, far_f + 4])
    colors = np.concatenate([np.tile([1.0, 0, 0], (4, 1)), np.tile([0, 0, 1.0], (4, 1))])
    image = rasterize(vertices, faces, colors, K, np.eye(4), 40, 30)
    centre, corner = image[15, 20], image[2, 2]
    assert centre[0] > 0.5 and centre[2] == 0  # the near red square in front
    assert corner[2] > 0.5 and corner[0] == 0  # the far blue one around it
    culled = rasterize(vertices, faces[:, ::-1], colors, K, np.eye(4), 40, 30)
    assert (culled == 1.0).all()  # seen from behind: nothing


def test_rasteriser_covers_a_sphere_like_its_projection():
    sphere = trimesh.creation.icosphere(subdivisions=4)
    w2c = look_at(np.array([0.0, 0.0, -5.0]), np.zeros(3), np.array([0.0, -1.0, 0.0]))
    width = height = 101
    K = pinhole(width, height, 60.0)
    image = rasterize(sphere.vertices, sphere.faces, np.full((len(sphere.vertices), 3), 0.5), K, w2c, width, height)
    covered = (image < 1.0).any(axis=2).mean()
    radius_px = K[0, 0] * np.tan(np.arcsin(1 / 5))  # the silhouette of a unit sphere 5 m away
    assert covered == pytest.approx(np.pi * radius_px**2 / (width * height), rel=0.05)


def random_trajectory(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    return poses


def test_trajectory_errors_after_alignment():
    from scipy.spatial.transform import Rotation

    gt = random_trajectory(20)
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    offset[:3, 3] = [1.0, 2.0, 3.0]
    est = offset @ gt  # the same trajectory in another world frame: no error after alignment
    est[7, :3, :3] = est[7, :3, :3] @ Rotation.from_euler("x", 5, degrees=True).as_matrix()
    ts = np.arange(20) / 30.0
    errors, reason = trajectory_errors(ts + 100.0, est, ts + 100.0, gt)
    assert reason is None and errors.times[0] == 0.0 and errors.times[-1] == pytest.approx(19 / 30)
    assert np.abs(errors.translation_m).max() < 1e-9
    # the best constant rotation takes 1/20 of frame 7's 5 degrees (the chordal mean of 19 x 0 and 1 x 5)
    shift = np.degrees(np.arctan2(np.sin(np.radians(5)), 19 + np.cos(np.radians(5))))
    assert errors.rotation_deg[7] == pytest.approx(5.0 - shift) and np.allclose(np.delete(errors.rotation_deg, 7), shift)
    assert trajectory_errors(ts, est, ts[:2], gt[:2])[0] is None


def test_plot_axes_put_up_last():
    poses = random_trajectory(10)
    poses[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # cameras with y (down) along world -y: up is +y
    axes = plot_axes(poses)
    assert np.allclose(axes[2], [0, 1, 0]) and np.allclose(axes @ axes.T, np.eye(3), atol=1e-9)
