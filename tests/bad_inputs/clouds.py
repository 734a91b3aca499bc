"""LAS files with a broken header or no points, written with laspy directly (canopy-kit's own
writer refuses to make them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_raw_las(path: Path, n_points: int = 200, scale: float = 0.001, offset: float = 0.0,
                  seed: int = 0) -> Path:
    """A LAS 1.2 file whose header holds ``scale`` and ``offset`` as given, however wrong."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale, dtype=np.float64)
    header.offsets = np.full(3, offset, dtype=np.float64)
    las = laspy.LasData(header)
    rng = np.random.default_rng(seed)
    ints = rng.integers(0, 5000, (n_points, 3)).astype(np.int32)
    las.X, las.Y, las.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    import warnings

    with warnings.catch_warnings():  # laspy computes bounds with the (bad) scale: NaN warnings
        warnings.simplefilter("ignore", RuntimeWarning)
        las.write(path)
    return path


def write_truncated_laz(path: Path, fraction: float = 0.6) -> Path:
    """A valid LAZ cut to ``fraction`` of its length."""
    from canopy_kit.cloud import PointCloud
    from canopy_kit.io.las import write_las

    rng = np.random.default_rng(1)
    write_las(path, PointCloud(rng.uniform(0, 10, (5000, 3))))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path
