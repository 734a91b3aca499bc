"""Compiled per-point loops of the segmentation (numba).

The crown split (:mod:`.crowns`) needs each point's neighbourhood covariance; in numpy that
is a gather of every point's ``k`` neighbours (a ``(N, k, 3)`` temporary), a mean and an
einsum over it. Here one loop per point does it without temporaries. Compiled on first
use and cached on disk (``cache=True``); no global state, so forked workers share it.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def neighbourhood_covariances(xyz: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Per point ``i``: the (3, 3) scatter matrix ``Σ (p − m)(p − m)ᵀ`` of its neighbours
    ``xyz[neighbours[i]]`` about their mean ``m``."""
    n, k = neighbours.shape
    out = np.empty((n, 3, 3), np.float64)
    for i in range(n):
        mx = my = mz = 0.0
        for j in range(k):
            q = neighbours[i, j]
            mx += xyz[q, 0]
            my += xyz[q, 1]
            mz += xyz[q, 2]
        mx, my, mz = mx / k, my / k, mz / k
        sxx = sxy = sxz = syy = syz = szz = 0.0
        for j in range(k):
            q = neighbours[i, j]
            dx, dy, dz = xyz[q, 0] - mx, xyz[q, 1] - my, xyz[q, 2] - mz
            sxx += dx * dx
            sxy += dx * dy
            sxz += dx * dz
            syy += dy * dy
            syz += dy * dz
            szz += dz * dz
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = sxx, sxy, sxz
        out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = sxy, syy, syz
        out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = sxz, syz, szz
    return out
