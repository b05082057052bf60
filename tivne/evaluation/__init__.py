"""Evaluate a run against its sequence (a library; the command line is :mod:`tivne.evaluate`).

* :mod:`~tivne.evaluation.run`: :func:`evaluate_run` -- the trajectory (ATE, flagged ``ate_partial``
  for a run that stopped early), re-rendered images and the 4D mesh metrics, as flat metrics.json keys.
* :mod:`~tivne.evaluation.ground_truth`: the :class:`GroundTruth` protocol, what a dataset with exact
  geometry offers (the synthetic scenes satisfy it), and adapters to numpy.
* :mod:`~tivne.evaluation.surfaces`: per moving object accuracy / completion / Chamfer over the part
  observed around the mesh time, ghost fraction, static metrics (definitions in its docstring).
* :mod:`~tivne.evaluation.images`: PSNR / SSIM / MSE / LPIPS of frames re-rendered at their
  estimated poses.
"""

from tivne.evaluation.ground_truth import GroundTruth, as_view, ground_truth_of
from tivne.evaluation.run import evaluate_run, trajectory_metrics

__all__ = ["GroundTruth", "as_view", "evaluate_run", "ground_truth_of", "trajectory_metrics"]
