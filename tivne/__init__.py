"""TivNe: dynamic dense RGB-D SLAM with a time-varying neural field."""

import os

# OpenMP reads its wait policy once, when torch's runtime loads, so it must be set before the first
# `import torch`. With the default (active) policy two threads spin against each other whenever
# another process shares the cores: 30-60 s/frame instead of ~1 on a shared 2-core box.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
