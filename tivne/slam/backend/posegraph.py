"""The back end of ``backend.method=graph``: every new keyframe becomes a node of the pose graph,
with edges to the keyframes it overlaps and, when one verifies, a loop closure; iSAM2 then returns
every keyframe's corrected pose (:class:`KeyframePoseGraph.add_keyframe`)."""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass
from typing import Any

import torch

from tivne.config import BackendConfig, OdometryConfig
from tivne.geometry import invert_pose
from tivne.render.rays import View
from tivne.slam.backend.edges import Alignment, align, covisible_candidates, keyframe_pyramid, loop_candidates
from tivne.slam.backend.graph import Factor, PoseGraph, left_to_gtsam_information
from tivne.slam.tracking.pyramid import PyramidLevel
from tivne.slam.tracking.sensor import Shutter, frame_shutters


@dataclass
class GraphCounters:
    """For metrics.json: keyframes in the graph, edges in it (chain included), chain edges that fell
    back to the tracked relative pose, co-visible edges rejected, loop closures accepted / rejected,
    iSAM2 time (ms, all updates), and the largest correction of a keyframe so far (m)."""

    keyframes: int = 0
    edges: int = 0
    chain_fallbacks: int = 0
    covisible_rejected: int = 0
    loops_accepted: int = 0
    loops_rejected: int = 0
    optimise_ms: float = 0.0
    align_ms: float = 0.0
    max_correction_m: float = 0.0
    refit_rounds: int = 0


def fallback_information(cfg: BackendConfig) -> torch.Tensor:
    """(6, 6) diagonal information, GTSAM (ω, v) order, of a chain edge the odometry could not
    measure: σ = max_edge_deg (rotation) and max_edge_m (translation), so other edges dominate it."""
    rot, trans = 1.0 / math.radians(cfg.max_edge_deg) ** 2, 1.0 / cfg.max_edge_m**2
    return torch.diag(torch.tensor([rot] * 3 + [trans] * 3, dtype=torch.float64))


class KeyframePoseGraph:
    """Keyframe pose graph with co-visibility edges and loop closures (see :mod:`tivne.slam.backend`)."""

    def __init__(self, cfg: BackendConfig, odometry: OdometryConfig, readout_s: float = 0.0) -> None:
        """``readout_s``: the camera's rolling-shutter readout (:class:`Shutter`; 0 = global shutter)."""
        self.cfg, self.odometry, self.readout_s = cfg, odometry, readout_s
        self.velocities: dict[int, torch.Tensor] = {}  # frame id -> (6,) the keyframe camera's velocity, where tracked with it
        self.graph = PoseGraph(cfg.robust, cfg.robust_k)
        self.counters = GraphCounters()
        self.closures: list[tuple[int, int]] = []  # (old, new) frame ids of the accepted loop closures
        self._pyramids: OrderedDict[int, tuple[tuple, list[PyramidLevel]]] = OrderedDict()

    def _pyramid(self, view: View, K: torch.Tensor) -> list[PyramidLevel]:
        """The keyframe's pyramid, rebuilt when its dynamic mask changed (a small LRU of recent ones)."""
        mask = view.dynamic
        key = (None,) if mask is None else (id(mask), int(mask.sum()))
        cached = self._pyramids.get(view.frame_id)
        if cached is not None and cached[0] == key:
            self._pyramids.move_to_end(view.frame_id)
            return cached[1]
        pyramid = keyframe_pyramid(view, K, self.odometry, self.cfg)
        self._pyramids[view.frame_id] = (key, pyramid)
        while len(self._pyramids) > self.cfg.loop_min_gap + 1:
            self._pyramids.popitem(last=False)
        return pyramid

    def _factor(self, a: Alignment, robust: bool, loop: bool) -> Factor:
        info = left_to_gtsam_information(a.result.information, a.result.T_ref_cur) * self.cfg.information_scale
        return Factor(a.ref, a.cur, a.result.T_ref_cur.double().cpu(), info, robust, loop)

    def add_keyframe(self, views: list[View], K: torch.Tensor, velocity: torch.Tensor | None = None) -> dict[int, torch.Tensor]:
        """``views``: the stored keyframes, oldest first, the new one last (at its tracked pose);
        ``velocity``: the new one's camera velocity (6,) (:attr:`TrackResult.velocity`), which with a
        rolling shutter its edges model as the odometry did. Adds its node and edges, optimises, and
        returns {frame id: corrected (4, 4) float64 c2w} for every keyframe of ``views``."""
        new, earlier = views[-1], [v for v in views[:-1] if v.frame_id in self.graph]
        if velocity is not None and self.readout_s > 0:
            self.velocities[new.frame_id] = velocity.detach().double().cpu()
        start = time.perf_counter()
        self.graph.add_node(new.frame_id, new.pose)
        self.counters.keyframes += 1
        if earlier:
            cur_pyr = self._pyramid(new, K)
            for i in covisible_candidates(earlier, new, K, self.cfg):
                self._add_covisible(earlier[i], new, cur_pyr, K, predecessor=i == len(earlier) - 1)
            for i in loop_candidates(earlier, new, K, self.cfg):
                old = keyframe_pyramid(earlier[i], K, self.odometry, self.cfg)  # not cached: loop candidates are rarely reused
                a = align(earlier[i], new, old, cur_pyr, self.odometry, self.cfg, loop=True, shutters=self._shutters(earlier[i], new))
                if a.accepted:
                    self.graph.add_factor(self._factor(a, robust=True, loop=True))
                    self.closures.append((a.ref, a.cur))
                    self.counters.loops_accepted += 1
                    self.counters.edges += 1
                else:
                    self.counters.loops_rejected += 1
        self.counters.align_ms += 1000 * (time.perf_counter() - start)
        poses = self.graph.optimise()
        self.counters.optimise_ms = self.graph.optimise_ms
        return {v.frame_id: poses[v.frame_id] for v in views if v.frame_id in poses}

    def _shutters(self, ref: View, cur: View) -> tuple[Shutter | None, ...]:
        """The rolling shutters of an edge's two keyframes, ``cur``'s first; () where ``cur``'s velocity is not known."""
        return frame_shutters(self.readout_s, self.velocities.get(cur.frame_id), self.velocities.get(ref.frame_id))

    def _add_covisible(self, ref: View, new: View, cur_pyr: list[PyramidLevel], K: torch.Tensor, predecessor: bool) -> None:
        a = align(ref, new, self._pyramid(ref, K), cur_pyr, self.odometry, self.cfg, loop=False, shutters=self._shutters(ref, new))
        if a.accepted:
            self.graph.add_factor(self._factor(a, robust=not predecessor, loop=False))
            self.counters.edges += 1
        elif predecessor:  # the chain must stay connected: the tracked relative pose, loosely
            T = invert_pose(ref.pose.double()) @ new.pose.double()
            self.graph.add_factor(Factor(ref.frame_id, new.frame_id, T.cpu(), fallback_information(self.cfg), False))
            self.counters.edges += 1
            self.counters.chain_fallbacks += 1
        else:
            self.counters.covisible_rejected += 1

    def record(self, displacement_m: float, refit: bool) -> None:
        """What applying the last correction did: the largest keyframe displacement, whether the map was re-fit."""
        self.counters.max_correction_m = max(self.counters.max_correction_m, float(displacement_m))
        self.counters.refit_rounds += int(refit)

    def metrics(self) -> dict[str, Any]:
        """metrics.json keys (``graph_`` prefix): the counters and the accepted closures as [old, new] frame ids."""
        return {f"graph_{k}": v for k, v in asdict(self.counters).items()} | {"graph_closures": [list(c) for c in self.closures]}

    def log_scalars(self) -> dict[str, float]:
        """TensorBoard scalars (``graph/`` prefix)."""
        return {f"graph/{k}": float(v) for k, v in asdict(self.counters).items()}

    def state_dict(self) -> dict:
        return {"graph": self.graph.state_dict(), "counters": asdict(self.counters), "closures": [list(c) for c in self.closures],
                "velocities": dict(self.velocities)}

    def load_state_dict(self, state: dict) -> None:
        self.graph.load_state_dict(state["graph"])
        self.counters = GraphCounters(**state["counters"])
        self.closures = [(int(a), int(b)) for a, b in state["closures"]]
        self.velocities = {int(i): v.double().cpu() for i, v in state.get("velocities", {}).items()}  # none in older checkpoints
        self._pyramids.clear()
