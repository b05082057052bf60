"""SLAM front end: classic dense RGB-D odometry (``odometry``) on image pyramids (``pyramid``) with IRLS (``robust``)."""
