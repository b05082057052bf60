"""Sensor models in data_modules.sensor."""

import numpy as np
import pytest
import torch

from data_modules.sensor import kinect_depth_sigma


def test_kinect_depth_sigma_values_and_types():
    # Nguyen et al. 2012: 1.2 mm at 0.4 m, growing with the square of the distance beyond it.
    assert kinect_depth_sigma(0.4) == pytest.approx(0.0012)
    assert kinect_depth_sigma(2.4) == pytest.approx(0.0012 + 0.0019 * 4.0)
    z = np.array([0.5, 1.0, 3.0], dtype=np.float32)
    assert isinstance(kinect_depth_sigma(z), np.ndarray)
    t = kinect_depth_sigma(torch.from_numpy(z))
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
    np.testing.assert_allclose(t.numpy(), kinect_depth_sigma(z))
