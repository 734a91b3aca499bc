"""IMU acceleration units: drivers that publish g instead of m/s² (Livox's built-in IMU).

``sensor_msgs/Imu`` says m/s², but livox_ros_driver(2) publish the Mid-360's and Avia's
accelerometer in g: at rest the magnitude is about 1 instead of 9.81, and mapping would
take gravity for a tenth of itself. The unit is told from the median magnitude over many
samples (a vehicle's own accelerations are a small fraction of gravity), so a normal IMU,
whose median is near 9.8 whatever it does, is never rescaled.
"""

from __future__ import annotations

import numpy as np

STANDARD_GRAVITY = 9.80665  # m/s² per g
# Median |acceleration| that marks g: 1 g at rest, well clear of 9.81 m/s² (no IMU in m/s²
# reads a median of 0.5-2 m/s² unless it is in free fall).
G_MEDIAN_RANGE = (0.5, 2.0)
MIN_SAMPLES = 20


def acceleration_scale(acceleration: np.ndarray) -> float:
    """Factor that brings ``acceleration`` (N, 3) to m/s²: STANDARD_GRAVITY when its median
    magnitude says g, else 1 (also with fewer than MIN_SAMPLES finite, non-zero samples)."""
    a = np.asarray(acceleration, float).reshape(-1, 3)
    magnitude = np.linalg.norm(a[np.isfinite(a).all(axis=1)], axis=1)
    magnitude = magnitude[magnitude > 0]  # all-zero samples: a driver starting up, no reading
    if len(magnitude) < MIN_SAMPLES:
        return 1.0
    low, high = G_MEDIAN_RANGE
    return STANDARD_GRAVITY if low <= float(np.median(magnitude)) <= high else 1.0


def g_units_warning(source: str, acceleration: np.ndarray) -> str:
    """The warning for an IMU read in g and converted (``source``: bag and topic)."""
    median = float(np.median(np.linalg.norm(np.asarray(acceleration, float), axis=1)))
    return (
        f"{source}: linear acceleration is in g, not m/s² (median magnitude {median:.3f}, as "
        f"Livox drivers publish it); multiplied by {STANDARD_GRAVITY} m/s² per g"
    )
