"""Rows and labels: tree positions grouped into rows by robust regression, then labelled.

The row axis is the dominant orientation of the links between each tree and its nearest
neighbours (trees in a row are closer to each other than to the next row's), refined by
the direction that lines the trees up best across it. Trees are grouped by their offset
across that axis, a robust line (or, with ``curved_rows``, a parabola) is fitted to each
group, trees are reassigned to the nearest fitted row within ``max_distance_to_row``, and
the fit is repeated. Any bearing works, and gently curved rows too.

Labels follow the paper and the simulator: seen while driving along the row direction
``d``, rows are numbered 0, 1, ... from left to right; in each alley pair the left row
(even number) is ``L`` and the right row (odd) is ``R``; trees are numbered along ``d``.
``d`` is the first pass of the trajectory when one is known. Otherwise it is the row axis
pointing north (+y) of east-west, or east (+x) when the rows run exactly east-west.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canopy_kit.config import RowsConfig
from canopy_kit.errors import InputError

MIN_TREES_FOR_AXIS = 4  # fewer trees: the row axis is the driving direction when it is known


@dataclass(frozen=True)
class RowLine:
    """One fitted row: ``across = c0 + c1 * along + c2 * along**2`` in the row frame."""

    row: int
    direction: np.ndarray  # unit driving direction d (xy)
    coef: tuple[float, float, float]
    along_range: tuple[float, float]
    n_trees: int

    @property
    def right(self) -> np.ndarray:
        """Unit vector to the right of ``direction``."""
        return np.array([self.direction[1], -self.direction[0]])

    def offset(self, xy: np.ndarray) -> np.ndarray:
        """Signed distance (to the right, metres) of points ``xy`` from the row line."""
        xy = np.atleast_2d(xy)
        along, across = xy @ self.direction, xy @ self.right
        c0, c1, c2 = self.coef
        return across - (c0 + c1 * along + c2 * along**2)

    def polyline(self, n: int = 25) -> np.ndarray:
        """Points (n, 2) on the row line over the trees' extent, in driving order."""
        a = np.linspace(*self.along_range, n)
        c0, c1, c2 = self.coef
        return a[:, None] * self.direction + (c0 + c1 * a + c2 * a**2)[:, None] * self.right


@dataclass
class RowAssignment:
    """Row number, index along the row and label of every tree, plus the fitted rows."""

    row: np.ndarray
    index_in_row: np.ndarray
    labels: list[str]
    lines: list[RowLine]
    direction: np.ndarray
    direction_source: str
    warnings: list[str] = field(default_factory=list)

    @property
    def tree_ids(self) -> list[str]:
        """Stable identifiers: ``r<row>-<label>`` (``t<k>`` for trees in no row: when no rows
        were found, or a stray in an alley)."""
        return [f"r{r}-{lab}" if r >= 0 else lab.lower() for r, lab in zip(self.row, self.labels)]


def row_label(row: int, index: int) -> str:
    """The paper's label: L for even rows, R for odd rows (alley pairs), then the index."""
    return f"{'L' if row % 2 == 0 else 'R'}{index}"


def default_direction(axis: np.ndarray) -> np.ndarray:
    """The documented default driving direction: the row axis pointing north, else east."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    if abs(axis[1]) > 1e-9:
        return axis if axis[1] > 0 else -axis
    return axis if axis[0] > 0 else -axis


def bearing_to_vector(bearing_deg: float) -> np.ndarray:
    """Unit xy vector of a bearing in degrees clockwise from north (+y)."""
    b = np.radians(bearing_deg)
    return np.array([np.sin(b), np.cos(b)])


def driving_direction_from_trajectory(xy: np.ndarray, min_length: float = 5.0) -> np.ndarray:
    """Direction of travel at the start of a trajectory (N, 2): the first pass along a row.

    The heading is taken between the first position and the first one at least
    ``min_length`` metres away from it, so standing still at the start does not matter.
    """
    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    if len(xy) < 2:
        raise InputError("trajectory: need at least two positions for a driving direction")
    dist = np.linalg.norm(xy - xy[0], axis=1)
    far = np.flatnonzero(dist >= min_length)
    if len(far) == 0:
        raise InputError(f"trajectory: the robot never moves {min_length} m from its start")
    v = xy[far[0]] - xy[0]
    return v / np.linalg.norm(v)


def row_axis(xy: np.ndarray, bandwidth: float = 0.5) -> np.ndarray:
    """Unit vector along the rows (sign arbitrary) from tree positions (N, 2), N >= 2."""
    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    if n == 2:
        v = xy[1] - xy[0]
        return v / np.linalg.norm(v)
    from scipy.spatial import cKDTree

    k = min(3, n)
    _, nn = cKDTree(xy).query(xy, k=k)
    vec = xy[nn[:, 1:]].reshape(-1, 2) - np.repeat(xy, k - 1, axis=0)
    ang = np.mod(np.arctan2(vec[:, 1], vec[:, 0]), np.pi)
    # Mode of the link orientations (angles doubled: a line has no sign).
    grid = np.radians(np.arange(0.0, 180.0, 0.5))
    dens = np.cos(2 * (grid[:, None] - ang[None, :]))
    dens = np.exp(8.0 * (dens - 1.0)).sum(axis=1)
    # Refine: among directions near the mode, the one lining trees up best across it.
    mode = grid[int(np.argmax(dens))]
    cand = mode + np.radians(np.arange(-10.0, 10.01, 0.25))
    best, best_score = mode, -np.inf
    sample = xy if n <= 1500 else xy[np.random.default_rng(0).choice(n, 1500, replace=False)]
    for a in cand:
        normal = np.array([-np.sin(a), np.cos(a)])
        c = sample @ normal
        score = np.exp(-0.5 * ((c[:, None] - c[None, :]) / bandwidth) ** 2).sum()
        if score > best_score:
            best, best_score = a, score
    return np.array([np.cos(best), np.sin(best)])


def _fit_row(along: np.ndarray, across: np.ndarray, curved: bool) -> np.ndarray:
    """Robust (Huber, iteratively reweighted) fit of across vs along: [c0, c1, c2]."""
    n = len(along)
    deg = 2 if curved and n >= 5 else (1 if n >= 3 else 0)
    a0 = along.mean()
    scale = max(np.ptp(along), 1.0)
    t = (along - a0) / scale
    design = np.column_stack([t**p for p in range(deg + 1)])
    w = np.ones(n)
    coef = np.zeros(deg + 1)
    for _ in range(10):
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(design * sw[:, None], across * sw, rcond=None)
        r = np.abs(across - design @ coef)
        delta = 0.3
        w = np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))
    coef = np.concatenate([coef, np.zeros(3 - len(coef))])
    # Back to polynomials in ``along`` itself.
    c0, c1, c2 = coef
    return np.array(
        [
            c0 - c1 * a0 / scale + c2 * a0**2 / scale**2,
            c1 / scale - 2 * c2 * a0 / scale**2,
            c2 / scale**2,
        ]
    )


def _group_by_offset(across: np.ndarray, gap: float) -> np.ndarray:
    """1-D groups around the peaks of the offsets' density, peaks at least ``1.5 gap`` apart."""
    sigma = gap / 3.0
    grid = np.arange(across.min() - 3 * sigma, across.max() + 3 * sigma + 0.05, 0.05)
    dens = np.zeros(len(grid))
    for start in range(0, len(across), 2000):
        c = across[start : start + 2000]
        dens += np.exp(-0.5 * ((grid[:, None] - c[None, :]) / sigma) ** 2).sum(axis=1)
    is_peak = np.r_[False, (dens[1:-1] >= dens[:-2]) & (dens[1:-1] > dens[2:]), False]
    peaks: list[float] = []
    for i in np.flatnonzero(is_peak)[np.argsort(-dens[is_peak])]:
        if all(abs(grid[i] - p) >= 1.5 * gap for p in peaks):
            peaks.append(grid[i])
    if not peaks:
        peaks = [float(np.median(across))]
    centres = np.sort(np.array(peaks))
    return np.argmin(np.abs(across[:, None] - centres[None, :]), axis=1)


def _drop_empty(groups: np.ndarray) -> np.ndarray:
    _, inv = np.unique(groups, return_inverse=True)
    return inv.ravel()


def _stray_groups(groups: np.ndarray, offset: dict[int, float], min_trees: int) -> set[int]:
    """Small groups of trees in an alley, no row themselves (pieces of crowns).

    A group is small with fewer than ``min_trees`` trees or than half a typical row's. It is
    a stray when the rows on both sides of it stand as close together as neighbouring rows
    do elsewhere (less than 1.5 times their median spacing): no row fits between them. A
    small group where a row fits (a row cut short, replants) or at the edge (a short last
    row, the first trees of a streamed drive) stays a row. Needs three big rows to know
    their spacing."""
    sizes = {g: int(np.sum(groups == g)) for g in offset}
    rows = [g for g in offset if sizes[g] >= min_trees]
    if not rows:
        return set()
    small = max(float(min_trees), float(np.median([sizes[g] for g in rows])) / 2)
    big = np.sort([offset[g] for g in offset if sizes[g] >= small])
    if len(big) < 3:
        return set()
    spacing = float(np.median(np.diff(big)))
    strays = set()
    for g, where in offset.items():
        if sizes[g] >= small or not big[0] < where < big[-1]:
            continue
        right = int(np.searchsorted(big, where))
        if big[right] - big[right - 1] < 1.5 * spacing:
            strays.add(g)
    return strays


def assign_rows(
    xy: np.ndarray,
    config: RowsConfig | None = None,
    driving_direction: np.ndarray | None = None,
    direction_source: str | None = None,
) -> RowAssignment:
    """Group tree positions ``xy`` (N, 2) into rows and label them (see module docstring)."""
    config = config or RowsConfig()
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    if not config.max_distance_to_row > 0:
        raise InputError(
            f"rows.max_distance_to_row must be positive, got {config.max_distance_to_row}"
        )
    if driving_direction is None and config.driving_direction is not None:
        driving_direction = bearing_to_vector(config.driving_direction)
        direction_source = "rows.driving_direction"
    if n == 0:
        d = default_direction(
            np.array([0.0, 1.0]) if driving_direction is None else driving_direction
        )
        return RowAssignment(
            np.zeros(0, int), np.zeros(0, int), [], [], d, "none", ["no trees: no rows to label"]
        )
    # Links between two or three trees may cross an alley (a streamed drive emits the trees
    # on both sides of the first alley first): with so few, a known driving direction is the
    # better guess of the row axis.
    trust_direction = driving_direction is not None and n < MIN_TREES_FOR_AXIS
    d, source = _row_direction(xy, driving_direction, direction_source, trust_direction)
    right = np.array([d[1], -d[0]])
    along, across = xy @ d, xy @ right
    gap = config.max_distance_to_row
    groups, coefs = _group_into_rows(along, across, gap, config.curved_rows)
    mean_offset = {g: np.median(across[groups == g]) for g in coefs}
    # Where rows exist, trees in an alley between two of them (stray segments) are in no
    # row: numbering them as a row would shift the numbers, L/R sides and spacing of the
    # real rows.
    strays = _stray_groups(groups, mean_offset, config.min_trees_per_row)
    row, index, lines, resid = _number_rows(groups, coefs, mean_offset, strays, along, across, d)
    warnings: list[str] = []
    not_rows = _why_not_rows(row, lines, resid, along, across, config)
    if n >= 3 and not trust_direction and not_rows:
        warnings.append(
            f"no rows detected: {'; '.join(not_rows)}; trees are labelled T0, T1, ... instead"
        )
        order_xy = np.lexsort((xy[:, 0], xy[:, 1]))
        idx = np.empty(n, dtype=np.int64)
        idx[order_xy] = np.arange(n)
        return RowAssignment(np.full(n, -1), idx, [f"T{i}" for i in idx], [], d, source, warnings)
    n_off_rows = int(np.sum(row < 0))
    if n_off_rows:
        warnings.append(
            f"{n_off_rows} of {n} trees stand in the alleys between the {len(lines)} rows "
            f"(groups of fewer than rows.min_trees_per_row = {config.min_trees_per_row} or half a "
            "row's trees, where the rows on both sides stand no further apart than rows do "
            "elsewhere): labelled T0, T1, ... along the driving direction, in no row"
        )
    labels = [row_label(int(r), int(i)) if r >= 0 else f"T{i}" for r, i in zip(row, index)]
    return RowAssignment(row, index, labels, lines, d, source, warnings)


def _row_direction(
    xy: np.ndarray,
    driving_direction: np.ndarray | None,
    direction_source: str | None,
    trust_direction: bool,
) -> tuple[np.ndarray, str]:
    """The unit direction rows are read along (the row axis, pointed the way the robot first
    drove when that is known) and where its sense came from."""
    if len(xy) >= 2 and not trust_direction:
        axis = row_axis(xy)
    else:
        axis = (
            np.asarray(driving_direction, float)[:2]
            if driving_direction is not None
            else np.array([0.0, 1.0])
        )
        axis = axis / np.linalg.norm(axis)
    if driving_direction is not None:
        dd = np.asarray(driving_direction, float)[:2]
        dd = dd / np.linalg.norm(dd)
        return (axis if axis @ dd >= 0 else -axis), direction_source or "given"
    return default_direction(axis), "default (row axis pointing north of east-west)"


def _group_into_rows(
    along: np.ndarray, across: np.ndarray, gap: float, curved: bool
) -> tuple[np.ndarray, dict]:
    """Groups of trees by their offset across the rows, refined (up to 3 times) by moving each
    tree to the nearest fitted row line; trees further than ``gap`` from every line start
    rows of their own. Returns each tree's group and each group's line coefficients."""
    n = len(along)
    groups = _group_by_offset(across, gap)
    for _ in range(3):
        coefs = {}
        for g in np.unique(groups):
            m = groups == g
            coefs[g] = _fit_row(along[m], across[m], curved)
        keys = list(coefs)
        resid = np.stack(
            [across - (coefs[g][0] + coefs[g][1] * along + coefs[g][2] * along**2) for g in keys],
            axis=1,
        )
        nearest = np.argmin(np.abs(resid), axis=1)
        new = np.array(keys)[nearest]
        far = np.abs(resid[np.arange(n), nearest]) > gap
        if far.any():  # trees far from every row start rows of their own
            new[far] = max(keys) + 1 + _group_by_offset(across[far], gap)
        new = _drop_empty(new)
        if np.array_equal(new, groups):
            break
        groups = new
    coefs = {
        g: _fit_row(along[groups == g], across[groups == g], curved) for g in np.unique(groups)
    }
    return groups, coefs


def _number_rows(
    groups: np.ndarray,
    coefs: dict,
    mean_offset: dict,
    strays: set,
    along: np.ndarray,
    across: np.ndarray,
    d: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, list[RowLine], np.ndarray]:
    """Rows numbered left to right as seen along ``d`` (strays: row -1), trees numbered along
    each row (strays along ``d`` among themselves). Returns each tree's row, index and offset
    from its row's line, and the rows' lines."""
    n = len(groups)
    # Rows left to right as seen along d: increasing offset to the right.
    order = sorted(set(coefs) - strays, key=lambda g: mean_offset[g])
    row_of_group = {g: r for r, g in enumerate(order)} | {g: -1 for g in strays}
    row = np.array([row_of_group[g] for g in groups], dtype=np.int64)
    index = np.zeros(n, dtype=np.int64)
    lines: list[RowLine] = []
    resid = np.zeros(n)
    for g in order:
        m = np.flatnonzero(groups == g)
        m = m[np.argsort(along[m], kind="stable")]
        index[m] = np.arange(len(m))
        c = coefs[g]
        resid[m] = across[m] - (c[0] + c[1] * along[m] + c[2] * along[m] ** 2)
        lines.append(
            RowLine(
                row_of_group[g],
                d,
                tuple(map(float, c)),
                (float(along[m].min()), float(along[m].max())),
                len(m),
            )
        )
    off_rows = np.flatnonzero(row < 0)
    index[off_rows[np.argsort(along[off_rows], kind="stable")]] = np.arange(len(off_rows))
    return row, index, lines, resid


def _why_not_rows(
    row: np.ndarray,
    lines: list[RowLine],
    resid: np.ndarray,
    along: np.ndarray,
    across: np.ndarray,
    config: RowsConfig,
) -> list[str]:
    """Why the candidate rows are not an orchard's (empty when they are): in an orchard most
    trees stand in rows, on their row's line, and closer together along a row than the rows
    stand apart."""
    n = len(row)
    gap = config.max_distance_to_row
    in_rows = np.isin(row, [ln.row for ln in lines if ln.n_trees >= config.min_trees_per_row])
    spread = np.median(np.abs(resid[in_rows])) if in_rows.any() else np.inf
    centres = np.sort([np.median(across[row == ln.row]) for ln in lines])
    spacing = np.median(np.diff(centres)) if len(centres) > 1 else np.inf
    steps = [np.diff(np.sort(along[row == ln.row])) for ln in lines if ln.n_trees >= 2]
    in_row = np.median(np.concatenate(steps)) if steps else np.inf
    off_line = min(gap / 3, 0.15 * spacing)
    not_rows = []
    if in_rows.mean() < 0.8:
        not_rows.append(
            f"only {in_rows.sum()} of {n} trees lie in rows of at least "
            f"{config.min_trees_per_row} trees (an orchard: 80 % or more)"
        )
    if np.isfinite(spread) and spread > off_line:
        not_rows.append(
            f"trees stand a median {spread:.2f} m off their row's line (an orchard: under "
            f"{off_line:.2f} m; rows.max_distance_to_row = {gap} m)"
        )
    if len(lines) > 1 and in_row >= spacing:
        not_rows.append(
            f"the candidate rows are {spacing:.1f} m apart, closer than their trees stand "
            f"along them ({in_row:.1f} m): in an orchard the trees of a row stand closer"
        )
    return not_rows
