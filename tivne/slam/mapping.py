"""Mapping: joint optimisation of E, Θd, Θs and the window's poses over current frame + keyframes,
and the final pass over every keyframe after the sequence."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from data_modules.sensor import kinect_depth_sigma
from tivne.config import LossWeights, MappingConfig, RenderConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import orthonormalize_pose, se3_exp
from tivne.render.losses import slam_loss
from tivne.render.rays import View
from tivne.render.renderer import render_pixels
from tivne.render.samplers import PixelPool, PixelSampler
from tivne.slam.keyframes import KeyframePolicy, KeyframeStore
from tivne.utils import torch_threads


@dataclass(frozen=True)
class MapRound:
    """One mapping round: the frame ids of its window (the current frame first), the refined poses
    ({frame id: (4, 4) c2w}, only where they could move) and the last step's loss terms."""

    window: tuple[int, ...]
    poses: dict[int, torch.Tensor]
    terms: dict[str, float]

    def scalars(self) -> dict[str, float]:
        """Log scalars (TensorBoard ``map/...``)."""
        counts = ("steps", "skipped_steps", "explained")  # not loss terms: logged under their own names
        out = {n if n in counts else f"loss_{n}" if n != "total" else "loss": v for n, v in self.terms.items()}
        return out | {"window": float(len(self.window))}


class Mapper:
    """Owns the map optimiser (persistent Adam over E and both MLPs, per-group learning rates), the
    pixel sampler and the render / loss settings of mapping."""

    def __init__(
        self, field: TimeVaryingField, cfg: MappingConfig, sampler: PixelSampler, render: RenderConfig, weights: LossWeights
    ) -> None:
        self.field = field
        self.cfg = cfg
        self.sampler, self.render, self.weights = sampler, render, weights
        self.seconds, self.iterations = 0.0, 0  # time and steps spent in online rounds
        decoder = [p for n, p in field.named_parameters() if not n.startswith("grid.")]
        # foreach: one kernel per update for the ~20 small MLP tensors instead of a Python loop over them
        self.optimizer = torch.optim.Adam(
            [{"params": [field.grid.embeddings], "lr": cfg.lr_embeddings}, {"params": decoder, "lr": cfg.lr_decoder}], foreach=True
        )
        field.grid.grow_callbacks.append(self._pad_embedding_state)
        self.steps = 0  # optimiser steps run so far (the final pass's budget is a share of them)
        self.owed = 0  # steps of first_iters not yet run (mapping.first_now ran at the first frame)

    def state_dict(self) -> dict:
        """The optimiser (Adam's moments, padded to E's rows, and step counts) and the steps run."""
        return {"optimizer": self.optimizer.state_dict(), "steps": self.steps, "owed": self.owed}

    def load_state_dict(self, state: dict) -> None:
        """After the field's own state (E must already have the saved number of rows)."""
        self.optimizer.load_state_dict(state["optimizer"])
        self.steps = int(state["steps"])
        self.owed = int(state.get("owed", 0))  # checkpoints before mapping.first_now owe nothing

    def _pad_embedding_state(self, old_rows: int, new_rows: int) -> None:
        """Keep Adam's moments aligned with E after the grid grows (new rows start from zero moments)."""
        state = self.optimizer.state.get(self.field.grid.embeddings)
        if not state:
            return
        for key in ("exp_avg", "exp_avg_sq"):
            moment = state[key]
            state[key] = torch.cat([moment, moment.new_zeros(new_rows - old_rows, moment.shape[1])])

    def map_frame(
        self, view: View, store: KeyframeStore, policy: KeyframePolicy, K: torch.Tensor, generator: torch.Generator | None, first: bool
    ) -> MapRound:
        """A mapping round on ``view`` (the current frame, tracked) and the keyframes ``policy`` picks;
        the first frame alone gets ``first_now`` of its ``first_iters`` steps with its pose fixed (it is
        the world frame); the rounds after it run the rest, at most ``iters`` more each. A frame with
        moving pixels gets ``iters`` steps, one without ``static_iters``."""
        if first:
            views, fixed, iters = [view], [True], min(self.cfg.first_now, self.cfg.first_iters)
            self.owed = self.cfg.first_iters - iters
        else:
            picked = policy.select(store, view, K, generator)
            views = [view] + [store.view(i) for i in picked]
            fixed = [False] + [v.frame_id == 0 for v in views[1:]]
            base = self.cfg.iters if view.dynamic is not None and bool(view.dynamic.any()) else self.cfg.static_iters
            extra = min(self.owed, base)
            iters, self.owed = base + extra, self.owed - extra
        start = time.perf_counter()
        poses, terms = self.run(views, fixed, iters, K, generator, settle=not first and self.cfg.settle_share > 0)
        self.seconds += time.perf_counter() - start
        self.iterations += int(terms["steps"])
        moved = {v.frame_id: p for v, p, f in zip(views, poses, fixed) if not f and self.cfg.optimize_poses}
        return MapRound(tuple(v.frame_id for v in views), moved, terms)

    def run(
        self,
        views: list[View],
        fixed: list[bool],
        iters: int,
        K: torch.Tensor,
        generator: torch.Generator | None = None,
        current_share: float | None = None,
        settle: bool = False,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Optimise the map on ``views`` (views[0] is the current frame, with ``current_share`` of
        the rays; default the config's). ``settle``: stop after ``settle_iters`` steps when the first
        step finds the current frame explained (:func:`explained_share`, the config's settle_*).

        Returns the refined (V, 4, 4) poses (unchanged where ``fixed``) and the last step's loss terms
        with ``steps`` (the steps run), ``skipped_steps`` and, when settling, ``explained``.
        """
        with torch_threads(self.cfg.threads):
            return self._run(views, fixed, iters, K, generator, current_share, settle)

    def _run(
        self, views: list[View], fixed: list[bool], iters: int, K: torch.Tensor, generator: torch.Generator | None,
        current_share: float | None, settle: bool,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """:meth:`run`'s steps (on the threads it set)."""
        cfg = self.cfg
        base = torch.stack([v.pose.detach() for v in views])
        movable = torch.tensor([not f for f in fixed], device=base.device, dtype=base.dtype)[:, None]
        pose_delta = torch.zeros(len(views), 6, device=base.device, dtype=base.dtype, requires_grad=cfg.optimize_poses)
        pose_opt = torch.optim.Adam([pose_delta], lr=cfg.lr_pose) if cfg.optimize_poses and movable.any() else None
        sampling = self.sampler.cfg
        pools = [PixelPool.from_masks(v.depth > 0, v.dynamic, sampling.mask_edge, sampling.label_edge) for v in views]
        any_unsure = any(pool.labels is not None for pool in pools)  # else no step reads a band (real data, still frames)
        share = cfg.current_share if current_share is None else current_share
        n_cur = cfg.rays if len(views) == 1 else int(cfg.rays * share)
        n_other = (cfg.rays - n_cur) // max(len(views) - 1, 1)
        counts = [n_cur] + [n_other] * (len(views) - 1)
        terms: dict[str, torch.Tensor] = {}
        skipped = step = 0
        explained = float("nan")
        while step < iters:
            step += 1
            poses = base @ se3_exp(pose_delta * movable) if pose_opt is not None else base
            pixels = [self.sampler(pool, n, generator) for pool, n in zip(pools, counts)]
            batch = render_pixels(self.field, views, pixels, poses, K, self.render, True, generator)
            if settle and step == 1:
                n = len(pixels[0])
                explained = explained_share(batch.rendered.depth[:n].detach(), batch.rays.depth[:n], cfg.settle_sigmas)
                if explained >= cfg.settle_share:
                    iters = min(iters, cfg.settle_iters)
            unsure = torch.cat([pool.is_unsure(p) for pool, p in zip(pools, pixels)]) if any_unsure else None
            loss, terms = slam_loss(batch, self.render.truncation, self.weights, unsure=unsure)
            if not torch.isfinite(loss) or not loss.requires_grad:  # never step the map on a broken batch
                skipped += 1
                continue
            self.optimizer.zero_grad(set_to_none=True)
            if pose_opt is not None:
                pose_opt.zero_grad(set_to_none=True)
            loss.backward()
            if not grads_finite(self.optimizer):
                skipped += 1
                continue
            self.optimizer.step()
            if pose_opt is not None:
                pose_opt.step()
        with torch.no_grad():
            final = base @ se3_exp(pose_delta * movable) if pose_opt is not None else base
        self.steps += step
        stats = {k: float(v) for k, v in terms.items()}
        stats["skipped_steps"], stats["steps"] = float(skipped), float(step)
        if settle:
            stats["explained"] = explained
        return orthonormalize_pose(final.detach()), stats


def explained_share(rendered: torch.Tensor, measured: torch.Tensor, n_sigma: float) -> float:
    """Share of rays (N,) whose rendered depth lies within ``n_sigma`` σ(z) of the measured depth
    (N,), σ the Kinect depth noise (:func:`data_modules.sensor.kinect_depth_sigma`): how much of a
    frame the map explains already, as far as the sensor can tell (1.0 for no rays)."""
    if rendered.numel() == 0:
        return 1.0
    return float(((rendered - measured).abs() <= n_sigma * kinect_depth_sigma(measured)).float().mean())


def grads_finite(optimizer: torch.optim.Optimizer) -> bool:
    """Whether every gradient the optimiser would apply is finite (one fused norm, one sync)."""
    grads = [p.grad for g in optimizer.param_groups for p in g["params"] if p.grad is not None]
    return not grads or bool(torch.isfinite(torch.nn.utils.get_total_norm(grads)))


def final_pass(mapper: Mapper, views: Sequence[View], K: torch.Tensor, generator: torch.Generator | None = None) -> dict[str, float]:
    """The last pass over the whole sequence (Co-SLAM's final global BA, poses fixed).

    ``mapping.final_share`` of the steps mapping ran so far, at most ``mapping.final_iters``, in
    rounds of ``mapping.iters``, each over a window of ``mapping.final_window`` views drawn without
    replacement from a shuffled cycle, so every time is revisited about equally often. Returns the
    last round's loss terms.
    """
    cfg = mapper.cfg
    budget = min(cfg.final_iters, int(round(cfg.final_share * mapper.steps)))
    if budget <= 0 or not views:
        return {}
    window = max(1, min(cfg.final_window, len(views)))
    order: list[int] = []
    done, terms = 0, {}
    while done < budget:
        if len(order) < window:  # next cycle; the last cycle's leftovers go first, no repeats in a window
            order += [i for i in torch.randperm(len(views), generator=generator).tolist() if i not in order]
        picked, order = order[:window], order[window:]
        iters = max(1, min(cfg.iters, budget - done))
        _, terms = mapper.run([views[i] for i in picked], [True] * window, iters, K, generator, current_share=1.0 / window)
        done += iters
    return terms
