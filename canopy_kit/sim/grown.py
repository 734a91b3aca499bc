"""A tree family grown from branches: space colonisation (Runions, Lane & Prusinkiewicz 2007).

No envelope is drawn for these trees. A cloud of attraction points marks where the tree may
grow (the space its training leaves it, made irregular by a random density of blobs); from the
trunk and the scaffolds a pruner left, every attraction point pulls the nearest branch node
within the radius of influence ``d_i``; each pulled node grows a new node ``D`` metres along
the mean of the unit vectors to its attraction points; attraction points within the kill
distance ``d_k`` of a node are removed. Branch radii follow the pipe model
(``r_parent^e = Σ r_child^e``). Leaf clusters sit on the shoots (nodes thinner than
``shoot_radius``), so the crown's form is what the branches made of the space they had.

Training forms, as orchards train them:

- ``vase``: open centre; 3-5 scaffolds at 35-55° from vertical, growth kept out of a cone
  above the trunk (almond, pistachio, peach);
- ``central_leader``: one leader up the middle, tiers narrowing upwards (apple, pear);
- ``hedgerow``: two cordon arms along the row, growth in a slab 0.8-1.4 m thick that runs
  past the neighbours' trunks (super-high-density olive and almond).

Young trees are smaller, with fewer attraction points and leaves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.sim.scene import cylinders, leaf_octahedra
from canopy_kit.sim.specimen import Specimen, joined, log_uniform

GROWN_FORMS = ("vase", "central_leader", "hedgerow")


@dataclass(frozen=True)
class Colonisation:
    """Space-colonisation settings (metres)."""

    step: float = 0.1  # D: length of a new segment
    influence: float = 0.9  # d_i: radius of influence of an attraction point
    kill: float = 0.25  # d_k: an attraction point this near a node is reached
    max_iterations: int = 250
    tropism: tuple[float, float, float] = (0.0, 0.0, 0.15)  # added to each growth direction
    tip_radius: float = 0.006
    pipe_exponent: float = 2.3
    shoot_radius: float = 0.018  # nodes thinner than this carry leaves
    min_wood_radius: float = 0.008  # thinner twigs are not meshed


@dataclass(frozen=True)
class Skeleton:
    """Branch nodes: positions (n, 3), parent index (-1 at the root) and pipe-model radii."""

    nodes: np.ndarray
    parent: np.ndarray
    radius: np.ndarray


def colonise(
    attractors: np.ndarray,
    nodes: np.ndarray,
    parent: np.ndarray,
    settings: Colonisation,
) -> Skeleton:
    """Grow the skeleton ``(nodes, parent)`` into the ``attractors`` (Runions et al. 2007)."""
    from scipy.spatial import cKDTree

    s = settings
    nodes = [np.asarray(nodes, float)]
    parent = [np.asarray(parent, np.int64)]
    att = np.asarray(attractors, float)
    all_nodes = nodes[0]
    att = att[cKDTree(all_nodes).query(att, distance_upper_bound=s.kill)[0] > s.kill]
    tropism = np.asarray(s.tropism)
    for _ in range(s.max_iterations):
        if len(att) == 0:
            break
        dist, near = cKDTree(all_nodes).query(att, distance_upper_bound=s.influence)
        pulled = np.isfinite(dist)
        if not pulled.any():
            break
        owner = near[pulled]
        unit = (att[pulled] - all_nodes[owner]) / dist[pulled, None]
        growers, inverse = np.unique(owner, return_inverse=True)
        direction = np.zeros((len(growers), 3))
        np.add.at(direction, inverse, unit)
        direction += tropism * np.bincount(inverse)[:, None]
        norm = np.linalg.norm(direction, axis=1)
        ok = norm > 1e-9
        growers, direction = growers[ok], direction[ok] / norm[ok, None]
        new = all_nodes[growers] + s.step * direction
        # a node pulled the same way twice would grow on top of its earlier child
        fresh = cKDTree(all_nodes).query(new, distance_upper_bound=0.3 * s.step)[0] > 0.3 * s.step
        if not fresh.any():
            break
        new, growers = new[fresh], growers[fresh]
        nodes.append(new)
        parent.append(growers)
        all_nodes = np.concatenate([all_nodes, new])
        att = att[cKDTree(new).query(att, distance_upper_bound=s.kill)[0] > s.kill]
    par = np.concatenate(parent)
    return Skeleton(all_nodes, par, pipe_radii(par, s.tip_radius, s.pipe_exponent))


def pipe_radii(parent: np.ndarray, tip: float, exponent: float) -> np.ndarray:
    """Radii by the pipe model: a tip has ``tip``; ``r^e`` of a node is the sum over its
    children. Children come after their parents (as growth appends them)."""
    n = len(parent)
    children = np.bincount(parent[parent >= 0], minlength=n)
    acc = np.where(children == 0, tip**exponent, 0.0)
    for i in range(n - 1, 0, -1):
        p = parent[i]
        if p >= 0:
            acc[p] += acc[i]
    return acc ** (1.0 / exponent)


@dataclass(frozen=True)
class GrownSpec:
    """Sizes of an old tree of each form (metres); young trees take ``young_scale`` of them."""

    crown_radius: tuple[float, float] = (1.7, 2.4)  # vase, central leader: radius at the widest
    crown_top: tuple[float, float] = (3.6, 4.8)
    trunk_height: tuple[float, float] = (0.6, 1.0)
    hedge_half_width: tuple[float, float] = (0.45, 0.75)
    hedge_spacing: tuple[float, float] = (1.2, 2.2)  # trees along a hedgerow
    attractor_density: tuple[float, float] = (90.0, 160.0)  # per m³ of growing space
    young_scale: tuple[float, float] = (0.4, 0.55)
    young_attractors: float = 0.35
    # leaf clusters per shoot node (one per 0.1 m of shoot), drawn log-uniformly: from
    # see-through crowns to crowns as opaque as an orchard's in summer
    leaves_per_shoot: tuple[float, float] = (0.5, 4.0)
    young_leaves_per_shoot: tuple[float, float] = (0.25, 0.6)
    leaf_size: tuple[float, float] = (0.08, 0.18)
    hedge_density_factor: float = 2.0
    blobs: int = 10  # random density blobs that make the growing space irregular


#: Old tall trees (walnut, pecan, old almond, olive: 8-12 m): wider, much higher crowns on a
#: taller trunk, the growing space filled half as densely (the shoots per m³ of an old crown)
TALL = GrownSpec(
    crown_radius=(2.6, 3.6),
    crown_top=(8.0, 11.5),
    trunk_height=(1.0, 1.6),
    attractor_density=(45.0, 80.0),
)


def grown_tree(
    rng: np.random.Generator,
    form: str,
    young: bool = False,
    spec: GrownSpec | None = None,
    settings: Colonisation | None = None,
    name: str | None = None,
) -> Specimen:
    """One tree of ``form`` (:data:`GROWN_FORMS`) grown at the origin, the row along x."""
    if form not in GROWN_FORMS:
        raise ValueError(f"form must be one of {GROWN_FORMS}, got {form!r}")
    spec = spec or GrownSpec()
    settings = settings or Colonisation()
    scale = rng.uniform(*spec.young_scale) if young else 1.0
    trunk_h = rng.uniform(*spec.trunk_height) * (0.8 if young else 1.0)
    space, nodes, parent = _training(form, rng, spec, scale, trunk_h)
    density = rng.uniform(*spec.attractor_density) * (spec.young_attractors if young else 1.0)
    if form == "hedgerow":  # a fruiting wall is pruned to a dense slab
        density *= spec.hedge_density_factor
    attractors = _irregular(space, density, rng, spec.blobs, scale)
    if young:
        settings = Colonisation(
            **{**settings.__dict__, "step": 0.07, "influence": 0.6, "kill": 0.18}
        )
    if form == "hedgerow":
        settings = Colonisation(**{**settings.__dict__, "tropism": (0.0, 0.0, 0.05)})
    skeleton = colonise(attractors, nodes, parent, settings)
    per_shoot = log_uniform(rng, *(spec.young_leaves_per_shoot if young else spec.leaves_per_shoot))
    if form == "hedgerow":
        per_shoot *= spec.hedge_density_factor
    leaves = _shoot_leaves(skeleton, settings, rng, per_shoot, spec.leaf_size)
    crown_base = float(leaves[:, 2].min()) if len(leaves) else trunk_h
    wood, trunk = _wood(skeleton, settings, crown_base)
    return Specimen(
        name or f"grown-{form}{'-young' if young else ''}",
        "grown",
        form,
        leaves,
        wood,
        trunk,
        envelope_m3=None,
        young=young,
        info={
            "nodes": len(skeleton.nodes),
            "attractors": len(attractors),
            "trunk_radius": float(skeleton.radius[0]),
        },
    )


def _training(
    form: str, rng: np.random.Generator, spec: GrownSpec, scale: float, trunk_h: float
) -> tuple:
    """(growing space as a point-membership function with its box, initial nodes, parents)."""
    step = 0.1
    trunk = np.column_stack([np.zeros(2), np.zeros(2), [0.0, 0.0]])[:0]
    zs = np.arange(0.0, trunk_h + 1e-9, step)
    trunk = np.column_stack([np.zeros_like(zs), np.zeros_like(zs), zs])
    nodes, parent = [trunk], [np.arange(len(zs)) - 1]
    top_index = len(zs) - 1
    radius = rng.uniform(*spec.crown_radius) * scale
    top = trunk_h + (rng.uniform(*spec.crown_top) - trunk_h) * scale
    if form == "vase":
        n = int(rng.integers(3, 6))
        az = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n + rng.normal(0, 0.2, n)
        tilt = np.radians(rng.uniform(35, 55, n))
        for a, t in zip(az, tilt):
            d = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
            length = rng.uniform(0.6, 1.0) * scale + 0.2
            k = np.arange(1, int(length / step) + 1)
            _append_limb(nodes, parent, trunk[-1] + np.outer(k * step, d), top_index)
        opening = rng.uniform(0.35, 0.6)  # open-centre radius at the top, as a share of R

        def inside(p: np.ndarray) -> np.ndarray:
            r = np.hypot(p[:, 0], p[:, 1])
            h = (p[:, 2] - trunk_h) / (top - trunk_h)
            outer = radius * np.sqrt(np.clip(1.0 - (2.0 * h - 1.1) ** 2 / 1.45, 0.0, None))
            return (h >= 0.05) & (h <= 1.0) & (r <= outer) & (r >= opening * radius * h)

        box = (np.array([-radius, -radius, trunk_h]), np.array([radius, radius, top]))
    elif form == "central_leader":
        leader_top = trunk_h + 0.55 * (top - trunk_h)
        k = np.arange(1, int((leader_top - trunk_h) / step) + 1)
        _append_limb(nodes, parent, trunk[-1] + np.outer(k * step, [0.0, 0.0, 1.0]), top_index)
        bottom = trunk_h + 0.1 * (top - trunk_h)

        def inside(p: np.ndarray) -> np.ndarray:
            r = np.hypot(p[:, 0], p[:, 1])
            h = (p[:, 2] - bottom) / (top - bottom)
            return (h >= 0) & (h <= 1) & (r <= radius * (1.0 - h) ** 0.85 + 0.15)

        box = (np.array([-radius, -radius, bottom]), np.array([radius, radius, top]))
    else:  # hedgerow
        half_len = 0.5 * rng.uniform(*spec.hedge_spacing) * 1.15
        half_w = rng.uniform(*spec.hedge_half_width) * (0.7 if scale < 1 else 1.0)
        top = trunk_h + (rng.uniform(2.6, 3.4) - trunk_h) * scale
        for sign in (-1.0, 1.0):
            d = np.array([sign * np.cos(0.35), 0.0, np.sin(0.35)])
            k = np.arange(1, int(0.8 * half_len / step) + 1)
            _append_limb(nodes, parent, trunk[-1] + np.outer(k * step, d), top_index)

        def inside(p: np.ndarray) -> np.ndarray:
            h = (p[:, 2] - trunk_h) / (top - trunk_h)
            width = half_w * (1.0 - 0.35 * np.clip(h, 0, 1))
            return (h >= 0) & (h <= 1) & (np.abs(p[:, 0]) <= half_len) & (np.abs(p[:, 1]) <= width)

        box = (np.array([-half_len, -half_w, trunk_h]), np.array([half_len, half_w, top]))
    return (inside, box), np.concatenate(nodes), np.concatenate(parent)


def _append_limb(nodes: list, parent: list, points: np.ndarray, attach: int) -> None:
    """Append a chain of ``points`` whose first hangs on node ``attach``."""
    start = sum(len(n) for n in nodes)
    nodes.append(points)
    parent.append(np.concatenate([[attach], start + np.arange(len(points) - 1)]))


def _irregular(
    space: tuple, density: float, rng: np.random.Generator, blobs: int, scale: float
) -> np.ndarray:
    """Attraction points in the growing space at a density modulated by random blobs: the
    space a tree gets is never filled evenly (gaps between scaffolds, shaded sides)."""
    inside, (lo, hi) = space
    p = rng.uniform(lo, hi, (int(density * np.prod(hi - lo) * 1.6), 3))
    p = p[inside(p)]
    centres = rng.uniform(lo, hi, (blobs, 3))
    sigma = rng.uniform(0.4, 0.9, blobs) * max(scale, 0.5)
    weight = rng.uniform(0.3, 1.0, blobs)
    d2 = ((p[:, None, :] - centres[None]) ** 2).sum(axis=2)
    field = (weight * np.exp(-0.5 * d2 / sigma**2)).sum(axis=1)
    keep = rng.random(len(p)) < np.clip(0.2 + field / max(float(field.max()), 1e-9), 0.0, 1.0)
    p = p[keep]
    return p[: int(density * np.prod(hi - lo))]


def _shoot_leaves(
    skeleton: Skeleton,
    settings: Colonisation,
    rng: np.random.Generator,
    per_shoot: float,
    size_range: tuple[float, float],
) -> np.ndarray:
    """Leaf clusters on the shoots: ``per_shoot`` clusters per thin node on average, each up
    to a segment's length from its node."""
    shoots = np.flatnonzero((skeleton.radius < settings.shoot_radius) & (skeleton.parent >= 0))
    count = rng.poisson(per_shoot, len(shoots))
    at = skeleton.nodes[np.repeat(shoots, count)]
    offset = rng.normal(0.0, 0.5 * settings.step, at.shape)
    size = rng.uniform(*size_range, len(at))
    return leaf_octahedra(at + offset, size, rng)


def _wood(
    skeleton: Skeleton, settings: Colonisation, crown_base: float
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """(crown wood, trunk below ``crown_base``): a tapered cylinder per segment thick enough."""
    child = np.flatnonzero(skeleton.parent >= 0)
    child = child[skeleton.radius[child] >= settings.min_wood_radius]
    par = skeleton.parent[child]
    p0, p1 = skeleton.nodes[par], skeleton.nodes[child]
    r0, r1 = skeleton.radius[par], skeleton.radius[child]
    low = np.maximum(p0[:, 2], p1[:, 2]) <= crown_base
    crown = cylinders(p0[~low], p1[~low], r0[~low], r1[~low], 6) if (~low).any() else None
    trunk = cylinders(p0[low], p1[low], r0[low], r1[low], 8) if low.any() else None
    return joined([crown] if crown else []), joined([trunk] if trunk else [])
