"""Which of a session's trees is which of the orchard's known trees: align, then match.

Positions come from each session's GNSS-georeferenced map, so two visits of one orchard
differ by a shift of up to a few metres (GNSS) and a small rotation. The session is first
shifted by the mode of the offsets between nearby tree pairs (a vote that a regular
planting pattern cannot fool as long as the GNSS error is under half the tree spacing),
then refined by a rigid fit on matched pairs (ICP on tree positions). Matching is a
minimum-distance assignment (Hungarian, per connected group of candidates) within a gate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from canopy_kit.errors import ConfigError


@dataclass
class MatchSettings:
    """How a session is aligned to the orchard and how far a tree may be from its match."""

    gate_m: float = 1.5  # a session tree farther than this from every known tree is new
    search_m: float = 4.0  # the largest GNSS offset between two sessions that is looked for
    refine: Literal["rigid", "translation", "none"] = "rigid"
    coverage_m: float = 2.5  # unmatched known trees within this of the session's area are missing
    max_iterations: int = 10

    def check(self) -> None:
        """Reject settings that cannot work, naming the setting."""
        for name in ("gate_m", "search_m", "coverage_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"match.{name} must be positive, got {getattr(self, name)}")
        if self.refine not in ("rigid", "translation", "none"):
            raise ConfigError(
                f"match.refine: {self.refine!r} is not one of rigid, translation, none"
            )


@dataclass
class Alignment:
    """Session → orchard frame: rotate by ``rotation_deg`` about the origin, then shift."""

    rotation_deg: float = 0.0
    dx: float = 0.0
    dy: float = 0.0
    rms_m: float = float("nan")  # residual of the matched pairs after alignment
    n_pairs: int = 0
    method: str = "none"

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Aligned positions of ``xy`` (N, 2)."""
        a = np.radians(self.rotation_deg)
        r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return np.asarray(xy, float).reshape(-1, 2) @ r.T + [self.dx, self.dy]


@dataclass
class TreeMatch:
    """The outcome for one session against the known trees."""

    alignment: Alignment
    pairs: np.ndarray  # (K, 2): session index, known index
    distances: np.ndarray  # (K,) metres after alignment
    new: np.ndarray  # session indices without a known tree
    missing: np.ndarray  # known indices near the session's trees but not matched
    aligned: np.ndarray  # (N, 2) session positions in the orchard frame


def assign(
    session_xy: np.ndarray, known_xy: np.ndarray, gate: float
) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-total-distance one-to-one pairs within ``gate``: (K, 2) indices and distances."""
    from scipy.optimize import linear_sum_assignment
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n, m = len(session_xy), len(known_xy)
    if n == 0 or m == 0:
        return np.zeros((0, 2), int), np.zeros(0)
    dist = cKDTree(known_xy).sparse_distance_matrix(
        cKDTree(session_xy), gate, output_type="coo_matrix"
    )
    kj, si, d = dist.row, dist.col, dist.data
    if len(d) == 0:
        return np.zeros((0, 2), int), np.zeros(0)
    graph = coo_matrix((np.ones(len(d)), (si, n + kj)), shape=(n + m, n + m))
    _, comp = connected_components(graph, directed=False)
    edge_comp = comp[si]
    order = np.argsort(edge_comp, kind="stable")
    bounds = np.flatnonzero(np.diff(edge_comp[order])) + 1
    pairs, dists = [], []
    for group in np.split(order, bounds):
        if len(group) == 1:  # the common case: one session tree, one known tree
            pairs.append([[si[group[0]], kj[group[0]]]])
            dists.append(d[group])
            continue
        rows, r_inv = np.unique(si[group], return_inverse=True)
        cols, c_inv = np.unique(kj[group], return_inverse=True)
        cost = np.full((len(rows), len(cols)), 1e6)
        cost[r_inv, c_inv] = d[group]
        ri, ci = linear_sum_assignment(cost)
        ok = cost[ri, ci] <= gate
        pairs.append(np.column_stack([rows[ri[ok]], cols[ci[ok]]]))
        dists.append(cost[ri[ok], ci[ok]])
    return np.concatenate(pairs).astype(int).reshape(-1, 2), np.concatenate(dists)


def coarse_offset(
    session_xy: np.ndarray, known_xy: np.ndarray, search: float, gate: float, seed: int = 0
) -> tuple[np.ndarray, int]:
    """The shift most tree pairs agree on (a vote over offsets within ``search``) and its support."""
    from scipy.spatial import cKDTree

    near = cKDTree(known_xy).query_ball_point(session_xy, search)
    counts = np.array([len(k) for k in near])
    if counts.sum() == 0:
        return np.zeros(2), 0
    k = np.concatenate([np.asarray(v, int) for v in near])
    s = np.repeat(np.arange(len(session_xy)), counts)
    deltas = known_xy[k] - session_xy[s]
    rng = np.random.default_rng(seed)
    candidates = (
        deltas if len(deltas) <= 4000 else deltas[rng.choice(len(deltas), 4000, replace=False)]
    )
    tree = cKDTree(deltas)
    support = tree.query_ball_point(candidates, gate / 2, return_length=True).astype(float)
    # Ties (a regular pattern shifted by one tree) go to the smaller shift: GNSS is unbiased.
    score = support - 1e-3 * np.linalg.norm(candidates, axis=1) / search
    best = candidates[int(np.argmax(score))]
    members = tree.query_ball_point(best, gate / 2)
    return deltas[members].mean(axis=0), len(members)


def rigid_fit(a: np.ndarray, b: np.ndarray, rotate: bool = True) -> tuple[float, np.ndarray]:
    """Rotation (radians) and shift that best map points ``a`` onto ``b`` (2-D Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    if not rotate or len(a) < 3:
        return 0.0, cb - ca
    h = (a - ca).T @ (b - cb)
    angle = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    r = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return angle, cb - r @ ca


def match_trees(
    session_xy: np.ndarray, known_xy: np.ndarray, settings: MatchSettings | None = None
) -> TreeMatch:
    """Align a session's tree positions to the known trees and pair them up."""
    st = settings or MatchSettings()
    st.check()
    session_xy = np.asarray(session_xy, float).reshape(-1, 2)
    known_xy = np.asarray(known_xy, float).reshape(-1, 2)
    alignment = Alignment()
    if len(known_xy) and len(session_xy) and st.refine != "none":
        shift, _ = coarse_offset(session_xy, known_xy, st.search_m, st.gate_m)
        angle, t = 0.0, shift
        previous = None
        for _ in range(st.max_iterations):
            current = Alignment(np.degrees(angle), *t)
            pairs, _ = assign(current.apply(session_xy), known_xy, st.gate_m)
            if len(pairs) == 0 or (previous is not None and np.array_equal(pairs, previous)):
                break
            previous = pairs
            angle, t = rigid_fit(
                session_xy[pairs[:, 0]],
                known_xy[pairs[:, 1]],
                rotate=st.refine == "rigid" and len(pairs) >= 3,
            )
        alignment = Alignment(float(np.degrees(angle)), float(t[0]), float(t[1]), method=st.refine)
    aligned = alignment.apply(session_xy)
    pairs, dist = assign(aligned, known_xy, st.gate_m)
    alignment.n_pairs = len(pairs)
    alignment.rms_m = float(np.sqrt(np.mean(dist**2))) if len(dist) else float("nan")
    new = np.setdiff1d(np.arange(len(session_xy)), pairs[:, 0])
    unmatched = np.setdiff1d(np.arange(len(known_xy)), pairs[:, 1])
    inside = within_area(known_xy[unmatched], aligned, st.coverage_m)
    return TreeMatch(alignment, pairs, dist, new, unmatched[inside], aligned)


def within_area(xy: np.ndarray, trees: np.ndarray, margin: float) -> np.ndarray:
    """Points ``xy`` inside the convex hull of ``trees`` grown by ``margin`` (the area a
    session looked at: a tree gone from the middle of it is missing, a block not driven is not)."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) == 0 or len(trees) == 0:
        return np.zeros(len(xy), bool)
    if len(trees) < 3:
        return cKDTree(trees).query(xy)[0] <= margin
    try:
        hull = ConvexHull(trees, qhull_options="QJ")  # joggled: a single row is a thin hull
    except QhullError:
        return cKDTree(trees).query(xy)[0] <= margin
    eq = hull.equations  # unit outward normals and offsets: n·x + c <= 0 inside
    return np.all(xy @ eq[:, :2].T + eq[:, 2] <= margin, axis=1)
