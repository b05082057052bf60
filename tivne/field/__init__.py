from tivne.field.networks import (
    CanonicalMLP,
    DeformationMLP,
    FieldOutputs,
    TimeVaryingField,
    time_encoding,
    time_to_tau,
)
from tivne.field.voxels import GridCapacityError, SparseVoxelGrid

__all__ = ["CanonicalMLP", "DeformationMLP", "FieldOutputs", "GridCapacityError", "SparseVoxelGrid", "TimeVaryingField", "time_encoding", "time_to_tau"]
