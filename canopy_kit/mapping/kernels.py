"""Compiled per-point loops of the mapping stage (numba): voxel keys, the voxel set's insert,
the binned pose of the map pass, the deskew rotation, the gyro integration and the range
filter.

The map pass touches every point of every sweep (about 20,000 per sweep, 90 % of them in
voxels the map already holds) and the odometry deskews every registered sweep. In numpy
each step is a pass over memory with temporary arrays; here one loop per point does the
work. Each kernel gives the results of the numpy expression it replaced (tested), is
compiled on first use and cached on disk (``cache=True``), and holds no global state, so
forked workers share it.
"""

from __future__ import annotations

import numba
import numpy as np

EMPTY = -1  # a free slot of the open-addressing table (keys are non-negative)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: slot = top bits of key * golden


@numba.njit(cache=True, nogil=True)
def insert_keys(keys: np.ndarray, table: np.ndarray, bits: int) -> np.ndarray:
    """Insert ``keys`` in order into ``table`` (linear probing); True where a key was new.

    A key repeated within ``keys`` is new at its first occurrence only. The caller keeps
    the table at most half full, so every probe sequence ends at a free slot.
    """
    new = np.zeros(keys.shape[0], np.bool_)
    mask = (1 << bits) - 1
    shift = np.uint64(64 - bits)
    for i in range(keys.shape[0]):
        key = keys[i]
        slot = np.int64((np.uint64(key) * _GOLDEN) >> shift)
        while True:
            held = table[slot]
            if held == key:
                break
            if held == EMPTY:
                table[slot] = key
                new[i] = True
                break
            slot = (slot + 1) & mask
    return new


@numba.njit(cache=True, nogil=True, inline="always")
def _move_point(
    xyz: np.ndarray, k: int, out: np.ndarray, i: int, rotation: np.ndarray, translation: np.ndarray
) -> None:
    """``out[i] = rotation @ xyz[k] + translation`` (float64)."""
    x, y, z = np.float64(xyz[k, 0]), np.float64(xyz[k, 1]), np.float64(xyz[k, 2])
    for r in range(3):
        out[i, r] = rotation[r, 0] * x + rotation[r, 1] * y + rotation[r, 2] * z + translation[r]


@numba.njit(cache=True, nogil=True)
def transform_by_bin(
    xyz: np.ndarray, bins: np.ndarray, rotations: np.ndarray, translations: np.ndarray
) -> np.ndarray:
    """``rotations[b] @ p + translations[b]`` for each point ``p`` of bin ``b`` (float64)."""
    out = np.empty((xyz.shape[0], 3), np.float64)
    for i in range(xyz.shape[0]):
        b = bins[i]
        _move_point(xyz, i, out, i, rotations[b], translations[b])
    return out


@numba.njit(cache=True, nogil=True)
def kept_time_span(times: np.ndarray, keep: np.ndarray) -> tuple[float, float]:
    """Smallest and largest of ``times[keep]`` (``keep`` not empty), without the gather."""
    lo = times[keep[0]]
    hi = lo
    for i in range(1, keep.shape[0]):
        t = times[keep[i]]
        if t < lo:
            lo = t
        elif t > hi:
            hi = t
    return lo, hi


@numba.njit(cache=True, nogil=True)
def place_kept_binned(
    xyz: np.ndarray,
    keep: np.ndarray,
    times: np.ndarray,
    lo: float,
    span: float,
    rotations: np.ndarray,
    translations: np.ndarray,
) -> np.ndarray:
    """Points ``xyz[keep]`` moved by the pose of their time bin: bin ``b`` of ``n`` =
    ``len(rotations)`` is ``clip(int((t - lo) / span * (n - 1) + 0.5), 0, n - 1)``, the numpy
    expression of ``assemble._pose_times`` evaluated in the same order (same bins), then
    :func:`transform_by_bin`'s product. One pass: no gathered copies of the points or
    times and no temporary per step (float64 ``times`` only)."""
    n = rotations.shape[0]
    out = np.empty((keep.shape[0], 3), np.float64)
    for i in range(keep.shape[0]):
        k = keep[i]
        v = (times[k] - lo) / span * (n - 1) + 0.5
        b = np.int64(v)
        if b < 0:
            b = 0
        elif b > n - 1:
            b = n - 1
        _move_point(xyz, k, out, i, rotations[b], translations[b])
    return out


@numba.njit(cache=True, nogil=True)
def voxel_keys(xyz: np.ndarray, size: float, bits: int) -> tuple[np.ndarray, bool]:
    """Each point's voxel ``floor(p / size)`` packed in ``bits`` bits per axis (offset so
    that the grid's centre is 0), and whether every voxel fits the packing."""
    offset = np.int64(1) << (bits - 1)
    limit = (np.int64(1) << bits) - 1
    keys = np.empty(xyz.shape[0], np.int64)
    fits = True
    for i in range(xyz.shape[0]):
        key = np.int64(0)
        for axis in range(3):
            v = np.floor(xyz[i, axis] / size) + offset
            k = np.int64(0)
            if v >= 0.0 and v <= limit:  # False for NaN and inf, which have no integer
                k = np.int64(v)
            else:
                fits = False
            key = (key << bits) | k
        keys[i] = key
    return keys, fits


@numba.njit(cache=True, nogil=True)
def rotate_and_shift(
    xyz: np.ndarray, bins: np.ndarray, rotvecs: np.ndarray, dt: np.ndarray, velocity: np.ndarray
) -> np.ndarray:
    """``p + w×p + ½ w×(w×p) + dt·v`` per point, ``w = rotvecs[bin]`` (second-order Rodrigues)."""
    out = np.empty((xyz.shape[0], 3), np.float64)
    for i in range(xyz.shape[0]):
        wx, wy, wz = rotvecs[bins[i], 0], rotvecs[bins[i], 1], rotvecs[bins[i], 2]
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        cx, cy, cz = wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px
        out[i, 0] = px + cx + 0.5 * (wy * cz - wz * cy) + dt[i] * velocity[0]
        out[i, 1] = py + cy + 0.5 * (wz * cx - wx * cz) + dt[i] * velocity[1]
        out[i, 2] = pz + cz + 0.5 * (wx * cy - wy * cx) + dt[i] * velocity[2]
    return out


@numba.njit(cache=True, nogil=True)
def integrate_gyro(
    q: np.ndarray, t_last: float, omega_last: np.ndarray, t: np.ndarray, omega: np.ndarray
) -> np.ndarray:
    """Orientations (xyzw) at ``t`` from ``q`` at ``t_last``: body-frame gyro increments by the
    midpoint rule, chained one after the other and normalised."""
    out = np.empty((t.shape[0], 4), np.float64)
    qx, qy, qz, qw = q[0], q[1], q[2], q[3]
    t_prev, wx0, wy0, wz0 = t_last, omega_last[0], omega_last[1], omega_last[2]
    for i in range(t.shape[0]):
        dt = t[i] - t_prev
        vx, vy, vz = (
            0.5 * (wx0 + omega[i, 0]) * dt,
            0.5 * (wy0 + omega[i, 1]) * dt,
            0.5 * (wz0 + omega[i, 2]) * dt,
        )
        angle = np.sqrt(vx * vx + vy * vy + vz * vz)
        k = np.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5 - angle * angle / 48.0
        sx, sy, sz, sw = vx * k, vy * k, vz * k, np.cos(0.5 * angle)
        qx, qy, qz, qw = (
            qw * sx + qx * sw + qy * sz - qz * sy,
            qw * sy - qx * sz + qy * sw + qz * sx,
            qw * sz + qx * sy - qy * sx + qz * sw,
            qw * sw - qx * sx - qy * sy - qz * sz,
        )
        norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = qx, qy, qz, qw
        t_prev, wx0, wy0, wz0 = t[i], omega[i, 0], omega[i, 1], omega[i, 2]
    return out


@numba.njit(cache=True, nogil=True)
def in_range(xyz: np.ndarray, min_r2: float, max_r2: float) -> np.ndarray:
    """True where ``min_r2 <= x² + y² + z² <= max_r2`` (so False for a non-finite point):
    one pass over the points instead of numpy's squared norm, finiteness and two bounds."""
    out = np.empty(xyz.shape[0], np.bool_)
    for i in range(xyz.shape[0]):
        r2 = xyz[i, 0] * xyz[i, 0] + xyz[i, 1] * xyz[i, 1] + xyz[i, 2] * xyz[i, 2]
        out[i] = r2 >= min_r2 and r2 <= max_r2
    return out


def warm_up() -> None:
    """Load (or compile) every kernel now, in this process.

    The first call of a kernel in a process costs about 0.35 s (numba sets up its typing
    context and reads the cache); worker processes forked afterwards inherit the loaded
    kernels instead of paying it each.
    """
    xyz = np.zeros((1, 3))
    index = np.zeros(1, np.int64)
    keys, _ = voxel_keys(xyz, 1.0, 21)
    insert_keys(keys, np.full(4, EMPTY, np.int64), 2)
    transform_by_bin(xyz, index, np.eye(3)[None], np.zeros((1, 3)))
    for points in (xyz, xyz.astype(np.float32)):  # scans decode to either
        place_kept_binned(points, index, np.zeros(1), 0.0, 1.0, np.eye(3)[None], np.zeros((1, 3)))
    kept_time_span(np.zeros(1), index)
    rotate_and_shift(xyz, index, np.zeros((1, 3)), np.zeros(1), np.zeros(3))
    integrate_gyro(np.array([0.0, 0.0, 0.0, 1.0]), 0.0, np.zeros(3), np.ones(1), np.zeros((1, 3)))
    in_range(xyz, 0.0, 1.0)
