"""The entity paths of a TivNe recording and the few rerun calls that log each kind of thing, shared
by the live recorder and the finished-run recording (same layout in both).

Timelines: ``frame`` (sequence: the frame number of the run) and ``scene_time`` (duration: seconds
since the run's first frame; add the static ``run`` entity's ``t0_s`` for the sequence clock of
trajectory.txt). Poses are c2w in the SLAM frame (the first camera's); ground truth is mapped into
it with the first frame that has both poses (``gt_to_slam``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh

WORLD = "world"
CAMERA = "world/camera"
GT_CAMERA = "world/gt_camera"
RGB = "world/camera/rgb"
DEPTH = "world/camera/depth"
MASK = "world/camera/mask"
RENDERED_RGB = "rendered/rgb"
RENDERED_DEPTH = "rendered/depth"
TRAJECTORY = "world/trajectory/estimated"
GT_TRAJECTORY = "world/trajectory/ground_truth"
KEYFRAMES = "world/keyframes"
MAP = "world/map"
MESH = "world/mesh"
OBJECTS = "world/objects"
GT_OBJECTS = "world/gt_objects"
STATUS = "tracking/status"
LOST = "plots/tracking_lost"
ERROR = "plots/translation_error_m"
RUN = "run"

ESTIMATE_COLOUR = (40, 140, 255)
GT_COLOUR = (60, 200, 90)
KEYFRAME_COLOUR = (255, 170, 30)


def rerun():
    """The rerun module; ImportError naming the extra to install when it is missing."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise ImportError("rerun-sdk is not installed; pip install -e '.[viewer]'") from exc
    return rr


def default_blueprint(rendered: bool = True, play_state: str = "paused"):
    """The layout a recording opens with: the 3D world (cameras, trajectories, map, meshes, boxes)
    beside the observed (and ``rendered``) frames, and the plots under it, on ``scene_time``
    (``play_state`` 'following': the time cursor at the newest data)."""
    import rerun.blueprint as rrb

    frames = [rrb.Spatial2DView(origin=RGB, name="colour")]
    frames += [rrb.Spatial2DView(origin=RENDERED_RGB, name="rendered")] if rendered else []
    frames += [rrb.Spatial2DView(origin=DEPTH, name="depth")]
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=WORLD, name="4D map"),
                rrb.Vertical(*frames),
                column_shares=[3, 1],
            ),
            rrb.TimeSeriesView(origin="plots", name="tracking"),
            row_shares=[4, 1],
        ),
        rrb.TimePanel(timeline="scene_time", play_state=play_state),
        collapse_panels=True,
    )


def set_time(rec, frame: int, seconds: float) -> None:
    """Put what follows at frame number ``frame`` and ``seconds`` since the first frame."""
    rec.set_time("frame", sequence=int(frame))
    rec.set_time("scene_time", duration=float(seconds))


def log_run_info(rec, t0: float, intrinsics_K: np.ndarray | None, width: int, height: int) -> None:
    """Static: the sequence time of the first frame and the camera model ((3, 3) K, OpenCV axes:
    RDF; none when ``intrinsics_K`` is None)."""
    rr = rerun()
    rec.log(RUN, rr.AnyValues(t0_s=float(t0)), static=True)
    rec.log(WORLD, rr.ViewCoordinates.RDF, static=True)
    if intrinsics_K is None:
        return
    rec.log(CAMERA, rr.Pinhole(image_from_camera=intrinsics_K, resolution=[width, height], camera_xyz=rr.ViewCoordinates.RDF,
                               image_plane_distance=0.15), static=True)


def log_pose(rec, entity: str, pose: np.ndarray) -> None:
    """A (4, 4) c2w pose as the entity's transform."""
    rr = rerun()
    rec.log(entity, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))


def log_strip(rec, entity: str, positions: Sequence[np.ndarray] | np.ndarray, colour: tuple[int, int, int]) -> None:
    """(N, 3) positions as one line strip (nothing for fewer than 2)."""
    rr = rerun()
    pts = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    if len(pts) >= 2:
        rec.log(entity, rr.LineStrips3D([pts], colors=[colour], radii=[0.004]))


def log_box(rec, entity: str, pose: np.ndarray, half_size: np.ndarray, colour: tuple[int, int, int]) -> None:
    """An oriented box: pose (4, 4) box-to-world, half_size (3,)."""
    rr = rerun()
    log_pose(rec, entity, pose)
    rec.log(entity, rr.Boxes3D(half_sizes=[np.asarray(half_size, dtype=np.float32)], colors=[colour]))


def log_mesh(rec, mesh: trimesh.Trimesh) -> None:
    """A mesh (vertex colours where it has them) at :data:`MESH`; an empty one clears it."""
    rr = rerun()
    if len(mesh.faces) == 0:
        rec.log(MESH, rr.Clear(recursive=False))
        return
    colours = None
    visual = getattr(mesh, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        colours = np.asarray(visual.vertex_colors)[:, :3]
    rec.log(MESH, rr.Mesh3D(
        vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
        triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
        vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
        vertex_colors=colours,
    ))


def decimate(points: np.ndarray, limit: int) -> np.ndarray:
    """(N, 3) -> at most ``limit`` of them, evenly strided (deterministic)."""
    if limit <= 0:
        return points[:0]
    step = max(1, -(-len(points) // limit))
    return points[::step]


def nearest_frame(timestamps: Sequence[float], t: float) -> int:
    """Index of the processed frame closest to time ``t`` (same clock)."""
    return int(np.argmin(np.abs(np.asarray(timestamps, dtype=np.float64) - float(t))))
