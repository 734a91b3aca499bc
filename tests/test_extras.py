"""The core install segments and measures a LAS without any extra; a stage that needs a
missing extra fails with an error naming it (the packages are hidden in a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.core.extras import EXTRAS, extra_of, needs_extra
from canopy_kit.errors import MissingExtraError
from canopy_kit.io.las_write import write_las
from tests.fixtures_sim import synthetic_orchard

ROOT = Path(__file__).resolve().parents[1]
HIDDEN = sorted({m for mods, _ in EXTRAS.values() for m in mods})

# Runs in a fresh interpreter: every module of every extra fails to import, as when the
# package is not installed; then the given code runs and its result is printed as JSON.
PRELUDE = textwrap.dedent(f"""
    import importlib.abc, json, sys
    HIDDEN = {HIDDEN!r}

    class Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HIDDEN:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None

    sys.meta_path.insert(0, Hide())
""")


def _run_without_extras(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    script = tmp_path / "without_extras.py"
    script.write_text(PRELUDE + textwrap.dedent(code))
    return subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
        check=False,
    )


def test_every_extra_module_is_declared_in_pyproject():
    """The extras table and pyproject's optional dependencies name the same packages."""
    import tomllib

    optional = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for extra, (modules, _) in EXTRAS.items():
        declared = " ".join(optional[extra]).lower().replace("-", "_")
        for module in modules:
            dist = {"kiss_icp": "kiss_icp", "distributed": "dask[distributed]"}.get(module, module)
            assert dist in declared, f"{module} of extra {extra!r} not in pyproject's {extra}"
    assert set(EXTRAS) <= set(optional)
    assert all(f"canopy-kit[{','.join(EXTRAS)}]" in dep for dep in optional["all"])


def test_needs_extra_names_the_extra_and_leaves_other_errors_alone():
    with pytest.raises(MissingExtraError, match=r"pip install 'canopy-kit\[aerial\]'"):
        with needs_extra("aerial"):
            raise ModuleNotFoundError("No module named 'pycolmap'", name="pycolmap")
    with pytest.raises(ModuleNotFoundError):  # a module of another extra is not relabelled
        with needs_extra("aerial"):
            raise ModuleNotFoundError("No module named 'gtsam'", name="gtsam")
    assert extra_of("gtsam.symbol_shorthand") == "mapping" and extra_of("numpy") is None


def test_core_install_segments_a_las_and_missing_extras_are_named(tmp_path):
    orchard = synthetic_orchard(rows=2, trees_per_row=4, seed=3)
    las = write_las(tmp_path / "orchard.laz", orchard.cloud)
    out = tmp_path / "seg"
    proc = _run_without_extras(
        f"""
        from canopy_kit.cli import main
        try:
            sys.argv = ["canopy-kit", "segment", {str(las)!r}, "--out", {str(out)!r},
                        "--export-trees"]
            main()
        except SystemExit as exc:
            assert not exc.code, exc.code
        from pathlib import Path
        from canopy_kit.io.clouds import read_cloud
        from canopy_kit.volume import estimate_volume
        volumes = {{p.stem: estimate_volume(read_cloud(p), "convex_hull").volume_m3
                   for p in sorted(Path({str(out)!r}, "trees").glob("*.laz"))}}
        result = {{"volumes": volumes,
                   "loaded": sorted(m for m in sys.modules if m.split(".")[0] in HIDDEN)}}
        from canopy_kit.errors import MissingExtraError
        from types import SimpleNamespace
        from ground_truth.sfm import run_sfm
        flight = SimpleNamespace(default_frame=lambda: None)  # SfM needs pycolmap first
        from canopy_kit.mapping.odometry import LidarOdometry, OdometrySettings
        from canopy_kit.io.open3d_clouds import read_ply, write_ply
        from canopy_kit.core.cloud import PointCloud
        import numpy as np
        ply = Path({str(tmp_path)!r}, "three.ply")
        ply.write_text("ply\\nformat ascii 1.0\\nelement vertex 3\\nproperty float x\\n"
                       "property float y\\nproperty float z\\nend_header\\n0 0 0\\n1 0 0\\n0 1 2\\n")
        result["ply_points"] = read_ply(ply).absolute_xyz.tolist()  # reading is the core's
        for name, call in [("aerial", lambda: run_sfm(flight, {str(tmp_path)!r})),
                           ("mapping", lambda: LidarOdometry(OdometrySettings())),
                           ("open3d", lambda: write_ply(Path({str(tmp_path)!r}, "w.ply"),
                                                        PointCloud(np.zeros((2, 3)))))]:
            try:
                call()
                result[name] = "no error"
            except MissingExtraError as exc:
                result[name] = str(exc)
        print(json.dumps(result))
    """,
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["loaded"] == []
    assert "canopy-kit[aerial]" in result["aerial"] and "pycolmap" in result["aerial"]
    assert "canopy-kit[mapping]" in result["mapping"] and "kiss_icp" in result["mapping"]
    assert "canopy-kit[open3d]" in result["open3d"] and "'open3d'" in result["open3d"]
    assert result["ply_points"] == [[0, 0, 0], [1, 0, 0], [0, 1, 2]]  # the file's, by hand
    assert not (tmp_path / "w.ply").exists()  # nothing half-written
    trees = pd.read_csv(out / "trees.csv")
    assert len(trees) == len(orchard.centres)  # every synthetic tree found and measured
    # Each crown is a dense shell sampled inside an ellipsoid of semi-axes 1.8, 1.8, 1.44 m:
    # the hull of its exported points fills that ellipsoid to within a few per cent.
    outer = 4 / 3 * np.pi * 1.8 * 1.8 * 1.44
    assert sorted(result["volumes"]) == sorted(trees["tree_id"])
    assert all(0.95 * outer < v <= outer for v in result["volumes"].values())
