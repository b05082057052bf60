"""Procedural synthetic RGB-D sequences with exact ground truth."""

from data_modules.synthetic.sequence import MovingCubeSequence

__all__ = ["MovingCubeSequence"]
