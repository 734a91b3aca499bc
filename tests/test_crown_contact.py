"""Crown contact (``segment.contact``): the share of a tree's crown within reach of another
tree's points, on hand-made crowns whose answer is known by construction, and the run check
that names the interwoven trees."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.segment.contact import CELL_M, REACH_M, TOUCHING_CONTACT, crown_contact


def lattice_cube(x0: float, n: int = 10) -> np.ndarray:
    """n³ points, one per CELL_M voxel (cell centres), the cube's x starting at ``x0``."""
    i = (np.arange(n) + 0.5) * CELL_M
    x, y, z = np.meshgrid(i + x0, i, i, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def test_two_cubes_touch_by_their_facing_layers_and_a_lone_one_not_at_all() -> None:
    """Cube B starts 0.2 m beyond cube A's last layer: only that layer (100 of 1000 points)
    lies within 0.3 m of B (the next is 0.35 m away), and B's first layer of A: 0.1 each. A
    third cube 5 m away touches nothing; ground points (label -1) beside it are no tree, and
    a crown scanned twice as densely keeps the same shares (the contact counts voxels)."""
    assert REACH_M == pytest.approx(0.3) and CELL_M == pytest.approx(0.15)
    a = lattice_cube(0.0)
    b = lattice_cube(a[:, 0].max() + 0.2 - 0.5 * CELL_M)
    c = lattice_cube(8.0)
    ground = c.copy()
    ground[:, 2] -= 0.1  # just under the lone cube: no tree's points
    xyz = np.vstack([a, b, c, ground])
    labels = np.repeat([0, 1, 2, -1], 1000)
    share = crown_contact(xyz, labels)
    assert share == pytest.approx({0: 0.1, 1: 0.1, 2: 0.0})
    denser = np.vstack([xyz, xyz + 0.01])  # two returns per voxel
    assert crown_contact(denser, np.concatenate([labels, labels])) == pytest.approx(share)


def test_bad_input_names_the_shapes() -> None:
    with pytest.raises(ValueError, match="crown_contact"):
        crown_contact(np.zeros((4, 2)), np.zeros(4, int))
    with pytest.raises(ValueError, match="one label per point"):
        crown_contact(np.zeros((4, 3)), np.zeros(3, int))
    assert crown_contact(np.zeros((3, 3)), np.full(3, -1)) == {}


def test_the_check_names_the_interwoven_trees_for_information() -> None:
    from canopy_kit.results.checks import touching_crowns_check

    trees = pd.DataFrame(
        {"tree_id": ["r0-L0", "r0-L1", "r0-L2"], "crown_contact": [0.0, 0.12, TOUCHING_CONTACT]}
    )
    check = touching_crowns_check(trees)
    assert check.status == "info" and check.value == "2 (67 %)"
    assert "r0-L1, r0-L2" in check.note and "r0-L0" not in check.note
    free = touching_crowns_check(trees.assign(crown_contact=0.0))
    assert free.value == "0 (0 %)" and free.note == ""


def test_an_interwoven_trees_interval_is_widened_and_says_so() -> None:
    """Trees of 10 m³ with the families' interval 9.8-11: the free one keeps it; the
    interwoven one (contact 0.12) spans 0.964-1.942 x its estimate and is flagged; one whose
    interval was already wider below (9.0-30, one-sided) keeps those bounds and gets the flag
    after its own; one without an interval (NaN) keeps none; another estimator is unchanged."""
    from canopy_kit.volume.interwoven import INTERWOVEN_RATIOS, widen_for_contact

    lo_r, hi_r = INTERWOVEN_RATIOS["foliage_envelope"]
    trees = pd.DataFrame(
        {
            "volume_foliage_envelope_m3": [10.0, 10.0, 10.0, 10.0],
            "volume_low_m3": [9.8, 9.8, 9.0, np.nan],
            "volume_high_m3": [11.0, 11.0, 30.0, np.nan],
            "crown_contact": [0.0, 0.12, 0.2, 0.3],
            "volume_interval_flags": ["", "", "one-sided scan", ""],
        }
    )
    out = widen_for_contact(trees, "foliage_envelope", "volume_foliage_envelope_m3", 0.08)
    assert out["volume_low_m3"].tolist()[:3] == pytest.approx([9.8, 10 * lo_r, 9.0])
    assert out["volume_high_m3"].tolist()[:3] == pytest.approx([11.0, 10 * hi_r, 30.0])
    assert np.isnan(out["volume_low_m3"][3]) and np.isnan(out["volume_high_m3"][3])
    flags = out["volume_interval_flags"].tolist()
    assert flags[0] == "" and flags[3] == ""
    assert flags[1].startswith("interwoven crown (contact 0.12)")
    assert flags[2].startswith("one-sided scan; interwoven crown (contact 0.20)")
    same = widen_for_contact(trees, "convex_hull", "volume_convex_hull_m3", 0.08)
    assert same.equals(trees)


def test_the_tables_contact_and_widening_come_from_the_labelled_points() -> None:
    """``with_crown_contact`` (the batch tree table and the stream both use it): two touching
    lattice cubes (contact 0.1 each, above TOUCHING_CONTACT) get their contact and the
    widened interval, the lone cube neither; on a wall (cut at its trunks) nothing changes."""
    from canopy_kit.config import load_preset
    from canopy_kit.results.tree_table import with_crown_contact
    from canopy_kit.volume.interwoven import INTERWOVEN_RATIOS

    a = lattice_cube(0.0)
    b = lattice_cube(a[:, 0].max() + 0.2 - 0.5 * CELL_M)
    xyz = np.vstack([a, b, lattice_cube(8.0)])
    labels = np.repeat([0, 1, 2], 1000)
    trees = pd.DataFrame(
        {
            "segment": [2, 0, 1],
            "volume_foliage_envelope_m3": [3.0, 3.0, 3.0],
            "volume_low_m3": [2.9, 2.9, 2.9],
            "volume_high_m3": [3.3, 3.3, 3.3],
            "volume_interval_flags": ["", "", ""],
        }
    )
    volume = load_preset("adaptive").volume
    assert volume.recommended == "foliage_envelope" and 0.1 >= TOUCHING_CONTACT
    out = with_crown_contact(trees, xyz, labels, volume)
    assert out["crown_contact"].tolist() == pytest.approx([0.0, 0.1, 0.1])
    lo_r, hi_r = INTERWOVEN_RATIOS["foliage_envelope"]
    assert out["volume_low_m3"].tolist() == pytest.approx([2.9, 3 * lo_r, 3 * lo_r])
    assert out["volume_high_m3"].tolist() == pytest.approx([3.3, 3 * hi_r, 3 * hi_r])
    wall = load_preset("wall").volume
    assert wall.interval_kind == "wall"
    assert with_crown_contact(trees, xyz, labels, wall).equals(trees)
