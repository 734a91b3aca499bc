"""Orchard layout: rows of trees with crowns, trunks and branches, from a seed and a spec.

Conventions (also in docs/SIMULATOR.md): rows run along the unit vector ``d`` (bearing
``row_bearing_deg`` from north); rows are numbered 0, 1, ... from left to right as seen
driving along ``d``; trees are numbered along ``d``. Labels follow the paper: seen from the
alley between rows 2k and 2k+1 while driving along ``d``, row 2k is on the left (``L0,
L1, ...``) and row 2k+1 on the right (``R0, R1, ...``); ``(row, label)`` is unique.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from canopy_kit.core.geo import LocalFrame
from canopy_kit.sim.config import OrchardSpec
from canopy_kit.sim.crown import CrownEnvelope
from canopy_kit.sim.crown_forms import FORM_NAMES, LobedForm, VaseForm, hedge_planes
from canopy_kit.sim.terrain import Terrain
from canopy_kit.sim.trellis import RowTrellis, build_trellis


@dataclass(frozen=True)
class Tree:
    """One tree: identity, trunk base, crown envelope, woody parts, crown form and leaf density.

    ``foliage_scale`` multiplies the orchard's foliage densities (sparse young trees);
    ``young``: drawn young (``OrchardSpec.young_probability``), its crown scaled down.
    """

    tree_id: int
    row: int
    index_in_row: int
    label: str
    base: tuple[float, float, float]
    crown: CrownEnvelope
    trunk_top: tuple[float, float, float]
    trunk_radius: float
    branch_tips: tuple[tuple[float, float, float], ...]
    doubled: bool = False
    crown_form: str = "ellipsoid"
    foliage_scale: float = 1.0
    young: bool = False

    @property
    def crown_base_height(self) -> float:
        """Height of the crown's lowest point above the trunk base."""
        return self.crown.z_range[0] - self.base[2]

    @property
    def height(self) -> float:
        """Tree height: crown top above the trunk base."""
        return self.crown.z_range[1] - self.base[2]


@dataclass
class Orchard:
    """The generated orchard: trees, terrain, frame and the layout vectors."""

    spec: OrchardSpec
    trees: list[Tree]
    terrain: Terrain
    frame: LocalFrame
    row_direction: np.ndarray
    right_direction: np.ndarray
    row_offsets: np.ndarray
    along_range: tuple[float, float]
    extra: dict = field(default_factory=dict)
    trellis: list[RowTrellis] = field(default_factory=list)  # posts, wires, drip line per row

    def to_local(self, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        """Orchard (along-row, across-row) coordinates to local (x, y)."""
        along = np.asarray(along, float)
        across = np.asarray(across, float)
        return along[..., None] * self.row_direction + across[..., None] * self.right_direction

    def to_orchard(self, xy: np.ndarray) -> np.ndarray:
        """Local (x, y) to (along-row, across-row)."""
        xy = np.asarray(xy, float)
        return np.stack([xy @ self.row_direction, xy @ self.right_direction], axis=-1)


def row_label(row: int, index: int) -> str:
    """The paper's label of a tree: L/R by the row's side in its alley pair, then the index."""
    return f"{'L' if row % 2 == 0 else 'R'}{index}"


def generate_orchard(spec: OrchardSpec, rng: np.random.Generator) -> Orchard:
    """Lay out rows and trees and grow their crowns, deterministically from ``rng``."""
    bearing = np.radians(spec.row_bearing_deg)
    d = np.array([np.sin(bearing), np.cos(bearing)])
    right = np.array([d[1], -d[0]])
    frame = LocalFrame.at(spec.origin_lat, spec.origin_lon, spec.origin_height)
    terrain = Terrain.random(
        rng,
        d,
        spec.terrain_slope_deg,
        spec.terrain_cross_slope_deg,
        spec.terrain_bump_amplitude,
        spec.terrain_bump_wavelength,
    )
    row_offsets = np.arange(spec.rows) * spec.row_spacing
    trees: list[Tree] = []
    along_max = 0.0
    for row in range(spec.rows):
        stations = _row_stations(spec, rng)
        along_max = max(along_max, stations[-1][0] if stations else 0.0)
        length = max(stations[-1][0], 1e-9) if stations else 1.0
        row_trees: list[Tree] = []
        for index, (along, doubled) in enumerate(stations):
            bow = spec.row_bow * (1.0 - (2.0 * along / length - 1.0) ** 2)
            jitter = rng.normal(0.0, spec.position_jitter, 2)
            a, c = along + jitter[0], row_offsets[row] + bow + jitter[1]
            xy = a * d + c * right
            # drawn only when asked for: other layouts keep their draws
            young = spec.young_probability > 0 and rng.random() < spec.young_probability
            tree = _grow_tree(
                spec, rng, len(trees) + len(row_trees), row, index, xy, d, terrain, doubled, young
            )
            row_trees.append(tree)
        row_trees = _fit_crowns(spec, row_trees, d, right, row_offsets[row])
        trees.extend(row_trees)
    # Removal after the layout is drawn: the other trees keep their ids, places and shapes.
    removed = set(spec.removed_trees) - set(spec.replanted_trees)
    trees = [t for t in trees if t.tree_id not in removed]
    spans: dict[int, tuple[float, float]] = {}
    for t in trees:
        a = float(np.dot(t.base[:2], d))
        lo, hi = spans.get(t.row, (a, a))
        spans[t.row] = (min(lo, a), max(hi, a))
    trellis = build_trellis(spec, spans, row_offsets, d, right, terrain)
    return Orchard(
        spec, trees, terrain, frame, d, right, row_offsets, (0.0, along_max), trellis=trellis
    )


def _row_stations(spec: OrchardSpec, rng: np.random.Generator) -> list[tuple[float, bool]]:
    """Along-row positions of the trees of one row, with missing and doubled trees."""
    lo, hi = spec.spacing_range
    stations: list[tuple[float, bool]] = []
    along = 0.0
    for i in range(spec.trees_per_row):
        if i > 0:
            along += rng.uniform(lo, hi)
        if rng.random() < spec.missing_probability and 0 < i < spec.trees_per_row - 1:
            continue
        stations.append((along, False))
        if rng.random() < spec.double_probability and i < spec.trees_per_row - 1:
            stations.append((along + rng.uniform(*spec.double_offset_range), True))
    stations.sort()
    return stations


def _grow_tree(
    spec: OrchardSpec,
    rng: np.random.Generator,
    tree_id: int,
    row: int,
    index: int,
    xy: np.ndarray,
    d: np.ndarray,
    terrain: Terrain,
    doubled: bool,
    young: bool = False,
) -> Tree:
    form = spec.crown_form
    if form == "mix":  # drawn only for mixed orchards: the other forms keep their draws
        form = FORM_NAMES[int(rng.integers(len(FORM_NAMES)))]
    diameter = rng.uniform(*spec.crown_diameter_range) * (rng.uniform(0.7, 0.9) if doubled else 1.0)
    # Growth scales the drawn crown (the draws stay the same, so the layout does too).
    diameter *= spec.replanted_crown_scale if tree_id in spec.replanted_trees else spec.crown_scale
    if young:
        diameter *= spec.young_crown_scale
    if form == "sparse":
        diameter *= spec.sparse_crown_scale
    a = diameter / 2.0
    b = a * rng.uniform(*spec.crown_across_ratio_range)
    crown_height = diameter * rng.uniform(*spec.crown_height_ratio_range)
    c_up, c_down = 0.55 * crown_height, 0.45 * crown_height
    if form == "vase":  # star-shaped from the trunk top, low in the crown
        c_up, c_down = 1.0 * crown_height, 0.2 * crown_height
    base_z = float(terrain.height(xy[0], xy[1]))
    crown_base = rng.uniform(*spec.crown_base_height_range)
    lean_dir = rng.uniform(0, 2 * np.pi)
    lean = rng.uniform(0.0, spec.lean_max)
    lean_xy = lean * np.array([np.cos(lean_dir), np.sin(lean_dir)])
    center = (xy[0] + lean_xy[0], xy[1] + lean_xy[1], base_z + crown_base + c_down)
    n_lobes = spec.crown_lobes
    dirs = rng.normal(size=(n_lobes, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    amps = rng.uniform(-1.0, 1.0, n_lobes) * spec.crown_irregularity * 2.0
    yaw = float(np.arctan2(d[1], d[0]) + rng.normal(0.0, 0.15))
    crown = CrownEnvelope(
        tuple(map(float, center)),
        (a, b, c_up, c_down),
        yaw,
        float(rng.uniform(*spec.crown_squareness_range)),
        tuple(map(tuple, dirs.tolist())),
        tuple(amps.tolist()),
        float(rng.uniform(2.5, 5.0)),
    )
    if form != "ellipsoid":
        crown = _shape_crown(spec, rng, crown, form, xy, d)
    foliage = spec.sparse_foliage_scale if form == "sparse" else 1.0
    return _attach_wood(
        spec,
        rng,
        Tree(
            tree_id,
            row,
            index,
            row_label(row, index),
            (float(xy[0]), float(xy[1]), base_z),
            crown,
            center,
            0.1,
            (),
            doubled,
            form,
            foliage,
            young,
        ),
    )


def _shape_crown(
    spec: OrchardSpec,
    rng: np.random.Generator,
    crown: CrownEnvelope,
    form: str,
    xy: np.ndarray,
    d: np.ndarray,
) -> CrownEnvelope:
    """Give a drawn crown its form (``crown_forms``); ``sparse`` keeps the ellipsoid."""
    a, b, c_up, _ = crown.semi_axes
    if form == "lobed":  # one lobe per scaffold limb, azimuths spread round the tree
        n = int(rng.integers(spec.branches_range[0], spec.branches_range[1] + 1))
        az = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n + rng.normal(0, 0.25, n)
        el = np.radians(rng.uniform(20.0, 55.0, n))
        dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return replace(
            crown,
            form=LobedForm(
                tuple(map(tuple, dirs.tolist())),
                float(rng.uniform(*spec.lobe_hollow_range)),
                float(rng.uniform(4.0, 7.0)),
            ),
        )
    if form == "vase":
        return replace(
            crown, form=VaseForm(float(rng.uniform(0.88, 0.95)), float(rng.uniform(0.55, 0.75)))
        )
    if form == "hedged":
        right = np.array([d[1], -d[0]])
        half_width = spec.hedge_cut * b
        return replace(
            crown,
            form=hedge_planes(
                right, crown.center, float(xy @ right), half_width, spec.hedge_cut * c_up
            ),
        )
    return crown


def _attach_wood(spec: OrchardSpec, rng: np.random.Generator, tree: Tree) -> Tree:
    """Trunk from the base to just inside the crown, and branches towards the crown shell."""
    cz_lo, _ = tree.crown.z_range
    cx, cy, cz = tree.crown.center
    top = (cx, cy, cz_lo + 0.35 * (cz - cz_lo))
    n_branches = int(rng.integers(spec.branches_range[0], spec.branches_range[1] + 1))
    tips = []
    for _ in range(n_branches):
        u = rng.normal(size=3)
        u[2] = abs(u[2]) + 0.3
        u /= np.linalg.norm(u)
        r = tree.crown.radius(u[None, :])[0] * rng.uniform(0.45, 0.75)
        tips.append(tuple((np.asarray(tree.crown.center) + u * r).tolist()))
    if isinstance(tree.crown.form, LobedForm):  # the scaffold limbs carry the lobes
        u = np.asarray(tree.crown.form.directions)
        r = tree.crown.radius(u) * rng.uniform(0.55, 0.8, len(u))
        tips = [tuple(p) for p in (np.asarray(tree.crown.center) + u * r[:, None]).tolist()]
    return replace(
        tree,
        trunk_top=tuple(map(float, top)),
        trunk_radius=float(rng.uniform(*spec.trunk_radius_range)),
        branch_tips=tuple(tips),
    )


def _extent_along(crown: CrownEnvelope, direction: np.ndarray) -> float:
    """How far the crown reaches from its centre along a horizontal unit direction."""
    s = crown.surface_points(4000)[:, :2] - np.asarray(crown.center[:2])
    return float((s @ direction).max())


def _fit_crowns(
    spec: OrchardSpec, trees: list[Tree], d: np.ndarray, right: np.ndarray, row_offset: float
) -> list[Tree]:
    """Keep the alleys drivable and, for structured orchards, crowns apart by a gap."""
    limit = spec.row_spacing / 2.0 - spec.alley_clearance
    fitted: list[Tree] = []
    for tree in trees:
        crown = tree.crown
        offset = float(np.dot(np.asarray(crown.center[:2]), right)) - row_offset
        reach = max(_extent_along(crown, right) + offset, _extent_along(crown, -right) - offset)
        if reach > limit:
            a, b, cu, cd = crown.semi_axes
            # Shrink across the row (growers hedge their rows), keeping the along-row size.
            crown = crown.with_semi_axes((a, b * limit / reach, cu, cd))
            for _ in range(5):
                reach = max(
                    _extent_along(crown, right) + offset, _extent_along(crown, -right) - offset
                )
                if reach <= limit:
                    break
                crown = crown.scaled(limit / reach * 0.999)
        fitted.append(_replace_crown(tree, crown))
    if spec.separate_crowns:
        for _ in range(3):
            for i in range(len(fitted) - 1):
                a_t, b_t = fitted[i], fitted[i + 1]
                gap_vec = np.asarray(b_t.crown.center[:2]) - np.asarray(a_t.crown.center[:2])
                dist = float(np.linalg.norm(gap_vec))
                u = gap_vec / dist
                reach = _extent_along(a_t.crown, u) + _extent_along(b_t.crown, -u)
                if reach + spec.min_crown_gap > dist:
                    k = (dist - spec.min_crown_gap) / reach * 0.999
                    fitted[i] = _replace_crown(a_t, _scale_about(a_t.crown, k))
                    fitted[i + 1] = _replace_crown(b_t, _scale_about(b_t.crown, k))
    return fitted


def _scale_about(crown: CrownEnvelope, k: float) -> CrownEnvelope:
    """Scale a crown keeping its lowest point (the crown base) at the same height."""
    z_lo = crown.z_range[0]
    scaled = crown.scaled(k)
    shift = z_lo - scaled.z_range[0]
    cx, cy, cz = crown.center
    return scaled.moved((cx, cy, cz + shift))


def _replace_crown(tree: Tree, crown: CrownEnvelope) -> Tree:
    if crown is tree.crown:
        return tree
    cz_lo, _ = crown.z_range
    cx, cy, cz = crown.center
    top = (cx, cy, cz_lo + 0.35 * (cz - cz_lo))
    old = np.asarray(tree.crown.center)
    tips = []
    for tip in tree.branch_tips:
        u = np.asarray(tip) - old
        r = np.linalg.norm(u)
        frac = r / tree.crown.radius((u / r)[None, :])[0]
        tips.append(
            tuple(
                (
                    np.asarray(crown.center) + u / r * crown.radius((u / r)[None, :])[0] * frac
                ).tolist()
            )
        )
    return replace(tree, crown=crown, trunk_top=tuple(map(float, top)), branch_tips=tuple(tips))
