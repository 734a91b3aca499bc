"""Orchard geometry: crown volumes, overlaps, layout, and parameter checks."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.errors import ConfigError
from canopy_kit.sim.config import load_sim_config
from canopy_kit.sim.crown import CrownEnvelope
from canopy_kit.sim.orchard import generate_orchard


def _orchard(kind: str, seed: int = 3, **orchard):
    cfg = load_sim_config(kind, {"orchard": {"rows": 3, "trees_per_row": 6, **orchard}})
    return generate_orchard(cfg.orchard, np.random.default_rng(seed))


def test_ellipsoid_volume_is_exact():
    env = CrownEnvelope((0.0, 0.0, 3.0), (2.0, 1.5, 1.2, 1.2), 0.4, 2.0)
    assert env.volume == pytest.approx(4 / 3 * np.pi * 2.0 * 1.5 * 1.2, rel=1e-9)
    # Different upper and lower semi-axes: two half ellipsoids.
    env2 = CrownEnvelope((0.0, 0.0, 3.0), (2.0, 1.5, 1.6, 0.8), 0.0, 2.0)
    assert env2.volume == pytest.approx(2 / 3 * np.pi * 2.0 * 1.5 * (1.6 + 0.8), rel=1e-9)


@pytest.mark.parametrize("kind", ["pistachio", "almond"])
def test_crown_volume_matches_monte_carlo(kind):
    orchard = _orchard(kind)
    rng = np.random.default_rng(11)
    for tree in orchard.trees[:6]:
        lo, hi = tree.crown.bounds
        pts = rng.uniform(lo, hi, (400_000, 3))
        mc = tree.crown.contains(pts).mean() * np.prod(hi - lo)
        assert tree.crown.volume == pytest.approx(mc, rel=0.02)


def _overlap_fraction(a, b, rng, n=200_000):
    lo, hi = a.crown.bounds
    pts = rng.uniform(lo, hi, (n, 3))
    inside_a = a.crown.contains(pts)
    return (inside_a & b.crown.contains(pts)).sum() / max(inside_a.sum(), 1)


def test_pistachio_crowns_do_not_overlap_and_almond_crowns_do():
    rng = np.random.default_rng(5)
    for kind, expect_overlap in (("pistachio", False), ("almond", True), ("almond-paper", True)):
        orchard = _orchard(kind)
        overlaps = []
        for a in orchard.trees:
            for b in orchard.trees:
                if (
                    a.tree_id < b.tree_id
                    and a.row == b.row
                    and abs(a.index_in_row - b.index_in_row) == 1
                ):
                    overlaps.append(_overlap_fraction(a, b, rng))
        if expect_overlap:
            assert sum(f > 0.01 for f in overlaps) >= 2, overlaps
        else:
            assert max(overlaps) == 0.0


def test_layout_follows_rows_and_labels():
    orchard = _orchard("pistachio", row_bearing_deg=30.0)
    d = orchard.row_direction
    assert d == pytest.approx([np.sin(np.radians(30)), np.cos(np.radians(30))])
    for tree in orchard.trees:
        along, across = orchard.to_orchard(np.array(tree.base[:2]))
        assert across == pytest.approx(orchard.row_offsets[tree.row], abs=0.5)
        assert tree.label == ("L" if tree.row % 2 == 0 else "R") + str(tree.index_in_row)
    by_row = {}
    for tree in orchard.trees:
        by_row.setdefault(tree.row, []).append(orchard.to_orchard(np.array(tree.base[:2]))[0])
    for alongs in by_row.values():
        assert np.all(np.diff(alongs) > 0)  # index increases along the row direction


def test_alley_stays_drivable():
    orchard = _orchard("almond")
    spec = orchard.spec
    for tree in orchard.trees:
        across = orchard.to_orchard(tree.crown.surface_points(3000)[:, :2])[:, 1]
        offset = across - orchard.row_offsets[tree.row]
        assert np.abs(offset).max() <= spec.row_spacing / 2 - spec.alley_clearance + 1e-6


def test_almond_has_missing_and_doubled_trees():
    orchard = _orchard("almond", seed=1, missing_probability=0.3, double_probability=0.3)
    counts = np.bincount([t.row for t in orchard.trees])
    assert any(t.doubled for t in orchard.trees)
    assert counts.min() < 6 or counts.max() > 6


@pytest.mark.parametrize(
    "overrides, parameter",
    [
        ({"orchard": {"spacing_range": [-5.0, 5.0]}}, "orchard.spacing_range"),
        ({"orchard": {"row_spacing": 0.0}}, "orchard.row_spacing"),
        ({"lidar": {"rings": 0}}, "lidar.rings"),
        (
            {"orchard": {"rows": 1, "trees_per_row": 1, "crown_diameter_range": [30.0, 40.0]}},
            "orchard.crown_diameter_range",
        ),
        ({"lidar": {"min_range": 5.0, "max_range": 2.0}}, "lidar.min_range"),
        ({"orchard": {"alley_clearance": 4.0}}, "orchard.alley_clearance"),
    ],
)
def test_impossible_parameters_name_the_parameter(overrides, parameter):
    with pytest.raises(ConfigError, match=parameter.replace(".", r"\.")):
        load_sim_config("pistachio", overrides)


def test_unknown_parameter_is_named():
    with pytest.raises(ConfigError, match="crown_colour"):
        load_sim_config("almond", {"orchard": {"crown_colour": "green"}})


def test_preset_extends_another_and_lists_only_what_differs(tmp_path):
    from dataclasses import asdict

    almond, paper = asdict(load_sim_config("almond")), asdict(load_sim_config("almond-paper"))
    differs = {k for k in almond["orchard"] if almond["orchard"][k] != paper["orchard"][k]}
    assert differs == {"crown_diameter_range"}
    assert paper["orchard"]["crown_diameter_range"] == [3.5, 5.0]
    assert all(almond[section] == paper[section] for section in almond if section != "orchard")
    # A user's file may extend a preset that itself extends another.
    mine = tmp_path / "mine.toml"
    mine.write_text('extends = "almond-paper"\n[orchard]\nrows = 2\n')
    cfg = load_sim_config(mine)
    assert (cfg.orchard.kind, cfg.orchard.rows, cfg.orchard.crown_diameter_range) == (
        "almond",
        2,
        [3.5, 5.0],
    )
    from canopy_kit.evaluate.truth import DEFAULT_ORCHARD_KIND, orchard_kind
    from canopy_kit.sim.config import OrchardSpec, sim_preset_names

    assert [orchard_kind(o) for o in ("almond-paper", "pistachio", "walnut")] == [
        "almond",
        "pistachio",
        "walnut",
    ]
    # The truth module reads the presets as data: it must agree with the simulator's loader.
    assert OrchardSpec().kind == DEFAULT_ORCHARD_KIND
    assert all(orchard_kind(n) == load_sim_config(n).orchard.kind for n in sim_preset_names())
    mine.write_text('extends = "walnut"\n')
    with pytest.raises(ConfigError, match=r"mine\.toml: extends 'walnut'"):
        load_sim_config(mine)
