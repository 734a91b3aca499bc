"""The measured solid as a mesh file: written through pyvista in every offered format,
wound outwards, closed, and bounding the volume the estimator reported (VTK's own volume of
the mesh read back is the independent check)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyvista as pv
from test_cli_foundation import run_cli

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.clouds import write_cloud
from canopy_kit.testing import crown, unit_cube
from canopy_kit.volume import estimator
from canopy_kit.volume.mesh_export import MESH_SUFFIXES, write_surface


@pytest.mark.parametrize("suffix", MESH_SUFFIXES)
@pytest.mark.parametrize(
    "method, points, truth",
    [("convex_hull", unit_cube(), 1.0), ("alpha_shape", crown(3000), None)],
    ids=["hull-cube", "alpha-crown"],
)
def test_mesh_read_back_bounds_the_measured_volume(tmp_path, suffix, method, points, truth):
    result, surface = estimator(method).with_surface(points)
    path = write_surface(tmp_path / f"tree{suffix}", surface)
    mesh = pv.read(path).triangulate()
    assert mesh.n_open_edges == 0  # closed
    assert mesh.volume == pytest.approx(result.volume_m3, rel=1e-6)
    if truth is not None:
        assert mesh.volume == pytest.approx(truth, rel=1e-9)  # the unit cube, by hand
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left


def test_convex_hull_triangles_face_outwards(tmp_path):
    _, surface = estimator("convex_hull").with_surface(crown(2000, seed=3))
    mesh = pv.read(write_surface(tmp_path / "hull.vtp", surface)).compute_normals(
        cell_normals=True, point_normals=False, consistent_normals=False, auto_orient_normals=False
    )
    outward = mesh.cell_centers().points - mesh.points.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", mesh.cell_data["Normals"], outward) > 0)


def test_unknown_mesh_format_is_refused_before_writing(tmp_path):
    _, surface = estimator("convex_hull").with_surface(unit_cube())
    with pytest.raises(InputError, match=r"tree\.las: cannot write a mesh as '\.las'"):
        write_surface(tmp_path / "tree.las", surface)
    assert not list(tmp_path.iterdir())


def test_volume_command_writes_the_mesh_of_its_result(tmp_path):
    cloud = write_cloud(tmp_path / "tree.laz", PointCloud(crown(4000, seed=1)))
    out = tmp_path / "tree_alpha.ply"
    run = run_cli("volume", str(cloud), "-m", "alpha_shape", "--mesh", str(out), "--json")
    assert run.returncode == 0, run.stderr
    said = json.loads(run.stdout)
    assert said["mesh"] == str(out)
    assert pv.read(out).volume == pytest.approx(said["volume_m3"], rel=1e-6)


def test_volume_command_refuses_a_mesh_it_cannot_draw(tmp_path):
    cloud = write_cloud(tmp_path / "tree.laz", PointCloud(crown(4000, seed=1)))
    out = tmp_path / "tree.ply"
    run = run_cli("volume", str(cloud), "-m", "voxel", "--mesh", str(out))
    assert run.returncode == 2
    assert "--mesh" in run.stderr and "voxel draws no surface" in run.stderr
    assert "convex_hull" in run.stderr
    assert not out.exists()


def _lobes(seed: int) -> np.ndarray:
    """Five overlapping shells of points: alpha shapes with cavities and pinched edges."""
    rng = np.random.default_rng(seed)
    parts = []
    for centre in rng.uniform([-1.5, -1.5, 2], [1.5, 1.5, 4], (5, 3)):
        d = rng.normal(size=(1500, 3))
        parts.append(centre + d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.6, 1.2))
    return np.concatenate(parts)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("alpha", [0.3, 0.6])
def test_alpha_shape_with_cavities_is_wound_outwards(tmp_path, seed, alpha):
    """Each boundary triangle is wound away from the tetrahedron it bounds, so VTK's volume
    of the written mesh (cavity walls facing into their cavity) is the alpha complex's sum
    of tetrahedra even where the boundary is not a single sphere-like surface."""
    result, surface = estimator("alpha_shape", alpha=alpha).with_surface(_lobes(seed))
    mesh = pv.read(write_surface(tmp_path / "lobes.vtp", surface))
    assert mesh.volume == pytest.approx(result.volume_m3, rel=1e-6)
