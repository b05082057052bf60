from tivne.field.clock import Clock
from tivne.field.networks import (
    CanonicalMLP,
    DeformationMLP,
    FieldOutputs,
    TimeVaryingField,
    time_encoding,
)
from tivne.field.voxels import GridCapacityError, SparseVoxelGrid

__all__ = ["CanonicalMLP", "Clock", "DeformationMLP", "FieldOutputs", "GridCapacityError", "SparseVoxelGrid", "TimeVaryingField", "time_encoding"]
