"""The SLAM back end: a keyframe pose graph (``backend.method=graph``) on GTSAM's iSAM2.

* :mod:`~tivne.slam.backend.edges`: which keyframes a new one is aligned to (co-visibility by
  reprojection overlap, loop candidates by pose proximity and overlap), the dense alignment and
  the edge tests (odometry checks, inlier ratio, consistency with the chain);
* :mod:`~tivne.slam.backend.graph`: the factor graph (gtsam objects rebuilt from plain tensors);
* :mod:`~tivne.slam.backend.posegraph`: :class:`KeyframePoseGraph`, one call per new keyframe;
* :mod:`~tivne.slam.backend.apply`: corrected poses applied through a small interface, and the
  map made to follow them (allocation, re-fit of the moved keyframes).
"""

from __future__ import annotations

from tivne.config import BackendConfig, OdometryConfig


def make_backend(cfg: BackendConfig | None, odometry: OdometryConfig, readout_s: float = 0.0):
    """A :class:`~tivne.slam.backend.posegraph.KeyframePoseGraph` for ``backend.method=graph``
    (``readout_s``: the camera's rolling shutter, which its edges model), None for ``none``; an
    ImportError (one line, how to install gtsam) when gtsam is missing."""
    if cfg is None or cfg.method == "none":
        return None
    from tivne.slam.backend.posegraph import KeyframePoseGraph

    return KeyframePoseGraph(cfg, odometry, readout_s)
