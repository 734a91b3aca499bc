"""The curated public API: every name resolves, importing stays cheap, notebooks use it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import canopy_kit as ck

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("open3d", "pycolmap", "pyvista", "sklearn", "scipy", "pandas", "matplotlib")


@pytest.mark.parametrize("name", [n for n in ck.__all__ if not n.startswith("__")])
def test_every_public_name_resolves(name):
    assert getattr(ck, name) is not None
    assert name in dir(ck)


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_thing"):
        ck.no_such_thing  # noqa: B018


def test_public_names_are_the_library_objects():
    from canopy_kit.config import load_preset
    from canopy_kit.volume.verb import ALPHA_COLUMN, volume_column

    assert ck.load_preset is load_preset
    assert ck.volume_column is volume_column
    assert ck.ALPHA_COLUMN == ALPHA_COLUMN == volume_column("alpha_shape")
    config = ck.load_preset("pistachio")
    assert isinstance(config, ck.PipelineConfig)
    cube = [[x, y, z] for x in (0, 0.5, 1) for y in (0, 0.5, 1) for z in (0, 0.5, 1)]
    assert ck.estimate_volume(cube, "convex_hull").volume_m3 == pytest.approx(1.0)  # hand value


def test_import_is_cheap():
    """``import canopy_kit`` loads none of the heavy libraries (each name loads on use)."""
    code = f"import sys, canopy_kit; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert loaded == ""


def test_reading_a_finished_map_does_not_load_the_odometry():
    """``mapping.map_source`` (a map made elsewhere) needs no odometry, KISS-ICP or numba."""
    odometry = ("kiss_icp", "numba", "canopy_kit.mapping.pipeline", "canopy_kit.mapping.frontend")
    code = (
        "import sys, canopy_kit.mapping.map_source; "
        f"print(','.join(m for m in {odometry!r} if m in sys.modules))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert loaded == ""
    from canopy_kit.mapping import build_map
    from canopy_kit.mapping.pipeline import build_map as defined

    assert build_map is defined


# Modules a notebook may import from canopy_kit: the package's public names, the plotting
# modules (figures are the notebooks' job) and the store's query layer.
NOTEBOOK_MODULES = {
    "canopy_kit",
    "canopy_kit.report.plots",
    "canopy_kit.segment.plots",
    "canopy_kit.mapping.plots",
    "canopy_kit.sim.plots",
    "canopy_kit.store",
    "canopy_kit.paper.consistency",
    "canopy_kit.paper.summary",
    "canopy_kit.paper.experiments",
    "canopy_kit.errors",
}


@pytest.mark.parametrize(
    "notebook", sorted((ROOT / "notebooks").glob("*.py")), ids=lambda p: p.name
)
def test_notebooks_use_the_public_api(notebook):
    tree = ast.parse(notebook.read_text())
    reached = {
        node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("canopy_kit")
    }
    assert reached <= NOTEBOOK_MODULES, f"{notebook.name} reaches into {reached - NOTEBOOK_MODULES}"
    sql = [
        n.value
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and "SELECT " in n.value
    ]
    assert not sql, f"{notebook.name} sends raw SQL; use canopy_kit.store's queries"


def test_public_names_do_not_shadow_subpackages():
    """A function named like a subpackage would be replaced by the subpackage once imported."""
    import pkgutil

    subpackages = {m.name for m in pkgutil.iter_modules(ck.__path__)}
    functions = {n for n, target in ck._PUBLIC.items() if ":" in target}
    assert not functions & subpackages
