"""Ground-height refinement of the odometry: height, roll and pitch from the ground.

With the ground removed, KISS-ICP's vertical estimate rests on trunks and crowns only and
drifts (measured: heights ramped by 2-6 mm per metre across an almond session, i.e.
different alleys saw the same crown 5-10 cm apart). Feeding ground points back to ICP
pins the height but drags the horizontal estimate (the flat-ground trap). So, as in
LeGO-LOAM, the ground fixes only what it can: after ICP, the sweep's ground points are
compared with a running grid of ground heights and a correction of height and tilt
(``dz + a·dx + b·dy``, about the sensor position) is applied before the local map is
updated; x, y and yaw stay as ICP found them.

Time chunks of the drive (:mod:`canopy_kit.mapping.chunks`) each start with an empty grid;
:func:`regrounded_poses` repeats the correction over the stitched drive against one grid of
every sweep before it, so a later chunk rests on the ground the earlier ones saw (off by
default: ``chunks.REGROUND_CHUNKS`` says what it did and did not fix).
"""

from __future__ import annotations

import numpy as np


class GroundHeightGrid:
    """Mean ground height per square cell of the map frame, built from registered sweeps.

    A dense array that grows (with margin) when points fall outside it: an orchard block
    of a few hundred metres needs a few hundred thousand 0.5 m cells.
    """

    def __init__(self, cell_size: float = 0.5, margin: int = 200) -> None:
        self.cell_size = float(cell_size)
        self.margin = margin
        self._origin = np.zeros(2, np.int64)  # cell index of element [0, 0]
        self._sum = np.zeros((0, 0))
        self._count = np.zeros((0, 0), np.int64)

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        return np.floor(xy / self.cell_size).astype(np.int64)

    def _ensure(self, cells: np.ndarray) -> None:
        lo, hi = cells.min(axis=0), cells.max(axis=0)
        shape = np.array(self._sum.shape, np.int64)
        if self._sum.size and np.all(lo >= self._origin) and np.all(hi < self._origin + shape):
            return
        new_lo = np.minimum(lo, self._origin) - self.margin if self._sum.size else lo - self.margin
        new_hi = (
            np.maximum(hi, self._origin + shape - 1) + self.margin
            if self._sum.size
            else hi + self.margin
        )
        size = new_hi - new_lo + 1
        total = np.zeros(size)
        count = np.zeros(size, np.int64)
        if self._sum.size:
            off = self._origin - new_lo
            total[off[0] : off[0] + shape[0], off[1] : off[1] + shape[1]] = self._sum
            count[off[0] : off[0] + shape[0], off[1] : off[1] + shape[1]] = self._count
        self._origin, self._sum, self._count = new_lo, total, count

    def heights(self, xy: np.ndarray, min_count: int = 3) -> np.ndarray:
        """Mean height of each point's cell (NaN where the cell has fewer than ``min_count``)."""
        out = np.full(len(xy), np.nan)
        if self._sum.size == 0 or len(xy) == 0:
            return out
        ij = self._cells(xy) - self._origin
        inside = np.all((ij >= 0) & (ij < np.array(self._sum.shape)), axis=1)
        i, j = ij[inside, 0], ij[inside, 1]
        n = self._count[i, j]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[inside] = np.where(n >= min_count, self._sum[i, j] / n, np.nan)
        return out

    def add(self, xyz: np.ndarray) -> None:
        """Add ground points (map frame)."""
        if len(xyz) == 0:
            return
        cells = self._cells(xyz[:, :2])
        self._ensure(cells)
        ij = cells - self._origin
        flat = ij[:, 0] * self._sum.shape[1] + ij[:, 1]
        uniq, inverse = np.unique(flat, return_inverse=True)
        self._sum.flat[uniq] += np.bincount(inverse.ravel(), weights=xyz[:, 2])
        self._count.flat[uniq] += np.bincount(inverse.ravel())


def ground_correction(
    ground_world: np.ndarray,
    sensor_xy: np.ndarray,
    grid: GroundHeightGrid,
    min_points: int = 100,
    trim: float = 0.1,
    max_tilt: float = 0.01,
    max_shift: float = 0.2,
) -> np.ndarray | None:
    """Least-squares ``(dz, a, b)`` with ``z - h(cell) ≈ dz + a·dx + b·dy``, or None.

    ``dx, dy`` are offsets from the sensor; residuals beyond ``trim`` of the first fit are
    dropped; corrections beyond the limits are clipped to them (the next sweeps go on
    correcting), so one bad fit cannot move a sweep far.
    """
    h = grid.heights(ground_world[:, :2])
    ok = np.isfinite(h)
    if ok.sum() < min_points:
        return None
    d = ground_world[ok, :2] - sensor_xy
    r = ground_world[ok, 2] - h[ok]
    if np.ptp(d, axis=0).min() < 2.0:
        return None
    axes = two_sided_axes(d)
    a = np.column_stack([np.ones(len(r)), d @ axes])
    coef = None
    use = np.abs(r - np.median(r)) <= 2 * trim
    for _ in range(2):
        if use.sum() < min_points:
            return None
        coef, *_ = np.linalg.lstsq(a[use], r[use], rcond=None)
        use = np.abs(r - a @ coef) <= trim
    if coef is None:
        return None
    slope = axes @ coef[1:] if axes.shape[1] else np.zeros(2)
    return np.r_[np.clip(coef[0], -max_shift, max_shift), np.clip(slope, -max_tilt, max_tilt)]


def two_sided_axes(offsets: np.ndarray, min_share: float = 0.2) -> np.ndarray:
    """Principal directions (2, k) along which the ground points lie on both sides of the sensor.

    A tilt about an axis is fitted only where the ground straddles the sensor: from ground
    seen on one side only (a LiDAR pitched down to the rear sees ground behind it alone),
    the slope picks up whatever makes near and far ground differ (grass seen at grazing
    angles far away, ground at steep angles nearby) and biases the pitch (measured: 0.25 deg
    in the alleys driven one way, and a 9 cm height ramp across a 4-row block).
    """
    _, vectors = np.linalg.eigh(np.cov(offsets.T))
    keep = []
    for k in range(2):
        proj = offsets @ vectors[:, k]
        if min(np.mean(proj > 0), np.mean(proj < 0)) >= min_share:
            keep.append(vectors[:, k])
    return np.array(keep).T.reshape(2, len(keep))


def refinement_points(ground: np.ndarray, max_points: int = 3000) -> np.ndarray:
    """The ground points (sensor frame) a sweep's correction uses: 2-20 m out, thinned evenly."""
    r2 = np.einsum("ij,ij->i", ground[:, :2], ground[:, :2])
    ground = ground[(r2 >= 4.0) & (r2 <= 400.0)]
    if len(ground) > max_points:
        ground = ground[:: int(np.ceil(len(ground) / max_points))]
    return ground


def regrounded_poses(
    poses: list[np.ndarray], grounds: list[np.ndarray | None], fixed: int
) -> tuple[list[np.ndarray], int]:
    """The poses corrected again, in drive order, against one ground grid of every sweep before.

    ``grounds[i]`` are sweep ``i``'s refinement points in its sensor frame (None: a sweep
    without, e.g. one left unregistered). The first ``fixed`` sweeps only fill the grid; each
    later one is corrected on its own (as the front end does), not carried on to the sweeps
    after it: their own corrections already hold what the local map inherited, and carrying
    each on (measured) doubled the height differences to a single process's odometry.
    Returns the poses and the number of sweeps corrected.
    """
    grid = GroundHeightGrid()
    out, corrected = [], 0
    for i, (pose, ground) in enumerate(zip(poses, grounds, strict=True)):
        if ground is not None and len(ground):
            ground = np.asarray(ground, float)
            world = ground @ pose[:3, :3].T + pose[:3, 3]
            coef = ground_correction(world, pose[:2, 3], grid) if i >= fixed else None
            if coef is not None:
                pose = apply_ground_correction(pose, coef)
                world = ground @ pose[:3, :3].T + pose[:3, 3]
                corrected += 1
            grid.add(world)
        out.append(pose)
    return out, corrected


def apply_ground_correction(pose: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """The pose moved so its ground points drop by ``dz + a·dx + b·dy`` (rotation about the sensor)."""
    dz, a, b = coef
    # Small rotations about the world y (by a) and x (by -b) axes through the sensor position.
    rot = np.array([[1.0, 0.0, a], [0.0, 1.0, b], [-a, -b, 1.0]])
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    out = pose.copy()
    p = pose[:3, 3]
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = p - np.array([0.0, 0.0, dz])
    return out
