"""Dataset readers for TivNe: every reader yields :class:`Frame` objects in time order."""

import os

# Before torch loads (see tivne/__init__.py): OpenMP reads its wait policy only once, at load time.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.sequence import SequenceDataModule, SequenceDataset

__all__ = ["DatasetError", "Frame", "Intrinsics", "SequenceDataModule", "SequenceDataset"]
