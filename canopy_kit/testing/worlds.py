"""Conformance rules for world plugins (``canopy_kit.worlds``): each a named check.

A world model rebuilds the exact geometry of a session its generator wrote
(:class:`canopy_kit.evaluate.truth.WorldModel`). The rules hold it to the session's own
truth tables, which the generator wrote independently of the rebuild: the orchard has the
trees of ``truth/trees.csv`` where the table puts them, every tree's complete foliage lies
around its trunk, the scene's surfaces are a valid mesh labelled with those trees, and a
rebuild gives the same world. ``check_world(MyWorld, session_dir)`` runs them all.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.evaluate.truth import load_truth
from canopy_kit.testing.estimators import Check, _run

POSITION_TOL_M = 0.05  # the truth table stores positions to the micrometre; a rebuild is exact


def _tree_positions(world: Any) -> dict[int, np.ndarray]:
    return {int(t.tree_id): np.asarray(t.base[:2], float) for t in world.orchard().trees}


def check_has_the_methods_of_a_world(world: Any) -> None:
    # the methods of the WorldModel protocol (canopy_kit.evaluate.truth)
    for method in ("orchard", "scene", "complete_foliage"):
        assert callable(getattr(world, method, None)), f"needs {method}()"


def _checks(session_dir: Path) -> list[tuple[str, Any]]:
    truth = load_truth(session_dir)
    table = truth.trees.set_index("tree_id")

    def check_orchard_has_the_truth_trees(world: Any) -> None:
        built = _tree_positions(world)
        assert set(built) == set(table.index), (
            f"orchard trees {sorted(built)[:8]}... differ from truth/trees.csv "
            f"{sorted(table.index)[:8]}..."
        )
        for tree_id, xy in built.items():
            expected = table.loc[tree_id, ["x", "y"]].to_numpy(float)
            off = float(np.hypot(*(xy - expected)))
            assert off <= POSITION_TOL_M, f"tree {tree_id} stands {off:.3f} m from its truth row"

    def check_foliage_lies_around_each_trunk(world: Any) -> None:
        foliage = world.complete_foliage()
        assert isinstance(foliage, dict), f"complete_foliage returned {type(foliage).__name__}"
        unknown = sorted(set(foliage) - set(table.index))
        assert not unknown, f"foliage for trees not in truth/trees.csv: {unknown[:5]}"
        for tree_id, pts in foliage.items():
            pts = np.asarray(pts)
            assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts), f"tree {tree_id}: {pts.shape}"
            assert np.isfinite(pts).all(), f"tree {tree_id}: foliage not finite"
            row = table.loc[tree_id]
            reach = float(np.hypot(*(pts[:, :2] - row[["x", "y"]].to_numpy(float)).T).max())
            limit = float(row["crown_diameter_m"]) + 1.0  # the crown leans: its width, not half
            assert reach <= limit, f"tree {tree_id}: foliage {reach:.2f} m from its trunk"

    def check_scene_is_a_labelled_mesh(world: Any) -> None:
        scene = world.scene()
        vertices = np.asarray(scene.vertices)
        triangles = np.asarray(scene.triangles)
        labels = np.asarray(scene.tree_id)
        assert vertices.ndim == 2 and vertices.shape[1] == 3, f"vertices {vertices.shape}"
        assert triangles.ndim == 2 and triangles.shape[1] == 3, f"triangles {triangles.shape}"
        assert triangles.min() >= 0 and triangles.max() < len(vertices), "a face's vertex is out"
        assert labels.shape == (len(triangles),), "one tree id per triangle"
        stray = sorted(set(np.unique(labels[labels >= 0]).tolist()) - set(table.index))
        assert not stray, f"surfaces labelled with trees not in truth/trees.csv: {stray[:5]}"

    def check_rebuilds_the_same_world(world: Any) -> None:
        again = type(world)(session_dir)
        a, b = _tree_positions(world), _tree_positions(again)
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a), (
            "two rebuilds of the session differ"
        )

    return [
        ("has_the_methods_of_a_world", check_has_the_methods_of_a_world),
        ("orchard_has_the_truth_trees", check_orchard_has_the_truth_trees),
        ("foliage_lies_around_each_trunk", check_foliage_lies_around_each_trunk),
        ("scene_is_a_labelled_mesh", check_scene_is_a_labelled_mesh),
        ("rebuilds_the_same_world", check_rebuilds_the_same_world),
    ]


def world_checks(session_dir: str | Path) -> list[Check]:
    """Every rule of the world contract, against the truth of one session the generator wrote."""
    return [Check(name, func) for name, func in _checks(Path(session_dir))]


def check_world(world: Any, session_dir: str | Path) -> None:
    """Build ``world`` (a class) on ``session_dir``, or take a built one, and run every rule;
    AssertionError naming each broken one."""
    built = world(Path(session_dir)) if isinstance(world, type) else world
    _run(built, world_checks(session_dir))
