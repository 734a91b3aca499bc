"""GNSS fixes in the local metric frame, with the error model the pose graph uses.

A standalone receiver's error is not white: it wanders by decimetres to metres over tens
of seconds (multipath, atmosphere). Treating 10 Hz fixes as independent would let that
slow wander bend the trajectory. Fixes are therefore averaged into epochs (``epoch``
seconds) and carry a Gauss-Markov bias state in the graph (see :mod:`.fusion`); only the
white part of the error shrinks with averaging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.geo import LocalFrame, utm_epsg
from canopy_kit.io.bag import GnssSeries

NO_FIX = -1  # sensor_msgs/NavSatStatus STATUS_NO_FIX


@dataclass
class GnssEpochs:
    """Epoch-averaged GNSS positions in a local frame."""

    t: np.ndarray  # (M,) epoch times, s
    xyz: np.ndarray  # (M, 3) local positions (antenna)
    sigma: np.ndarray  # (M, 3) reported 1-sigma per axis (east, north, up)
    count: np.ndarray  # (M,) fixes per epoch
    frame: LocalFrame
    n_fixes: int
    n_rejected: int


def local_frame_for(gnss: GnssSeries) -> LocalFrame:
    """A UTM-based local frame whose origin is the first valid fix, rounded to whole metres."""
    ok = _valid(gnss)
    if not ok.any():
        raise InputError("GNSS topic has no valid fix (all NO_FIX or non-finite)")
    i = int(np.flatnonzero(ok)[0])
    lat, lon, alt = float(gnss.latitude[i]), float(gnss.longitude[i]), float(gnss.altitude[i])
    exact = LocalFrame.at(lat, lon, alt)
    return LocalFrame(utm_epsg(lat, lon), float(np.round(exact.origin_easting)),
                      float(np.round(exact.origin_northing)), float(np.round(alt)))


def _valid(gnss: GnssSeries) -> np.ndarray:
    return (np.isfinite(gnss.latitude) & np.isfinite(gnss.longitude) & np.isfinite(gnss.altitude)
            & (gnss.status > NO_FIX) & (np.abs(gnss.latitude) <= 90) & (np.abs(gnss.longitude) <= 180))


def reported_sigmas(gnss: GnssSeries, default_horizontal: float, default_vertical: float) -> np.ndarray:
    """Per-fix 1-sigma (east, north, up) from the NavSatFix covariance, defaults where unknown."""
    n = len(gnss.t)
    out = np.tile([default_horizontal, default_horizontal, default_vertical], (n, 1)).astype(float)
    cov = gnss.covariance
    if cov.shape == (n, 9):
        diag = cov[:, [0, 4, 8]]
        known = np.all(np.isfinite(diag) & (diag > 0), axis=1)
        out[known] = np.sqrt(diag[known])
    return out


def gnss_epochs(gnss: GnssSeries, frame: LocalFrame, epoch: float = 1.0,
                default_horizontal: float = 1.0, default_vertical: float = 2.0) -> GnssEpochs:
    """Valid fixes converted to ``frame`` and averaged over ``epoch``-second bins."""
    ok = _valid(gnss)
    n_rejected = int((~ok).sum())
    t = gnss.t[ok]
    if len(t) == 0:
        raise InputError("GNSS topic has no valid fix (all NO_FIX or non-finite)")
    xyz = frame.to_local(gnss.latitude[ok], gnss.longitude[ok], gnss.altitude[ok])
    sigma = reported_sigmas(gnss, default_horizontal, default_vertical)[ok]
    bins = np.floor((t - t[0]) / epoch).astype(np.int64)
    _, start, count = np.unique(bins, return_index=True, return_counts=True)
    sums = np.add.reduceat(np.column_stack([t, xyz, sigma]), start, axis=0)
    mean = sums / count[:, None]
    return GnssEpochs(mean[:, 0], mean[:, 1:4], mean[:, 4:7], count, frame, int(len(t)), n_rejected)
