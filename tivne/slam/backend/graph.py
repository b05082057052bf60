"""Keyframe pose graph on GTSAM's iSAM2: poses c2w of keyframes, relative-pose factors between them.

The graph's own state is plain tensors (nodes, factors); the gtsam objects are built from them, so
a checkpoint holds no gtsam object and :meth:`PoseGraph.load_state_dict` rebuilds the solver.

Tangent conventions. The odometry's information matrix H is for the twist δ = (v, w) of a LEFT
perturbation T ← exp(δ) T of T_ref_cur (:class:`tivne.slam.tracking.odometry.OdometryResult`); GTSAM's
``BetweenFactorPose3`` measures the error e = Log(T̂⁻¹ · X_ref⁻¹ X_cur) on the RIGHT, ordered
(ω, v). With T = exp(δ) T̂, e = Ad(T̂⁻¹) δ, so Λ_e = Ad(T̂)ᵀ H Ad(T̂) ((v, w) order), then reordered.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from tivne.geometry import adjoint_vw
from tivne.settings import ConfigError

GRAPH_MISSING = "backend.method=graph needs gtsam, which is not installed: pip install 'tivne[graph]' (or pip install gtsam)"


def require_gtsam():
    """The gtsam module, or a one-line :class:`ConfigError` saying how to install it."""
    try:
        import gtsam
    except ImportError:
        raise ConfigError(GRAPH_MISSING) from None
    return gtsam


def left_to_gtsam_information(H: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Information (6, 6) of a left twist (v, w) on T (4, 4) -> of GTSAM's right twist (ω, v) on T."""
    H, T = H.double().cpu(), T.double().cpu()
    Ad = adjoint_vw(T)
    L = Ad.T @ H @ Ad
    order = [3, 4, 5, 0, 1, 2]
    L = L[order][:, order]
    return 0.5 * (L + L.T)


@dataclass(frozen=True)
class Factor:
    """A relative-pose measurement between keyframes ``ref`` and ``cur`` (frame ids):
    c2w_cur = c2w_ref @ measured (4, 4); information (6, 6) in GTSAM's (ω, v) right tangent;
    robust: under the robust kernel (every measurement but the chain's)."""

    ref: int
    cur: int
    measured: torch.Tensor
    information: torch.Tensor
    robust: bool
    loop: bool = False


def to_pose3(gtsam, T: torch.Tensor):
    return gtsam.Pose3(np.ascontiguousarray(T.detach().double().cpu().numpy()))


class PoseGraph:
    """iSAM2 over keyframe poses (c2w, float64); the first node is held by a tight prior."""

    PRIOR_SIGMA = 1e-6  # the first keyframe defines the SLAM world frame

    def __init__(self, robust: str = "cauchy", robust_k: float = 1.0, relinearize_threshold: float = 1e-5) -> None:
        self.gtsam = require_gtsam()
        self.robust, self.robust_k, self.relinearize_threshold = robust, float(robust_k), float(relinearize_threshold)
        self.nodes: dict[int, torch.Tensor] = {}  # frame id -> initial pose (4, 4) float64
        self.factors: list[Factor] = []
        self.optimise_ms = 0.0
        self._reset_solver()

    def _reset_solver(self) -> None:
        g = self.gtsam
        params = g.ISAM2Params()
        params.setRelinearizeThreshold(self.relinearize_threshold)
        params.relinearizeSkip = 1
        self.isam = g.ISAM2(params)
        self._graph, self._values = g.NonlinearFactorGraph(), g.Values()
        self._estimate: dict[int, torch.Tensor] = {}

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self.nodes

    def add_node(self, frame_id: int, pose: torch.Tensor) -> None:
        """A keyframe at its initial (tracked) c2w pose (4, 4); the first one gets the prior."""
        pose = pose.detach().double().cpu()
        self.nodes[int(frame_id)] = pose
        self._values.insert(int(frame_id), to_pose3(self.gtsam, pose))
        if len(self.nodes) == 1:
            noise = self.gtsam.noiseModel.Isotropic.Sigma(6, self.PRIOR_SIGMA)
            self._graph.add(self.gtsam.PriorFactorPose3(int(frame_id), to_pose3(self.gtsam, pose), noise))

    def add_factor(self, factor: Factor) -> None:
        self.factors.append(factor)
        self._graph.add(self._between(factor))

    def _between(self, f: Factor):
        g = self.gtsam
        noise = g.noiseModel.Gaussian.Information(np.ascontiguousarray(f.information.double().numpy()))
        if f.robust:
            kernel = (g.noiseModel.mEstimator.Cauchy if self.robust == "cauchy" else g.noiseModel.mEstimator.Huber).Create(self.robust_k)
            noise = g.noiseModel.Robust.Create(kernel, noise)
        return g.BetweenFactorPose3(int(f.ref), int(f.cur), to_pose3(g, f.measured), noise)

    def optimise(self, extra_iterations: int = 2) -> dict[int, torch.Tensor]:
        """Feed the pending nodes / factors to iSAM2 (plus a few relinearising updates, which a
        closure needs to converge); returns every node's pose (4, 4) float64."""
        start = time.perf_counter()
        self.isam.update(self._graph, self._values)
        for _ in range(extra_iterations):
            self.isam.update()
        self._graph, self._values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
        est = self.isam.calculateEstimate()
        self._estimate = {i: torch.from_numpy(est.atPose3(i).matrix().copy()) for i in self.nodes}
        self.optimise_ms += 1000 * (time.perf_counter() - start)
        return dict(self._estimate)

    def estimate(self) -> dict[int, torch.Tensor]:
        """The last optimised poses (nodes added since: their initial pose)."""
        return {i: self._estimate.get(i, p) for i, p in self.nodes.items()}

    def whitened_error(self, factor: Factor, poses: dict[int, torch.Tensor]) -> float:
        """sqrt(eᵀ Λ e) of ``factor`` at ``poses`` (without the robust kernel)."""
        g = self.gtsam
        between = to_pose3(g, poses[factor.ref]).between(to_pose3(g, poses[factor.cur]))
        e = torch.from_numpy(g.Pose3.Logmap(to_pose3(g, factor.measured).between(between)))
        return float((e @ factor.information.double() @ e).clamp_min(0).sqrt())

    # ---- checkpoint: plain tensors only --------------------------------------------------------
    def state_dict(self) -> dict:
        ids = list(self.nodes)
        est = self.estimate()
        stack = lambda xs, shape: torch.stack(xs) if xs else torch.zeros(0, *shape, dtype=torch.float64)  # noqa: E731
        return {
            "ids": ids,
            "initial": stack([self.nodes[i] for i in ids], (4, 4)),
            "estimate": stack([est[i] for i in ids], (4, 4)),
            "ref": [f.ref for f in self.factors], "cur": [f.cur for f in self.factors],
            "measured": stack([f.measured.double() for f in self.factors], (4, 4)),
            "information": stack([f.information.double() for f in self.factors], (6, 6)),
            "robust": [bool(f.robust) for f in self.factors], "loop": [bool(f.loop) for f in self.factors],
            "optimise_ms": float(self.optimise_ms),
        }

    def load_state_dict(self, state: dict) -> None:
        """Rebuild nodes, factors and the solver (linearised at the saved estimate)."""
        self._reset_solver()
        self.nodes, self.factors = {}, []
        for i, initial in zip(state["ids"], state["initial"]):
            self.add_node(int(i), initial.double().cpu())
        fields = zip(state["ref"], state["cur"], state["measured"], state["information"], state["robust"], state["loop"])
        for ref, cur, T, info, robust, loop in fields:
            self.add_factor(Factor(int(ref), int(cur), T.double().cpu(), info.double().cpu(), bool(robust), bool(loop)))
        self._values = self.gtsam.Values()
        for i, pose in zip(state["ids"], state["estimate"]):
            self._values.insert(int(i), to_pose3(self.gtsam, pose.double().cpu()))
        if self.nodes:
            self.optimise(extra_iterations=0)
        # the run continues from the saved estimate (the solver's relinearised one differs by its last step)
        self._estimate = {int(i): pose.double().cpu() for i, pose in zip(state["ids"], state["estimate"])}
        self.optimise_ms = float(state["optimise_ms"])
