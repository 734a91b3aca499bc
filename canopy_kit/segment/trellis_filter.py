"""Posts and wires out of a row section: a fruiting wall's trellis is not canopy (issue 52).

A fruiting wall's posts (about 0.1 m thick, taller than the wall, and at both ends of the
row) and wires (a few mm, along the row) would otherwise set a section's height and stretch
the row past its trees. In the section's across-row x height grid (occupied cells, one-cell
gaps across closed), a post is a column at most ``TRELLIS_MAX_WIDTH_M`` (0.3 m) wide
standing at least ``POLE_MIN_HEIGHT_M`` (0.3 m) where no canopy is beside it, and narrow
along the row too about one line, upright or leaning (the middle half of its returns within
0.15 m of the line fitted along the row against height, at most ``MAX_POST_LEAN_DEG``: a
wall's face seen without its inside is as narrow across, but runs the section's length at
every height), and which does not go on into the neighbouring sections (returns as high as
its top within 0.3 m beyond the section, 0.15-0.45 m from its line along the row, and not
found to be a post there: the tip of a crown reaching into a section is as narrow as a post
within it; a leaning anchor post crosses several sections, and a section beside one where a
post was found is judged again without it); a wire seen end-on is an isolated blob at most 0.3 m across
and high (unless, short along the row, it goes on beyond the section as a crown's tip does);
both are left out. (A post's returns in the canopy's top cell layer still count, 0.1 m at
most; a post sticking out of the wall by less than 0.3 m, or a wire touching the canopy, can
raise a section's height by that much. A crown's top is far wider than 0.3 m for more than a
few millimetres below its apex.)

One rule for both users (:func:`trellis_along_row`): the row profile
(:mod:`canopy_kit.segment.row_profile`) leaves the trellis out of each 1 m section, and the
segmentation (:func:`trellis_in_segments`, called by ``segment.verb.segment``) takes it out
of the tree segments, so that no post sets a tree's height or stretches an end tree.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage

TRELLIS_MAX_WIDTH_M = 0.3  # posts and wires (end-on) are at most this wide in a section grid
POLE_MIN_HEIGHT_M = 0.3  # a narrow column at least this tall is a post, not a crown's top
MIN_RETURNS = 3  # returns that show canopy going on (row_profile.MIN_CELL_POINTS)
SECTION_M = 1.0  # row sections the rule looks at (row_profile.SECTION_M)
CELL_M = 0.1  # across-row x height grid cell (row_profile.CELL_M)
MAX_POST_LEAN_DEG = 35.0  # anchor posts lean 10-30 deg out of a row's end


def clustered(offset: np.ndarray, height: np.ndarray, cell_m: float, min_points: int) -> np.ndarray:
    """Which points' ``cell_m`` cell of the across-row x height grid holds ``min_points``."""
    if len(offset) == 0:
        return np.zeros(0, bool)
    i = np.floor(offset / cell_m).astype(np.int64)
    j = np.floor(height / cell_m).astype(np.int64)
    i -= i.min()
    j -= j.min()
    key = i * (int(j.max()) + 1) + j  # one integer per cell: a 1-D count, not rows of pairs
    if key.max() <= 8 * len(key) + 1_000_000:
        return np.bincount(key)[key] >= min_points
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse] >= min_points


def _goes_on(
    offset: np.ndarray,
    height: np.ndarray,
    along: np.ndarray,
    beside: np.ndarray | None,
    cell_m: float,
    min_points: int = MIN_RETURNS,
    line: tuple[float, float] | None = None,
) -> bool:
    """Whether canopy goes on beyond the section from a narrow part of it (a crown's tip
    reaching in): ``min_points`` returns of ``beside`` as high as its top, within
    ``TRELLIS_MAX_WIDTH_M`` of it across and more than half that but at most 1.5 times that
    from its line along the row (``line``: its along-row position at height 0 and per metre
    of height; None: upright at its median), spread wider or higher than that (a wire going
    on is as thin as it is here; a leaning post going on lies on its line)."""
    if beside is None or len(beside) == 0 or len(offset) == 0:
        return False
    w = TRELLIS_MAX_WIDTH_M
    a0, slope = (float(np.median(along)), 0.0) if line is None else line
    off_line = np.abs(beside[:, 2] - a0 - slope * beside[:, 1])  # along the row, at its height
    near = beside[
        (beside[:, 1] >= height.max() - cell_m)
        & (beside[:, 0] >= offset.min() - w)
        & (beside[:, 0] <= offset.max() + w)
        & (off_line > w / 2)  # not the post going on
        & (off_line <= 1.5 * w)  # but next to it
    ]
    if len(near) < min_points:
        return False
    return bool(np.ptp(near[:, 0]) > w or np.ptp(near[:, 1]) > w)


def _post_line(along: np.ndarray, height: np.ndarray) -> tuple[float, float]:
    """A narrow part's line along the row: its position at height 0 and its lean (metres along
    per metre up), fitted to its returns and kept within ``MAX_POST_LEAN_DEG`` (upright at the
    median when the returns span less than ``POLE_MIN_HEIGHT_M`` of height)."""
    if len(along) < 3 or np.ptp(height) < POLE_MIN_HEIGHT_M:
        return float(np.median(along)), 0.0
    slope = float(np.polyfit(height, along, 1)[0])
    limit = np.tan(np.radians(MAX_POST_LEAN_DEG))
    slope = float(np.clip(slope, -limit, limit))
    return float(np.median(along - slope * height)), slope


def without_trellis(
    offset: np.ndarray,
    height: np.ndarray,
    along: np.ndarray,
    cell_m: float,
    beside: np.ndarray | None = None,
    min_points: int = MIN_RETURNS,
) -> np.ndarray:
    """Which points of a row section (across-row ``offset``, ``height`` above the ground,
    ``along`` the row) are left when posts and wires are taken out (module docstring): a
    post is narrow across the row and along it, a wall's face only across, and a crown's tip
    reaching into the section goes on beyond it (``beside``: the points just outside the
    section, as (offset, height, along) rows; ``min_points`` of them show it)."""
    keep = np.ones(len(offset), bool)
    if len(offset) == 0:
        return keep
    i = np.floor((offset - offset.min()) / cell_m).astype(np.int64) + 1
    j = np.floor((height - height.min()) / cell_m).astype(np.int64) + 1
    occupied = np.zeros((i.max() + 2, j.max() + 2), dtype=bool)  # a free border
    occupied[i, j] = True
    across = np.array([[0, 1, 0], [0, 1, 0], [0, 1, 0]], bool)  # neighbours across the row
    grid = ndimage.binary_closing(occupied, structure=across) | occupied  # one-cell gaps
    narrow_cells = max(1, round(TRELLIS_MAX_WIDTH_M / cell_m))
    runs, _ = ndimage.label(grid, structure=across)  # per height level, runs across the row
    narrow = grid & (np.bincount(runs.ravel())[runs] <= narrow_cells)
    trellis = np.zeros_like(grid)
    parts, _ = ndimage.label(narrow, structure=np.ones((3, 3), bool))
    part_of_point = parts[i, j]
    for k, box in enumerate(ndimage.find_objects(parts), start=1):
        if (box[1].stop - box[1].start) * cell_m < POLE_MIN_HEIGHT_M - 1e-9:
            continue
        mine = part_of_point == k
        a = along[mine]
        if len(a) == 0:
            continue
        # most of its returns within half the width of one line along the row, upright or
        # leaning: a post (a wire meeting it adds a few); a face runs along the section
        line = _post_line(a, height[mine])
        residual = a - line[0] - line[1] * height[mine]
        if np.ptp(np.percentile(residual, [25, 75])) > TRELLIS_MAX_WIDTH_M / 2:
            continue
        if not _goes_on(offset[mine], height[mine], a, beside, cell_m, min_points, line):
            trellis[box] |= parts[box] == k
    # what is left of a post, and wires end-on: small isolated blobs
    blobs, _ = ndimage.label(grid & ~trellis, structure=np.ones((3, 3), bool))
    blob_of_point = blobs[i, j]
    for k, box in enumerate(ndimage.find_objects(blobs), start=1):
        if box is None or any(b.stop - b.start > narrow_cells for b in box):
            continue
        mine = blob_of_point == k
        a = along[mine]
        # a wire runs along the section; a crown's tip reaching in is short and goes on
        tip = len(a) and np.ptp(np.percentile(a, [25, 75])) <= TRELLIS_MAX_WIDTH_M / 2
        if not (tip and _goes_on(offset[mine], height[mine], a, beside, cell_m, min_points)):
            trellis[box] |= blobs[box] == k
    return ~trellis[i, j]


def trellis_along_row(
    along: np.ndarray,
    offset: np.ndarray,
    height: np.ndarray,
    start: float,
    n_sections: int,
    section_m: float = SECTION_M,
    cell_m: float = CELL_M,
    min_cell_points: int = MIN_RETURNS,
) -> np.ndarray:
    """Which of a row's points (``along`` the row, ``offset`` across it, ``height`` above the
    ground) are posts or wires: per section of ``section_m`` from ``start``, the returns in
    grid cells holding ``min_cell_points`` go through :func:`without_trellis`, with the points
    up to a post's width beyond the section showing whether canopy goes on. Sparse returns
    count with a post or wire found within one cell of them (the row profile ignores them);
    points outside the sections are not judged (False)."""
    along, offset, height = (np.asarray(v, float).ravel() for v in (along, offset, height))
    trellis = np.zeros(len(along), bool)
    if len(along) == 0 or n_sections <= 0:
        return trellis
    margin = TRELLIS_MAX_WIDTH_M
    order = np.argsort(along, kind="stable")
    a_sorted = along[order]
    edges = start + np.arange(n_sections + 1) * section_m
    bounds = np.searchsorted(a_sorted, edges)
    windows = np.searchsorted(a_sorted, np.column_stack([edges[:-1] - margin, edges[1:] + margin]))
    filled = np.flatnonzero(np.diff(bounds) > 0)
    found = np.zeros(n_sections, bool)

    def judge(s: int) -> None:
        members = order[bounds[s] : bounds[s + 1]]
        dense = members[clustered(offset[members], height[members], cell_m, min_cell_points)]
        if len(dense) == 0:
            return
        lo, hi = windows[s]
        beside = order[np.r_[lo : bounds[s], bounds[s + 1] : hi]]
        beside = beside[~trellis[beside]]  # a post found beyond is not canopy going on
        near = np.column_stack([offset[beside], height[beside], along[beside]])
        kept = without_trellis(
            offset[dense], height[dense], along[dense], cell_m, near, min_cell_points
        )
        found[s] |= bool((~kept).any())
        trellis[dense[~kept]] = True
        # sparse returns next to a post or wire (a post's cap) are part of it
        cells = _cells(offset[dense[~kept]], height[dense[~kept]], cell_m)
        if len(cells):
            near_cells = (cells[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 2)
            sparse = np.setdiff1d(members, dense)
            mine = _cells(offset[sparse], height[sparse], cell_m)
            trellis[sparse[_in(mine, near_cells)]] = True

    for s in filled:
        judge(s)
    # once more beside a section where a post was found: the end of a leaning post crossing
    # into this section went on into that post, which is no canopy going on
    beside_post = np.zeros(n_sections, bool)
    beside_post[1:] |= found[:-1]
    beside_post[:-1] |= found[1:]
    for s in filled[beside_post[filled]]:
        judge(s)
    return trellis


_NEIGHBOURS = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)])


def _cells(offset: np.ndarray, height: np.ndarray, cell_m: float) -> np.ndarray:
    return np.column_stack([np.floor(offset / cell_m), np.floor(height / cell_m)]).astype(np.int64)


def _in(cells: np.ndarray, of: np.ndarray) -> np.ndarray:
    """Which rows of ``cells`` (K, 2) are among the rows of ``of``."""
    key = lambda c: c[:, 0] * 1_000_003 + c[:, 1]  # noqa: E731
    return np.isin(key(cells), key(of))


def trellis_in_segments(
    xy: np.ndarray,
    height: np.ndarray,
    labels: np.ndarray,
    rows: Any,
    segment_row: np.ndarray,
    section_m: float = SECTION_M,
) -> np.ndarray:
    """Which labelled map points are posts or wires (:func:`trellis_along_row` per fitted row
    of ``rows``, a ``segment.rows.RowAssignment``, on the points of the segments in it:
    ``segment_row`` per segment label)."""
    labels = np.asarray(labels)
    trellis = np.zeros(len(labels), bool)
    segment_row = np.asarray(segment_row)
    for line in rows.lines:
        mine = np.flatnonzero(labels >= 0)
        mine = mine[segment_row[labels[mine]] == line.row]
        if len(mine) == 0:
            continue
        along = xy[mine] @ line.direction
        first = np.floor(along.min() / section_m) * section_m
        n = int(np.floor((along.max() - first) / section_m)) + 1
        found = trellis_along_row(along, line.offset(xy[mine]), height[mine], first, n, section_m)
        trellis[mine[found]] = True
    return trellis
