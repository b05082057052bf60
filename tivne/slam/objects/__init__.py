"""Rigid moving objects: instances per frame, one SE(3) track per object, their TUM output."""

from tivne.slam.objects.track import ObjectTrack
from tivne.slam.objects.tracker import ObjectObservation, ObjectTracker

__all__ = ["ObjectObservation", "ObjectTrack", "ObjectTracker"]
