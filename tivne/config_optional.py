"""The settings of the optional parts of a run (each off or the paper's way by default): object
fields (``field=objects``, section ``object_field``), object tracking (``objects``), the viewer
(``viewer``), the pose-graph back end (``backend``) and ``python -m tivne.report`` (``report``). Same mechanism as :mod:`tivne.config`, which
lists them among its sections and re-exports them."""

from __future__ import annotations

import dataclasses
import importlib.util
from dataclasses import dataclass
from typing import ClassVar

from tivne.settings import ConfigError, Settings, setting


@dataclass(frozen=True)
class ObjectFieldConfig(Settings):
    """Object fields of ``field=objects`` (:class:`tivne.field.objects.ObjectField`): one canonical
    field per moving object in its own frame, beside the static field of ``field.*``. tracks: where
    the objects' SE(3) poses come from ("tracked": the object tracker of ``objects.*``, which must
    be on; "oracle": the dataset's ground truth, the ablation's upper bound). voxel_size, embed_dim, hidden_dim, num_hidden, capacity: each object's grid and decoder;
    time: keep Θd for the residual non-rigid motion (Δe exactly 0 at the object's first time);
    time_frequencies, offset_ramp: as ``field.*``; time_lowest_octave: as ``field.*``, -3 so that an
    object's time code repeats only after 16 units of τ (seconds at ``field.time_scale`` 1) of its
    life: with ``field``'s 0 it repeats every 2, and a deforming object's states 2 s apart shared one
    code (the breathing blob of a 10 s run, on its exact track, 0.75-4.7 cm off; with -3, 0.4-1.7 cm);
    surface_cell: record of the object's observed
    surface (object frame) for ``mesh.near_surface``; box_margin: metres the object box grows by;
    window: an object is placed at τ only if observed within this many τ; mesh_resolution: the
    marching-cubes step of the object meshes (metres, object frame); allocation_dilation: voxels
    allocated around each object's depth points (its own grid)."""

    section: ClassVar[str] = "object_field"
    tracks: str = setting("tracked", choices=("tracked", "oracle"))
    voxel_size: float = setting(0.04, gt=0)
    embed_dim: int = setting(16, ge=1)
    hidden_dim: int = setting(64, ge=1)
    num_hidden: int = setting(3, ge=1)
    capacity: int = setting(4096, ge=1)
    max_capacity: int = setting(500_000, ge=1)
    time: bool = True
    time_frequencies: int = setting(4, ge=0)
    time_lowest_octave: int = setting(-3, ge=-16, le=16)
    offset_ramp: float = setting(0.1, gt=0)
    allocation_dilation: int = setting(1, ge=0)
    surface_cell: float = setting(0.01, ge=0)
    box_margin: float = setting(0.1, ge=0)
    window: float = setting(0.5, ge=0)
    mesh_resolution: float = setting(0.01, gt=0)

    def object_config(self, field: Settings) -> Settings:
        """Each object's :class:`tivne.field.TimeVaryingField` section: ``field`` (a
        :class:`tivne.config.FieldConfig`, which imports this module) with these settings."""
        own = ("voxel_size", "embed_dim", "hidden_dim", "num_hidden", "capacity", "max_capacity", "time", "time_frequencies",
               "time_lowest_octave", "offset_ramp", "surface_cell")
        return dataclasses.replace(field, name="object", **{k: getattr(self, k) for k in own})


@dataclass(frozen=True)
class ObjectsConfig(Settings):
    """Rigid moving objects (:class:`tivne.slam.objects.ObjectTracker`): track: one SE(3) track per
    object, written to objects/<id>.txt. source: "dataset" (the frames' instance ids, Co-Fusion
    mask_id, the synthetic family), "geometric" (connected, depth-continuous segments of the
    frame's dynamic mask, identities by overlap under the predicted motion) or "auto" (the objects
    follow the run's masks: with ``masks=dataset`` the instance ids where a frame has them and the
    segments of its motion mask where it has only that; else "geometric" on whatever mask the
    provider makes: geometric, folder, Mask R-CNN). min_pixels: smaller
    instances are ignored. levels: odometry pyramid levels on an object's pixels (objects are
    small: the coarsest level must keep pixels). depth_smoothing: radius (pixels) of the mean filter
    over the object's own depths before its odometry (0 = off; axial noise biases the object's
    rotation towards zero, the errors-in-variables effect, on few pixels). keyframe_overlap, keyframe_inliers: a new reference observation
    when the odometry's overlap with the current one, or its inlier ratio, falls below these (a
    turning object's faces go oblique and its shading changes long before the overlap drops). min_iou: a segment continues a
    track when its overlap with the track's predicted mask reaches this. reid_distance: a segment
    re-identifies a lost track whose predicted centre is this close (m) and whose size agrees
    within reid_size_ratio. max_gap_s: a track unseen longer is lost (then only re-identified).
    border_wait: a new object the image border cuts off waits up to this many frames for a whole
    view before its track starts from it (0 = start at once); the waiting views are then aligned to
    it, back to the first that shows less than half as much of the object (a sliver's rotation is
    barely determined, and every later view would be aligned to it). accel_sigma (m/s²),
    angular_accel_sigma (rad/s²): the motion prior of each object's odometry, a Gaussian on the
    deviation from its constant-velocity prediction at its centre with σ = ½ a Δt² over the Δt
    since its last observation (0 = no prior): the pixels decide where they constrain the pose;
    where they do not (a symmetric object's spin, texture smeared by motion blur) the object keeps
    its motion instead of drifting."""

    section: ClassVar[str] = "objects"
    track: bool = False
    source: str = setting("auto", choices=("auto", "dataset", "geometric"))
    min_pixels: int = setting(200, ge=16)
    levels: int = setting(2, ge=1, le=4)
    depth_smoothing: int = setting(1, ge=0, le=4)
    keyframe_overlap: float = setting(0.85, ge=0, le=1)
    keyframe_inliers: float = setting(0.5, ge=0, le=1)  # as the camera's tracking.reference_min_inliers
    min_iou: float = setting(0.2, gt=0, le=1)
    reid_distance: float = setting(0.25, gt=0)
    reid_size_ratio: float = setting(1.6, ge=1)
    max_gap_s: float = setting(0.2, gt=0)
    border_wait: int = setting(15, ge=0)
    accel_sigma: float = setting(4.0, ge=0)
    angular_accel_sigma: float = setting(30.0, ge=0)


@dataclass(frozen=True)
class ViewerConfig(Settings):
    """``viewer=rerun`` (:mod:`tivne.viewer`): a rerun recording of the run. sink: 'file' (run_dir/
    viewer.rrd, headless), 'spawn' (a local viewer window; needs a display) or 'serve' (gRPC on
    grpc_port for ``rerun --connect``, plus the web viewer on web_port; a viewer that connects late
    still gets what came before, up to server_memory_limit). image_every: colour / depth / mask /
    rendered images every n frames (null = output.image_every; 0 = never); rendered: also the
    colour and depth rendered at the estimated pose (a render of the frame, at render_stride);
    trajectory_every: re-log the trajectory line strips every n frames; map_points: at most this
    many points of the map at each mapping round (0 = none), map_every: every n-th mapping round."""

    section: ClassVar[str] = "viewer"
    kind: str = setting("none", choices=("none", "rerun"))
    sink: str = setting("file", choices=("file", "spawn", "serve"))
    image_every: int | None = setting(None, ge=0)
    rendered: bool = True
    render_stride: int = setting(2, ge=1)
    trajectory_every: int = setting(5, ge=1)
    map_points: int = setting(20000, ge=0)
    map_every: int = setting(5, ge=1)
    grpc_port: int = setting(9876, ge=1, le=65535)
    web_port: int = setting(9090, ge=1, le=65535)
    server_memory_limit: str = "1GiB"

    def check(self) -> None:
        if self.kind == "rerun" and importlib.util.find_spec("rerun") is None:
            raise ConfigError("viewer=rerun: rerun-sdk is not installed; pip install -e '.[viewer]'")


@dataclass(frozen=True)
class BackendConfig(Settings):
    """The keyframe pose graph (:mod:`tivne.slam.backend`). method: 'none' (keyframe poses are the
    tracked ones) or 'graph' (iSAM2 over keyframe poses; needs gtsam, the ``graph`` extra).
    Edges: each new keyframe is aligned by the dense odometry to its predecessor and to up to
    ``covisible`` more of the last ``loop_min_gap`` keyframes whose view it overlaps (share of its
    pixels reprojecting into theirs >= min_overlap). Loop closures: up to ``loop_candidates`` older
    keyframes within loop_max_distance_m / loop_max_angle_deg of it and overlapping, verified from a
    wider basin (loop_extra_levels more pyramid levels). An edge is kept when the odometry succeeds,
    its inlier ratio is >= min_inlier_ratio and it agrees with the current estimate within
    max_edge_m / max_edge_deg (loops: loop_max_correction_m / _deg). information_scale: factor on
    the odometry's JᵀWJ (it treats pixels as independent, which they are not); robust / robust_k:
    the kernel on the whitened error of every edge but the predecessor's. refit_iters: mapping
    steps over the keyframes a correction moved by more than refit_min_m (the stale part of the field)."""

    section: ClassVar[str] = "backend"
    method: str = setting("none", choices=("none", "graph"))
    covisible: int = setting(2, ge=0)
    min_overlap: float = setting(0.5, ge=0, le=1)
    loop_min_gap: int = setting(8, ge=2)
    loop_candidates: int = setting(1, ge=0)
    loop_max_distance_m: float = setting(0.5, gt=0)
    loop_max_angle_deg: float = setting(30.0, gt=0)
    loop_extra_levels: int = setting(1, ge=0, le=3)
    min_inlier_ratio: float = setting(0.6, ge=0, le=1)
    max_edge_m: float = setting(0.05, gt=0)
    max_edge_deg: float = setting(3.0, gt=0)
    loop_max_correction_m: float = setting(0.15, gt=0)
    loop_max_correction_deg: float = setting(8.0, gt=0)
    information_scale: float = setting(0.01, gt=0)
    robust: str = setting("cauchy", choices=("cauchy", "huber"))
    robust_k: float = setting(3.0, gt=0)
    refit_iters: int = setting(20, ge=0)
    refit_min_m: float = setting(0.01, ge=0)

    def check(self) -> None:
        if self.method == "graph" and importlib.util.find_spec("gtsam") is None:
            raise ConfigError("backend.method=graph needs gtsam, which is not installed: pip install 'tivne[graph]' (or pip install gtsam)")


@dataclass(frozen=True)
class ReportConfig(Settings):
    """``python -m tivne.report``: frames: how many processed frames (evenly spaced) the render / GT /
    depth-error contact sheet re-renders from the checkpoint (0 = none); render_stride: their pixel
    step; mesh_width: pixels across each mesh snapshot (two viewpoints per mesh time); mesh_faces:
    at most this many faces are rasterised per snapshot (the rest are dropped evenly, for speed)."""

    section: ClassVar[str] = "report"
    frames: int = setting(4, ge=0)
    render_stride: int = setting(2, ge=1)
    mesh_width: int = setting(480, ge=32)
    mesh_faces: int = setting(400_000, ge=1)
