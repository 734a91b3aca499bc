"""The crown-following split (``segment.crowns``) on shells with a known answer.

A big crown and a small one planted 2 m from it, as the simulator's doubled almond trees:
what a scanner sees is the outer surface of their union, so each visible point lies on
the shell of its own crown and outside the other. The nearest trunk in the horizontal
plane puts the border half-way between the trunks; the true border (where the shells
meet) lies much closer to the small tree.
"""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.evaluate.segmentation_score import score_point_labels
from canopy_kit.segment.crowns import crown_split, fit_crowns, point_normals


def shell(
    rng: np.random.Generator,
    centre: np.ndarray,
    radii: tuple[float, float],
    n: int,
    thickness: float = 0.15,
) -> np.ndarray:
    """Points on (just inside) an ellipsoidal shell with horizontal/vertical radii."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 1.0 - thickness * rng.random(n)
    return centre + u * r[:, None] * np.array([radii[0], radii[0], radii[1]])


def union_surface(
    rng: np.random.Generator,
    crowns: list[tuple[np.ndarray, tuple[float, float]]],
    density: float = 250.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Visible points of overlapping crowns (each crown's shell outside the others), truth ids."""
    pts, ids = [], []
    for k, (c, (h, v)) in enumerate(crowns):
        area = 4 * np.pi * h * max(h, v)
        p = shell(rng, c, (h, v), int(density * area))
        outside = np.ones(len(p), bool)
        for j, (c2, (h2, v2)) in enumerate(crowns):
            if j != k:
                d = (p - c2) / np.array([h2, h2, v2])
                outside &= np.linalg.norm(d, axis=1) > 1.0
        keep = outside & (p[:, 2] > 0.8)  # the canopy band
        pts.append(p[keep])
        ids.append(np.full(keep.sum(), k))
    return np.concatenate(pts), np.concatenate(ids)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_crown_split_follows_a_small_crown_inside_a_big_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    big = (np.array([0.0, 0.0, 3.0]), (3.0, 2.2))
    small = (np.array([0.0, 2.2, 2.5]), (2.3, 1.7))
    xyz, truth = union_surface(rng, [big, small])
    trunks = np.array([[0.0, 0.0], [0.0, 2.2]])
    nearest = np.linalg.norm(xyz[:, None, :2] - trunks[None], axis=2).argmin(axis=1)
    labels = crown_split(xyz, trunks)
    voronoi = score_point_labels(nearest, truth)
    crowns = score_point_labels(labels, truth)
    assert crowns.n_correct == 2
    # The 2-D border half-way between the trunks gives the small tree a slice of the big
    # crown: point-wise the crown split is clearly better.
    assert np.mean(labels == truth) >= 0.97
    assert np.mean(labels == truth) > np.mean(nearest == truth) + 0.05
    assert voronoi.trees.iou.min() < crowns.trees.iou.min()


def test_fit_crowns_recovers_centres_from_caps() -> None:
    """Only caps are seen (each crown hidden inside the other near their meeting), yet the
    normal lines meet near each crown's centre and the shells fit its radii."""
    rng = np.random.default_rng(5)
    big = (np.array([0.0, 0.0, 3.0]), (3.0, 2.2))
    small = (np.array([0.0, 2.2, 2.5]), (2.3, 1.7))
    xyz, truth = union_surface(rng, [big, small])
    centre, semi = fit_crowns(xyz, point_normals(xyz), truth, 2, np.zeros((2, 2)))
    assert np.linalg.norm(centre[0] - big[0]) < 0.4
    assert np.linalg.norm(centre[1] - small[0]) < 0.5
    assert semi[0, 0] > semi[1, 0]  # the big crown is found bigger


def test_crown_split_trivial_inputs() -> None:
    xyz = np.random.default_rng(0).normal(size=(50, 3))
    assert np.all(crown_split(xyz, np.zeros((1, 2))) == 0)
    two = crown_split(xyz, np.array([[-5.0, 0.0], [5.0, 0.0]]))
    assert set(np.unique(two)) <= {0, 1}


def test_neighbourhood_covariances_match_numpy() -> None:
    """The compiled scatter matrices equal numpy's gather, mean and einsum."""
    from scipy.spatial import cKDTree

    from canopy_kit.segment.kernels import neighbourhood_covariances

    xyz = np.random.default_rng(5).normal(0, 2, (3000, 3))
    _, nb = cKDTree(xyz).query(xyz, k=12)
    p = xyz[nb] - xyz[nb].mean(axis=1, keepdims=True)
    expected = np.einsum("nki,nkj->nij", p, p)
    assert np.allclose(neighbourhood_covariances(xyz, nb), expected, rtol=1e-12, atol=1e-12)


def test_normals_of_a_plane_are_its_normal() -> None:
    rng = np.random.default_rng(6)
    xy = rng.uniform(-1, 1, (2000, 2))
    tilt = np.array([0.3, -0.2])  # z = 0.3 x - 0.2 y
    xyz = np.column_stack([xy, xy @ tilt])
    normal = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    assert np.allclose(np.abs(point_normals(xyz) @ normal), 1.0, atol=1e-9)
