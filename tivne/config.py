"""Every setting of the system, its default and its allowed values: the one source of both.

Each section of the Hydra config (``render``, ``tracking``, ``mapping``, ...) is a frozen dataclass
below. Its fields carry their range or choices (:func:`setting`), and :class:`Settings` checks them
when an instance is built, so a bad value anywhere -- a command-line override, a YAML file, a test
-- is refused with one line naming the key, the value and what is allowed (:class:`ConfigError`).
The YAML files under ``conf/`` only *choose* between presets; the defaults themselves come from here
(:func:`default_tree` turns these dataclasses into the base node that Hydra composes onto).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from data_modules.sensor import KINECT_SIGMA
from tivne.config_optional import BackendConfig, ObjectFieldConfig, ObjectsConfig, ReportConfig, ViewerConfig
from tivne.settings import ConfigError, Settings, default_tree, setting

__all__ = ["ConfigError", "Settings", "default_tree", "setting", "SECTIONS", "BackendConfig", "ObjectFieldConfig", "ObjectsConfig",
           "ReportConfig", "ViewerConfig"]


# ------------------------------------------------------------------------------------------------
# The sections
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RuntimeConfig(Settings):
    """threads: torch threads (null = torch's default, all cores; conf/config.yaml sets it per job
    under a parallel launcher, :func:`tivne.cli.threads_per_job`). tune_allocator: glibc mallopt keeps
    activations in the heap (measured 1.1-3x faster optimiser steps on CPU)."""

    section: ClassVar[str] = "runtime"
    threads: int | None = setting(None, ge=1)
    tune_allocator: bool = True


@dataclass(frozen=True)
class FieldConfig(Settings):
    """The time-varying field (paper §III-A). time=false is the "w/o time" ablation (Vox-Fusion-like
    static field on the same code path). voxel_size in metres; embed_dim = Q; capacity / max_capacity:
    initial and hard cap of embedding rows; time_scale: τ = (t - t0)·time_scale with t in seconds;
    offset_ramp: Δe gated by tanh(τ / ramp), exactly 0 at τ = 0; canonical_time: feed τ to Θs too (the paper does;
    off, a time input extrapolates at unseen τ and moves the static map); surface_cell: record the
    cells of this size (metres) that held static depth, for ``mesh.near_surface`` (0 = no record)."""

    section: ClassVar[str] = "field"
    name: str = "tivne"
    time: bool = True
    voxel_size: float = setting(0.1, gt=0)
    embed_dim: int = setting(16, ge=1)
    capacity: int = setting(20000, ge=1)
    max_capacity: int = setting(2_000_000, ge=1)
    init_std: float = setting(0.01, ge=0)
    hidden_dim: int = setting(64, ge=1)
    num_hidden: int = setting(3, ge=1)
    time_frequencies: int = setting(4, ge=0)
    time_lowest_octave: int = setting(0, ge=-16, le=16)
    time_scale: float = setting(1.0, gt=0)
    offset_ramp: float = setting(0.1, gt=0)
    canonical_time: bool = False
    surface_cell: float = setting(0.02, ge=0)


@dataclass(frozen=True)
class RenderConfig(Settings):
    """Where samples go along a ray and how sharp the surface is. truncation: tr in metres (SDF band
    and bell width); samples span D ± band·tr (n_band of them) plus n_free in free space in front;
    near: closest depth; chunk: rays per forward pass when rendering whole images. n_band 8 (was 12):
    11-16 % less time per frame on the cube and both real tails with the same camera ATE and real-data
    PSNR, the synthetic scenes' geometry and object figures within 0.2 cm, their PSNR 0.0-0.4 dB lower
    (experiment=quality keeps 12)."""

    section: ClassVar[str] = "render"
    truncation: float = setting(0.05, gt=0)
    band: float = setting(2.0, gt=0)
    n_band: int = setting(8, ge=1)
    n_free: int = setting(4, ge=0)
    near: float = setting(0.05, ge=0)
    chunk: int = setting(8192, ge=1)


@dataclass(frozen=True)
class LossWeights(Settings):
    """λ of each loss term (paper Eq. 6). colour 5 (Co-SLAM's value: Vox-Fusion's 0.5 left colour
    unlearnt here, L1 0.15 vs 0.05); offset ‖Δe‖² on background samples."""

    section: ClassVar[str] = "loss"
    color: float = setting(5.0, ge=0)
    depth: float = setting(1.0, ge=0)
    free_space: float = setting(10.0, ge=0)
    sdf: float = setting(5000.0, ge=0)
    offset: float = setting(0.1, ge=0)

    def without_offset(self) -> "LossWeights":
        return dataclasses.replace(self, offset=0.0)


@dataclass(frozen=True)
class TrackingConfig(Settings):
    """The tracking front end (:mod:`tivne.slam.tracking`). method: 'odometry' (RGB-D odometry against
    a reference frame), 'odometry+field' (refined by the field tracker, section ``field_tracking``) or
    'field' (the paper's tracker alone). reference: the odometry's reference frame -- 'keyframe' (every
    mapping keyframe), 'frame' (the previous frame) or 'adaptive' (only when the overlap or inlier
    ratio with the reference falls below reference_min_overlap / reference_min_inliers, which also
    apply to the other two). motion_model: the initial pose, 'zero' (paper) or 'constant_velocity'
    (from the trajectory's last two poses). min_static_pixels: a frame with fewer static pixels with
    depth is not tracked and not mapped. Lost: the odometry and its wider-basin retry fail, the field tracker
    alone keeps < ``field_tracking.min_inlier_ratio`` of its rays, or the pose lands > max_jump_m / max_jump_deg
    from the prediction; a lost frame is reported, never mapped, and bridged between the tracked frames around
    it once the next one is tracked (``Trajectory.bridge_lost``).
    overlap: track the next frame in a worker thread (overlap_threads OpenMP threads of its own)
    while the current one is mapped, where the order changes nothing (method 'odometry', which does
    not read the map, and ``mapping.optimize_poses`` off): the same poses and map in less wall time
    on a CPU, since the odometry's many small operations barely use a second core.
    stored_references: past references kept; a stale reference is replaced by the oldest stored one
    within reuse_max_m / reuse_max_deg of the frame that sees reuse_min_overlap of it (verified by an
    alignment keeping that overlap and reference_min_inliers), else by the frame: a camera back at a
    view drops the drift of the references in between. joint_references: stored references seeing
    the predicted view (overlap >= reference_min_overlap, within reuse_max_deg) aligned jointly with
    the reference at the finest level (0 = the reference alone)."""

    section: ClassVar[str] = "tracking"
    method: str = setting("odometry", choices=("odometry", "odometry+field", "field"))
    reference: str = setting("adaptive", choices=("adaptive", "keyframe", "frame"))
    reference_min_overlap: float = setting(0.7, ge=0, le=1)
    reference_min_inliers: float = setting(0.5, ge=0, le=1)
    max_jump_m: float = setting(0.3, gt=0)
    max_jump_deg: float = setting(30.0, gt=0)
    motion_model: str = setting("constant_velocity", choices=("zero", "constant_velocity"))
    min_static_pixels: int = setting(512, ge=1)
    overlap: bool = True
    overlap_threads: int = setting(1, ge=1)
    stored_references: int = setting(8, ge=1)
    reuse_max_m: float = setting(0.1, ge=0)
    reuse_max_deg: float = setting(15.0, ge=0)
    reuse_min_overlap: float = setting(0.85, ge=0, le=1)
    joint_references: int = setting(2, ge=0)

    @property
    def reads_map(self) -> bool:
        """Whether tracking reads the map (the field tracker alone or after the odometry): then the
        first frame's map is whole before frame 1, and no track overlaps a mapping round."""
        return self.method != "odometry"


@dataclass(frozen=True)
class FieldTrackingConfig(Settings):
    """The paper's field tracker (:func:`tivne.slam.tracking.field.track_frame`; ``tracking.method``
    'field' or 'odometry+field'): iters optimiser steps per frame over ``rays`` pixels (one fixed set
    per frame, so the best-loss iterate is comparable). outlier_factor: rays with depth residual >
    factor x median are dropped (0 disables). exclude_dynamic: draw no tracking rays from masked
    pixels. query_time: 'last_mapped' renders the map at the latest time it was trained on (moving
    pixels become outliers), 'frame' at the frame's own τ. stratified: jitter samples each iteration
    (off: the loss is a deterministic function of the pose, so the best iterate is not chosen by
    sampling noise). lr_final_factor: the learning rate decays exponentially to this fraction over
    the iterations. min_inlier_ratio: with ``tracking.method=field``, a frame keeping fewer of its
    rays is lost."""

    section: ClassVar[str] = "field_tracking"
    iters: int = setting(30, ge=1)
    rays: int = setting(512, ge=1)
    lr_rot: float = setting(2e-3, gt=0)
    lr_trans: float = setting(2e-3, gt=0)
    outlier_factor: float = setting(10.0, ge=0)
    keep_best: bool = True
    exclude_dynamic: bool = True
    query_time: str = setting("last_mapped", choices=("last_mapped", "frame"))
    stratified: bool = False
    lr_final_factor: float = setting(0.1, gt=0, le=1)
    min_inlier_ratio: float = setting(0.3, ge=0, le=1)


@dataclass(frozen=True)
class OdometryConfig(Settings):
    """Dense RGB-D odometry (:func:`tivne.slam.tracking.odometry.track_pyramids`; ``tracking.method=odometry``) (noise-model based defaults, not tuned to one sequence).

    levels: pyramid levels (1 = full resolution only). max_iterations: Gauss–Newton iterations per level. photometric / geometric: which
    residual terms enter. robust: "huber" (k 1.345) or "cauchy" (k 2.3849) kernel on the normalised residuals. depth_sigma: (a, b, z0)
    of σ(z). intensity_sigma_min: floor of the photometric scale (1/255, one 8-bit step). brightness_offset: subtract the median
    photometric residual (a global exposure change). photometric_depth_noise: add the current depth's noise, seen through the image
    gradient, to each photometric σ. colour_parallax_m: the colour–depth baseline that the colour registration leaves out; colour at
    depth z then lies f·b·|1/z − 1/z̃| pixels off (z̃ the frame's median depth, where a fitted colour camera is exact), added to each
    photometric σ through the gradient. null: 0.025, the Kinect's RGB–IR baseline, for colour remapped by dataset.colour_camera without
    dataset.colour_offset (7-Scenes tail ATE 2.674 -> 2.170 cm), else 0 (registered colour, or the offset modelled). photometric_weight:
    an extra factor on the photometric information (1 = the noise scales alone decide). geometric_scale: "data" (σ(z) shapes the
    per-pixel point-to-plane weights, the MAD of the residuals sets the overall scale, at least depth_quantum metres, as for the
    photometric term) or "model" (scale ≥ σ(z)). outlier_sigmas: a pair whose depth difference exceeds this many robust σ is rejected
    (occlusion, another surface). max_normal_angle_deg: reject point-to-plane pairs whose normals disagree more. min_depth, max_depth:
    usable depth range in metres. tol_pixels: a level stops when the update moves the image by less than this many of its pixels (|w|·f
    + |v|·f/z̄, z̄ the median depth); stall_pixels: or by less than this without shrinking. damping: Levenberg–Marquardt λ relative to
    diag(H). max_points: at most about this many current pixels at the finest level (one in each k x k tile; 0 = all): past a few ten
    thousand, systematic errors limit it, not the count. pick: which pixel of a tile, "grid" (its corner), "gradient" (its strongest
    intensity gradient: pyramid.pick_pixels) or "split" (photometric on the gradient's pixels, point-to-plane on the grid's).
    coarse_points_ratio: each coarser level takes this many times fewer; 2 is 10-22 % faster on the real tails, loses a whipping camera.
    inlier_sigmas: a usable pair is an inlier when its depth difference is within this many σ_pair of the sensor model.
    min_correspondences, min_overlap, min_inlier_ratio, max_pose_std: what OdometryResult.ok needs. depth_filter: pyramid.filter_depth."""

    section: ClassVar[str] = "odometry"
    levels: int = setting(3, ge=1, le=6)
    max_iterations: int = setting(20, ge=1)
    photometric: bool = True
    geometric: bool = True
    robust: str = setting("huber", choices=("huber", "cauchy"))
    depth_sigma: tuple[float, ...] = setting(list(KINECT_SIGMA), ge=0)
    intensity_sigma_min: float = setting(1.0 / 255.0, gt=0)
    brightness_offset: bool = True
    photometric_depth_noise: bool = True
    colour_parallax_m: float | None = setting(None, ge=0)
    photometric_weight: float = setting(1.0, ge=0)
    geometric_scale: str = setting("data", choices=("data", "model"))
    depth_quantum: float = setting(0.0002, gt=0)
    outlier_sigmas: float = setting(5.0, gt=0)
    max_normal_angle_deg: float = setting(30.0, gt=0, le=90)
    min_depth: float = setting(0.2, ge=0)
    max_depth: float = setting(6.0, gt=0)
    tol_pixels: float = setting(0.05, gt=0)
    stall_pixels: float = setting(0.25, ge=0)
    damping: float = setting(1e-4, ge=0)
    max_points: int = setting(20000, ge=0)
    coarse_points_ratio: float = setting(1.0, ge=1)
    inlier_sigmas: float = setting(3.0, gt=0)
    min_correspondences: int = setting(64, ge=6)
    min_overlap: float = setting(0.3, ge=0, le=1)
    min_inlier_ratio: float = setting(0.3, ge=0, le=1)
    max_pose_std: float = setting(0.01, gt=0)
    brightness_gain: bool = False  # #20: also a contrast gain (MAD ratio) before the brightness offset
    depth_filter: bool = False  # #20: bilateral filter of inverse depth before the pyramid (KinectFusion)
    pick: str = setting("grid", choices=("grid", "gradient", "split"))

    def check(self) -> None:
        if not (self.photometric or self.geometric):
            raise ConfigError("odometry.photometric=false and odometry.geometric=false: enable at least one term")
        if len(self.depth_sigma) != 3:
            raise ConfigError(f"odometry.depth_sigma={list(self.depth_sigma)}: must be [a, b, z0] of sigma(z) = a + b (z - z0)^2")
        if self.max_depth <= self.min_depth:
            raise ConfigError(f"odometry.max_depth={self.max_depth}: must be > odometry.min_depth ({self.min_depth})")


@dataclass(frozen=True)
class MappingConfig(Settings):
    """iters: steps per mapping round of a frame with moving pixels; static_iters: of a frame without (the static map gathers over many
    frames, a moving object at each time has its own): both real tails at 3 instead of 5 ran 15-20 % faster, same ATE, PSNR -0.03 /
    +0.4 dB (the final pass, a share of the online steps, shrinks with them). first_iters: steps the first frame's map gets in all,
    first_now of them on the first frame alone (so it returns in about a second), the rest added to the next rounds, at most iters
    more each; only with ``tracking.method=odometry``, which does not read the map (else all first_iters at once). rays per step,
    current_share of them from the current frame, the rest split over the picked keyframes. every: map every n-th frame. Every frame
    mapped (5 steps where objects move): each frame's track overlaps a mapping round (``tracking.overlap``); 5 instead of 10 steps
    took 30-55 % off s/frame (scene family, cube, real tails) with the same camera ATE, object Chamfer within 0.1 cm but for the
    breathing blob's first mesh (1.1 -> 1.5 cm), PSNR 0.3-0.9 dB lower (``experiment=quality`` takes 20). threads: torch's threads
    for the steps (null: the process's): a step is a few hundred small ops, each a parallel region whose waking threads cost more
    than they share, and the next frame's track wants a core of its own. optimize_poses: refine the window's poses (never the first
    frame's; on, 20 Adam steps per round added noise here: 2.6 vs 1.0 cm peak error over 40 frames). The final pass: after the
    sequence, steps over the whole keyframe set (windows of final_window keyframes, poses fixed), because the online window rarely
    revisits early and middle times: final_share of the steps mapping took online, at most final_iters (so it stays a small part of
    the run; 0 = off). Adaptive rounds (settle_share > 0): a round whose current frame the map explains (at its first step,
    settle_share of its rays render a depth within settle_sigmas σ(z), the Kinect noise, of the measured one) stops after
    settle_iters steps. Off: iters=10 settled at 5 gave the breathing blob a better first mesh (1.3 vs 1.5 cm at 5 steps) but few
    rounds settle where objects move or depth is real (s/frame cube 0.128 -> 0.186, fr1 tail 0.093 -> 0.144, same ATE)."""

    section: ClassVar[str] = "mapping"
    iters: int = setting(5, ge=1)
    static_iters: int = setting(3, ge=1)
    first_iters: int = setting(200, ge=0)  # 40 in all: first frame ~6x cheaper, but a 40-frame cube's first mesh 1.15 vs 0.59 cm
    first_now: int = setting(30, ge=0)
    rays: int = setting(512, ge=1)
    current_share: float = setting(0.5, gt=0, le=1)
    lr_embeddings: float = setting(1e-2, gt=0)
    lr_decoder: float = setting(5e-3, gt=0)
    lr_pose: float = setting(5e-4, gt=0)
    optimize_poses: bool = False
    every: int = setting(1, ge=1)
    final_iters: int = setting(300, ge=0)
    final_share: float = setting(0.1, ge=0)
    final_window: int = setting(8, ge=1)
    settle_share: float = setting(0.0, ge=0, le=1)
    settle_sigmas: float = setting(3.0, gt=0)
    settle_iters: int = setting(5, ge=1)
    threads: int | None = setting(1, ge=1)


@dataclass(frozen=True)
class KeyframeConfig(Settings):
    """policy 'overlap' (paper Eq. 11): the keyframes with the lowest reprojection overlap with the
    current frame among those overlapping it (ratio > min_overlap), measured on overlap_pixels
    sampled pixels; 'random': uniformly at random (Vox-Fusion). A keyframe every ``every`` frames,
    ``window`` of them per mapping round. max_stored: keyframes kept in memory; when full, the one whose
    removal leaves the smallest gap in time is dropped (the sequence stays covered, more sparsely), so
    memory stops growing with the sequence (a 640x480 keyframe: uint8 colour, float32 depth and its mask, about 2.5 MB)."""

    section: ClassVar[str] = "keyframe"
    policy: str = setting("overlap", choices=("overlap", "random"))
    every: int = setting(5, ge=1)
    window: int = setting(4, ge=1)
    overlap_pixels: int = setting(256, ge=1)
    min_overlap: float = setting(0.0, ge=0, lt=1)
    max_stored: int = setting(250, ge=3)


@dataclass(frozen=True)
class SamplerConfig(Settings):
    """Mapping's pixel sampler: dynamic_share of the rays from dynamic (masked) pixels; 0 = uniform, mask_weighted over-samples
    moving objects so the field learns them from the few pixels they cover. mask_edge: no ray from a pixel within this many pixels
    of a motion mask's edge (either side), where depth and colour mix an object with what is behind it (0: off; 1 was mixed).
    label_edge: rays within this many pixels of it regress the composition's SDF, not the part their label names
    (:func:`tivne.render.losses.routed_sdf`; ``field=objects`` with masks): there depth jitter mixes the labels."""

    section: ClassVar[str] = "sampler"
    name: str = "mask_weighted"
    dynamic_share: float = setting(0.3, ge=0, le=1)
    mask_edge: int = setting(0, ge=0)
    label_edge: int = setting(2, ge=0)


@dataclass(frozen=True)
class MeshConfig(Settings):
    """Meshes (train, ``tivne.mesh`` and ``tivne.evaluate`` share these keys). times: seconds on the sequence clock (empty = the
    first and last frame); resolution: marching-cubes step in metres. Observed space only (:class:`tivne.meshing.MeshCulling`):
    min_hits: voxels that held static depth in >= n frames (0: also the unobserved dilation shell); dynamic_window: ... or where a
    moving object was seen at the observations just before and just after the mesh time, each within this many seconds (null:
    never; the union of a whole window would show its path); near_surface: drop faces farther than one ``field.surface_cell`` from
    any observed static depth point, unless on a moving object seen then (the field is unsupervised past the sampled band behind a
    surface and makes surfaces up there, inside observed voxels); backfaces: drop faces no camera saw from their free side
    (surfaces behind the supervised band). carve_window: ``field=objects``' static mesh at t loses the faces that the stored
    keyframes within this many seconds of t see past (:func:`tivne.meshing.carve_free_space`; null: off)."""

    section: ClassVar[str] = "mesh"
    times: tuple[float, ...] = setting([])
    resolution: float = setting(0.02, gt=0)
    min_hits: int = setting(1, ge=0)
    dynamic_window: float | None = setting(0.2, ge=0)
    near_surface: bool = True
    backfaces: bool = True
    carve_window: float | None = setting(0.25, ge=0)


@dataclass(frozen=True)
class OutputConfig(Settings):
    """image_every: log rendered images every n frames (0 = never). save_every: rewrite
    trajectory.txt every n frames, so an interrupted run keeps its poses (0 = only at the end).
    checkpoint_every: write the whole state of the run (map, optimiser, keyframes, poses, tracker,
    masks, RNGs, position) to checkpoints/slam.pt every n frames and before the final pass, so a
    crashed run continues from there with ``resume=true`` (0 = only at the end and on SIGINT /
    SIGTERM; each one costs a write of the stored keyframes). evaluate: compute the mesh metrics against the dataset's GT
    geometry at the end (where it has one)."""

    section: ClassVar[str] = "output"
    image_every: int = setting(50, ge=0)
    save_every: int = setting(25, ge=0)
    checkpoint_every: int = setting(50, ge=0)
    evaluate: bool = True


@dataclass(frozen=True)
class AllocationConfig(Settings):
    """Where the map grows (:class:`tivne.slam.allocation.VoxelAllocator`): voxels are allocated where
    every ``stride``-th pixel's depth lands (on both axes), and ``dilation`` voxels around them."""

    section: ClassVar[str] = "allocation"
    stride: int = setting(4, ge=1)
    dilation: int = setting(1, ge=0)


@dataclass(frozen=True)
class MeshEvalSettings(Settings):
    """Knobs of the evaluation against ground truth (``tivne.evaluate``'s ``settings``; sample counts
    trade time for the estimates' noise; definitions in :mod:`tivne.evaluation.surfaces`).

    threshold_m: completion-ratio and ghost distance. object_margin_m: dilation of a moving object's
    GT box; the mesh inside counts as that object. window_s: a moving object's surface counts as
    observed at mesh time t when a camera saw it within ± this many seconds of t (completion is
    judged on that part). pred_samples: samples on the whole mesh; object_samples: on the mesh near
    each object and on each object's GT surface; static_samples: on the GT static surface.
    render_every: re-render every k-th processed frame for PSNR / SSIM (0 = no image metrics);
    render_stride: every n-th pixel of those frames.

    Distances to the mesh are distances to area-uniform samples on it, so a completion ratio at
    ``threshold_m`` is only exact when a disc of that radius holds several samples: 200k samples on
    a ~60 m^2 room give ~26 per 5 cm disc (a miss probability of e^-26).
    """

    section: ClassVar[str] = "settings"
    threshold_m: float = setting(0.05, gt=0)
    object_margin_m: float = setting(0.05, ge=0)
    window_s: float = setting(0.5, ge=0)
    pred_samples: int = setting(200_000, ge=1)
    object_samples: int = setting(50_000, ge=1)
    static_samples: int = setting(100_000, ge=1)
    render_every: int = setting(10, ge=0)
    render_stride: int = setting(2, ge=1)
    seed: int = setting(0, ge=0)


@dataclass(frozen=True)
class RunDirConfig(Settings):
    """What ``tivne.train`` does with a run directory (``hydra.run.dir``) that already holds results
    (trajectory.txt, metrics.json, checkpoints/, meshes/, renders/): refuse it (default), continue
    it from its last checkpoint (resume=true; the config must be the same) or clear those results
    first (overwrite=true). Top-level keys: ``resume=true``, not ``run_dir.resume``."""

    section: ClassVar[str] = ""
    resume: bool = False
    overwrite: bool = False

    def check(self) -> None:
        if self.resume and self.overwrite:
            raise ConfigError("resume=true and overwrite=true: choose one (resume continues the run, overwrite clears it)")


@dataclass(frozen=True)
class TrainerConfig(Settings):
    """accelerator: cpu, gpu/cuda (one CUDA device) or auto; progress_bar: Lightning's bar in a
    terminal; when stdout is not one (a file, CI), one plain line every log_every frames instead
    (:class:`tivne.viewer.progress.PlainProgress`)."""

    section: ClassVar[str] = "trainer"
    accelerator: str = setting("cpu", choices=("cpu", "gpu", "cuda", "auto"))
    devices: int = setting(1, ge=1, le=1)
    progress_bar: bool = True
    log_every: int = setting(10, ge=1)


@dataclass(frozen=True)
class ObjectiveConfig(Settings):
    """What ``python -m tivne.train`` returns, the value a sweeper (``hydra/sweeper=optuna``) minimises.
    metric: 'ate' (ate_rmse_m), 'chamfer' (object_chamfer_mean_m: needs output.evaluate and a dataset
    with GT geometry), 's_per_frame', or 'weighted' = ate_weight·ate_rmse_m + chamfer_weight·
    object_chamfer_mean_m + time_weight·s_per_frame (a term of weight 0 is left out, so its metric may
    be missing; the defaults count 1 cm of either error like 1 s/frame). A metric the run could not
    compute is never replaced by a number: the command returns nothing and the trial fails."""

    section: ClassVar[str] = "objective"
    metric: str = setting("ate", choices=("ate", "chamfer", "s_per_frame", "weighted"))
    ate_weight: float = setting(100.0, ge=0)
    chamfer_weight: float = setting(100.0, ge=0)
    time_weight: float = setting(1.0, ge=0)

    def check(self) -> None:
        if self.metric == "weighted" and self.ate_weight == self.chamfer_weight == self.time_weight == 0:
            raise ConfigError("objective.metric=weighted: every weight is 0; give at least one term a weight > 0")


SECTIONS: tuple[type[Settings], ...] = (
    RuntimeConfig, FieldConfig, ObjectFieldConfig, RenderConfig, LossWeights, TrackingConfig, FieldTrackingConfig, OdometryConfig,
    MappingConfig, KeyframeConfig, SamplerConfig, MeshConfig, OutputConfig, AllocationConfig, TrainerConfig, ObjectiveConfig,
    RunDirConfig, ObjectsConfig, ViewerConfig, BackendConfig,
)
