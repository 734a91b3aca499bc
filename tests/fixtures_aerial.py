"""Helpers for the drone ground-truth tests: synthetic photos and aerial results."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd

NADIR = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera x east, y south, z down


def two_photos_of_a_block(height: float) -> tuple[list, list[np.ndarray]]:
    """Two nadir photos (30 m up, 8 m apart) of textured flat ground with a 6 × 6 m block
    ``height`` metres tall at the origin: their cameras and grey images."""
    from canopy_kit.sim.drone_render import PinholeView, fbm2
    from ground_truth.camera import camera_from_pose

    cams, images = [], []
    for k, cx in enumerate((-4.0, 4.0)):
        view = PinholeView(np.array([cx, 0.0, 30.0]), NADIR, 400.0, 300, 300)
        d = view.ray_directions().reshape(-1, 3)
        t_top = (height - 30.0) / d[:, 2]
        p = view.position + d * t_top[:, None]
        on_block = (np.abs(p[:, 0]) < 3) & (np.abs(p[:, 1]) < 3)
        t = np.where(on_block, t_top, (0.0 - 30.0) / d[:, 2])
        p = view.position + d * t[:, None]
        images.append(fbm2(p[:, 0], p[:, 1], 0.6, 3, 5).reshape(300, 300).astype(np.float32))
        cams.append(
            camera_from_pose(
                f"c{k}", "SIMPLE_PINHOLE", (400.0, 150.0, 150.0), 300, 300, view.position, NADIR
            )
        )
    return cams, images


def aerial_result(diameters: list[float] | np.ndarray) -> SimpleNamespace:
    """An aerial result whose crowns, one per segment 0.., all matched, have these diameters
    (sphere volumes from them, no ellipsoid or CHM volume)."""
    d = np.asarray(diameters, float)
    trees = pd.DataFrame(
        {
            "segment": np.arange(len(d)),
            "matched": True,
            "aerial_diameter_max_m": d,
            "aerial_diameter_mean_m": d,
            "aerial_sphere_volume_m3": np.pi * d**3 / 6,
            "aerial_ellipsoid_volume_m3": np.nan,
            "aerial_chm_volume_m3": np.nan,
            "aerial_height_m": 4.0,
            "aerial_distance_m": 0.2,
        }
    )
    return SimpleNamespace(trees=trees)


def synthetic_hedgerows(
    bearing_deg: float = 20.0,
    rows: int = 3,
    trees_per_row: int = 7,
    row_spacing: float = 7.5,
    bow_m: float = 0.0,
    seed: int = 0,
    res: float = 0.1,
):
    """An 'orthomosaic' and CHM of hedgerows: crowns 5.2-6.4 m wide on 4.2-5.2 m spacing, so
    neighbours overlap by 0.5-2 m; boxy domes (the CHM dips little between two trees),
    a random lean of the crown off its trunk up to 0.4 m; rows along ``bearing_deg`` from
    north, bowed by ``bow_m`` in the middle. Returns (grid, rgb, chm, crown centres (N, 2),
    row index per crown)."""
    from ground_truth.raster import Grid

    rng = np.random.default_rng(seed)
    a = np.radians(90.0 - bearing_deg)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    centres, row_of, sizes = [], [], []
    for r in range(rows):
        along = np.cumsum(np.r_[0.0, rng.uniform(4.2, 5.2, trees_per_row - 1)])
        length = along[-1]
        for s in along:
            bow = bow_m * (1.0 - (2.0 * s / length - 1.0) ** 2)
            lean = rng.uniform(0.0, 0.4) * np.array([np.cos(t := rng.uniform(0, 6.3)), np.sin(t)])
            centres.append(s * u + (r * row_spacing + bow) * v + lean)
            row_of.append(r)
            sizes.append((rng.uniform(5.2, 6.4), rng.uniform(4.4, 5.0), rng.uniform(3.5, 4.5)))
    centres = np.array(centres)
    lo, hi = centres.min(axis=0) - 6.0, centres.max(axis=0) + 6.0
    grid = Grid.covering(lo, hi, res)
    x, y = grid.centers()
    chm = np.zeros(grid.shape)
    for (cx, cy), (d_along, d_across, h) in zip(centres, sizes):
        p, q = (x - cx) * u[0] + (y - cy) * u[1], (x - cx) * v[0] + (y - cy) * v[1]
        r4 = (np.abs(p) / (d_along / 2)) ** 2.5 + (np.abs(q) / (d_across / 2)) ** 2.5
        inside = r4 < 1
        chm[inside] = np.maximum(chm[inside], h * (1 - r4[inside]) ** 0.4)
    rgb = np.empty(grid.shape + (3,), np.uint8)
    rgb[...] = (150, 120, 90)
    rgb[chm > 0.3] = (60, 110, 40)
    rgb = np.clip(rgb + rng.normal(0, 6, rgb.shape), 0, 255).astype(np.uint8)
    chm = chm + rng.normal(0, 0.05, chm.shape) * (chm > 0)
    return grid, rgb, chm, centres, np.array(row_of)


def canopy_kit_cli() -> list[str]:
    """The command that runs ``canopy-kit`` from this interpreter's environment."""
    import sys
    from pathlib import Path

    script = Path(sys.executable).with_name("canopy-kit")
    return (
        [str(script)]
        if script.exists()
        else [sys.executable, "-c", "from canopy_kit.cli import main; main()"]
    )


def processed_simulated_flight(root, preset: str, overrides: dict, seeded: bool):
    """A simulated drone flight (``load_sim_config(preset, overrides)``, drone on) processed by
    ``canopy-kit ground-truth`` in the simulator's frame, with the true trees as ``--seeds``
    when ``seeded``: (session folder, output folder, CLI stdout)."""
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session

    cfg = load_sim_config(preset, {**overrides, "drone": {"enabled": True}})
    sim, out = root / "sim", root / "out"
    simulate_drone_session(sim, cfg)
    return sim, out, ground_truth_cli(sim, out, seeded)


def ground_truth_cli(sim, out, seeded: bool) -> str:
    """``canopy-kit ground-truth`` on a simulated session's photos (``sim/drone``) in the
    simulator's frame into ``out``, the true trees as ``--seeds`` when ``seeded``: its stdout."""
    import subprocess

    seeds = ["--seeds", str(sim / "truth" / "trees.csv")] if seeded else []
    result = subprocess.run(
        [
            *canopy_kit_cli(),
            "ground-truth",
            str(sim / "drone"),
            "--out",
            str(out),
            *seeds,
            "--threads",  # COLMAP on several threads does not repeat bit for bit
            "1",
            "--frame",
            str(sim / "truth" / "frame.json"),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout
