"""A tree's measured solid as a mesh file (PLY, STL, OBJ, VTP, VTK) for ParaView,
CloudCompare or MeshLab, through pyvista.

The surfaces the estimators draw (:class:`~canopy_kit.volume.surface.Surface`) wind every
triangle outwards (the convex hull's away from its centroid, the alpha shape's away from the
tetrahedron it bounds, so a cavity's wall faces into the cavity). :func:`surface_mesh`
checks that before anything is written: the volume VTK computes for the mesh must be the
estimator's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.errors import InputError, ProcessingError
from canopy_kit.volume.surface import Surface

MESH_SUFFIXES = (".ply", ".stl", ".obj", ".vtp", ".vtk")
VOLUME_RTOL = 1e-3  # the written mesh's volume (VTK's) against the estimator's


def surface_mesh(surface: Surface) -> Any:
    """The surface as a ``pyvista.PolyData``.

    ProcessingError when VTK's volume of the mesh is not the estimator's (a surface not
    closed, or a triangle wound inwards, would give another one).
    """
    import pyvista as pv

    faces = np.column_stack([np.full(len(surface.faces), 3), surface.faces]).ravel()
    mesh = pv.PolyData(np.asarray(surface.vertices, dtype=np.float64), faces)
    measured = float(mesh.volume)
    if not np.isclose(measured, surface.volume_m3, rtol=VOLUME_RTOL, atol=1e-9):
        raise ProcessingError(
            f"the {surface.name} surface does not bound the measured solid: VTK gives "
            f"{measured:.4f} m³ for the mesh, the estimator {surface.volume_m3:.4f} m³"
        )
    return mesh


def write_surface(path: str | Path, surface: Surface) -> Path:
    """Write the oriented mesh in the format the suffix names, atomically."""
    from canopy_kit.core.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(
            f"{path}: cannot write a mesh as {path.suffix or 'no suffix'!r} "
            f"(writable: {', '.join(MESH_SUFFIXES)})"
        )
    mesh = surface_mesh(surface)
    with atomic_path(path) as tmp:
        mesh.save(tmp)
    return path
