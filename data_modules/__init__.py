"""Dataset readers for TivNe: every reader yields :class:`Frame` objects in time order."""

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.sequence import SequenceDataModule, SequenceDataset

__all__ = ["DatasetError", "Frame", "Intrinsics", "SequenceDataModule", "SequenceDataset"]
