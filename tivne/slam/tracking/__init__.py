"""Camera tracking: the front end (:class:`Tracker`), its typed result, the dense RGB-D odometry
(``odometry``, ``pyramid``, ``robust``) and the paper's field tracker (``field``)."""

from tivne.slam.tracking.result import FieldTrackStats, TrackResult, TrackStatus
from tivne.slam.tracking.tracker import PoseLookup, Tracker, TrackingCounts

__all__ = ["FieldTrackStats", "PoseLookup", "TrackResult", "TrackStatus", "Tracker", "TrackingCounts"]
