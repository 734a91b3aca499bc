"""Rows of trees of every family, for measuring volume estimators on trees built different ways.

:func:`family_rows` draws, for one family and seed, the rows that
``benchmarks/bench_volume_families.py`` drives past (:func:`canopy_kit.sim.alley.drive_row`):

- ``envelope``: the orchard simulator's crowns (pistachio preset), one row per crown form,
  with the default and the harsher crowns (deep lobe hollows, leaves in a 0.3 m shell);
- ``lobe_union``: unions of ellipsoidal lobes on scaffold tips (:mod:`canopy_kit.sim.lobe_union`);
- ``grown``: space-colonisation trees (:mod:`canopy_kit.sim.grown`), vase, central leader
  and hedgerow, old and young;
- ``real``: real tree clouds made into splats (:mod:`canopy_kit.sim.real_tree`), three turns
  of each along a row.

Every row is deterministic in (family, seed). Which seeds tuned anything and which are held
out is the benchmark's business, not this module's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.sim.specimen import COMPLETE_DENSITY, FAMILIES, Specimen, sample_mesh

ENVELOPE_FORMS = ("ellipsoid", "lobed", "vase", "hedged", "sparse")
HARSH = {"lobe_hollow_range": [0.25, 0.35], "leaf_penetration_m": 0.3}
# crowns as opaque as an orchard's in summer: four times the preset's leaf clusters
OPAQUE = {"foliage_density_shell": 240.0, "foliage_density_core": 24.0}
VARIANTS = {"default": {}, "harsh": HARSH, "opaque": OPAQUE}
TREES_PER_ROW = 3
CLEARANCE = (0.8, 2.0)  # metres from the widest crown's side to the alley's centre line
SPEED = (1.0, 2.2)  # m/s along the alley


@dataclass(frozen=True)
class FamilyRow:
    """A row to drive past: its name, trees, gaps between trunks (m) and the family."""

    name: str
    family: str
    specimens: list[Specimen]
    gaps: list[float]
    positions: np.ndarray | None = None  # (K, 2) trunk positions of a plot, instead of gaps


def family_rows(
    family: str,
    seed: int,
    real_clouds: Sequence[str | Path] = (),
    real_plots: Sequence[str | Path] = (),
) -> list[FamilyRow]:
    """The rows of ``family`` for ``seed`` (``real_clouds``: single-tree files of the real
    family; ``real_plots``: plot files, split into trees that keep where they stood)."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    return {
        "envelope": _envelope_rows,
        "lobe_union": _lobe_union_rows,
        "grown": _grown_rows,
        "real": lambda s: _real_rows(s, real_clouds, real_plots),
    }[family](seed)


def _envelope_rows(seed: int) -> list[FamilyRow]:
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.orchard import generate_orchard
    from canopy_kit.sim.specimen import from_orchard_tree

    rows = []
    for variant, extra in VARIANTS.items():
        for k, form in enumerate(ENVELOPE_FORMS):
            if variant != "default" and form == "sparse":
                continue
            orchard_spec = {"rows": 1, "trees_per_row": TREES_PER_ROW, "crown_form": form, **extra}
            config = load_sim_config("pistachio", {"seed": seed, "orchard": orchard_spec})
            rng = np.random.default_rng([seed, k, len(rows)])
            orchard = generate_orchard(config.orchard, rng)
            trees = [from_orchard_tree(t, config.orchard, rng) for t in orchard.trees]
            along = [float(np.dot(t.base[:2], orchard.row_direction)) for t in orchard.trees]
            rows.append(FamilyRow(f"{form}-{variant}", "envelope", trees, list(np.diff(along))))
    return rows


def _lobe_union_rows(seed: int) -> list[FamilyRow]:
    from canopy_kit.sim.lobe_union import lobe_union_tree

    rng = np.random.default_rng([seed, 17])
    old = [lobe_union_tree(rng, name=f"lobe-union-{i}") for i in range(2 * TREES_PER_ROW)]
    young = [lobe_union_tree(rng, True, name=f"lobe-union-young-{i}") for i in range(TREES_PER_ROW)]
    return [
        FamilyRow("old-a", "lobe_union", old[:TREES_PER_ROW], _gaps(rng, TREES_PER_ROW, 4.5, 5.5)),
        FamilyRow("old-b", "lobe_union", old[TREES_PER_ROW:], _gaps(rng, TREES_PER_ROW, 4.0, 5.0)),
        FamilyRow("young", "lobe_union", young, _gaps(rng, TREES_PER_ROW, 2.5, 3.5)),
    ]


def _grown_rows(seed: int) -> list[FamilyRow]:
    from canopy_kit.sim.grown import GROWN_FORMS, TALL, grown_tree

    rng = np.random.default_rng([seed, 29])
    rows = []
    for form in GROWN_FORMS:
        for young in (False, True):
            n = TREES_PER_ROW + (2 if form == "hedgerow" and not young else 0)
            trees = [
                grown_tree(rng, form, young, name=f"grown-{form}{'-young' if young else ''}-{i}")
                for i in range(n)
            ]
            if form == "hedgerow":  # trunks as far apart as the wall each tree was grown to
                gaps = [float(np.ptp(t.leaves[:, 0])) * 0.8 for t in trees[:-1]]
            elif young:
                gaps = _gaps(rng, n, 2.5, 3.5)
            else:
                gaps = _gaps(rng, n, 4.5, 5.5)
            rows.append(FamilyRow(f"{form}{'-young' if young else ''}", "grown", trees, gaps))
    # tall old trees (walnut, pecan, old almond and olive reach 8-12 m): their own stream, so
    # the rows above are the same with or without them
    tall_rng = np.random.default_rng([seed, 31])
    for form in ("vase", "central_leader"):
        trees = [
            grown_tree(tall_rng, form, spec=TALL, name=f"grown-{form}-tall-{i}")
            for i in range(TREES_PER_ROW)
        ]
        rows.append(
            FamilyRow(f"{form}-tall", "grown", trees, _gaps(tall_rng, TREES_PER_ROW, 7.5, 9.0))
        )
    return rows


def _real_rows(
    seed: int, clouds: Sequence[str | Path], plots: Sequence[str | Path] = ()
) -> list[FamilyRow]:
    from canopy_kit.sim.real_tree import plot_specimens, real_tree

    rows = []
    for path in clouds:
        tree = real_tree(path, seed=seed)
        lo, hi = tree.extent()
        width = float(np.hypot(*(hi - lo)[:2]))
        turns = [
            tree.turned(2 * np.pi * k / TREES_PER_ROW + seed, f"{tree.name}-turn{k}")
            for k in range(TREES_PER_ROW)
        ]
        rows.append(FamilyRow(tree.name, "real", turns, [width + 1.0] * (TREES_PER_ROW - 1)))
    for path in plots:
        trees, positions = plot_specimens(path, seed=seed)
        rows.append(FamilyRow(Path(path).stem, "real", trees, [], positions))
    return rows


def _gaps(rng: np.random.Generator, n: int, lo: float, hi: float) -> list[float]:
    return list(rng.uniform(lo, hi, n - 1))


@dataclass
class ScannedTree:
    """One tree of a row after a drive: what its family knows and its clouds, each thinned to
    the pipeline's voxel grid: ``complete`` (every leaf and branch, or a real tree's full
    cloud) and ``scans`` per side (``left``, ``right``, ``both``)."""

    row: str
    family: str
    name: str
    form: str
    young: bool
    envelope_m3: float | None
    complete: np.ndarray
    scans: dict[str, np.ndarray]
    surfaces: np.ndarray | None = None  # a real tree's splats, sampled completely


def scanned_trees(
    row: FamilyRow,
    sensor: str,
    mount_height: float = 1.8,
    voxel_size: float = 0.1,
    seed: int = 0,
    complete: Sequence[np.ndarray] | None = None,
) -> list[ScannedTree]:
    """Drive ``sensor`` past ``row`` on both sides (clearance and speed drawn per row from
    ``CLEARANCE`` and ``SPEED``) and thin every tree's clouds to ``voxel_size`` (one point
    per voxel, the one nearest its centre, as the volume stage measures trees).
    ``complete``: the thinned complete clouds when already made."""
    from canopy_kit.core.voxel import voxel_representatives
    from canopy_kit.sim.alley import SIDES, drive_row

    def thin(xyz: np.ndarray) -> np.ndarray:
        return xyz[voxel_representatives(xyz, voxel_size)[0]] if voxel_size else xyz

    drive = np.random.default_rng([seed, sum(map(ord, row.name))])
    scan = drive_row(
        row.specimens,
        row.gaps,
        sensor,
        mount_height=mount_height,
        clearance=float(drive.uniform(*CLEARANCE)),
        speed=float(drive.uniform(*SPEED)),
        seed=seed,
        lead=lead_for(row),
        positions=row.positions,
    )
    out = []
    for k, sp in enumerate(row.specimens):
        clouds = {side: thin(scan.tree_points(k, [side])) for side in SIDES}
        clouds["both"] = thin(scan.tree_points(k, SIDES))
        reference = complete[k] if complete is not None else thin(sp.complete_foliage(seed=k))
        surfaces = None
        if sp.reference is not None:  # the splats the drive saw, beside the cloud they stand for
            mesh = sp.crown_mesh()
            surfaces = thin(sample_mesh(*mesh, COMPLETE_DENSITY, np.random.default_rng(k)))
        out.append(
            ScannedTree(
                row.name,
                sp.family,
                sp.name,
                sp.form,
                sp.young,
                sp.envelope_m3,
                reference,
                clouds,
                surfaces,
            )
        )
    return out


def lead_for(row: FamilyRow) -> float:
    """How far before the first and past the last trunk the drive runs: far enough to see the
    tallest crown's top over the trees (a real drive runs the whole row), at least 6 m."""
    top = max(float(sp.extent()[1][2]) for sp in row.specimens)
    return max(6.0, 2.0 * top)
