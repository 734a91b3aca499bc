"""Aerial ground truth on simulated drone flights: accuracy against the simulator's truth, and speed.

Prints the numbers quoted in docs/BENCHMARKS.md ("Ground truth (drone photogrammetry)")
and docs/GROUND_TRUTH.md:

* accuracy: pistachio and almond flights (4 rows x 10 trees, a seed the defaults were not
  tuned on): registration, camera georeferencing error, crown detection, diameter and
  height errors, volume-model biases; crowns from the imagery alone (the preset's
  ``crown_seeds``) and seeded by tree positions;
* sphere-model bias of the paper's ground truth against the exact crown volume, on many
  simulated trees (no photogrammetry involved);
* speed: SfM time per image and in total for about 20 and 50 photos, and the surface,
  orthomosaic and crown stages.

Usage: ``python benchmarks/bench_ground_truth.py [--work DIR] [--only accuracy|sphere|speed]
[--orchard KIND] [--pattern nadir double-grid orbit]``.
Flights are rendered once into ``--work`` (default ``work/bench_ground_truth``, git-ignored)
and reused.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
ACCURACY_FLIGHTS = [("pistachio", 4, 10, 1), ("almond", 4, 10, 1)]
SPEED_FLIGHTS = [("pistachio", 3, 7, 2), ("pistachio", 6, 12, 2)]  # about 20 and 50 photos


def flight(work: Path, kind: str, rows: int, trees: int, seed: int, pattern: str = "nadir") -> Path:
    """A rendered drone-only session (cached) flown in ``pattern`` (nadir, double-grid, orbit)."""
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session

    suffix = "" if pattern == "nadir" else f"_{pattern}"
    root = work / f"{kind}_{rows}x{trees}_s{seed}{suffix}"
    if not (root / "truth" / "drone_cameras.csv").exists():
        cfg = load_sim_config(
            kind,
            {
                "seed": seed,
                "orchard": {"rows": rows, "trees_per_row": trees},
                "drone": {"enabled": True, "pattern": pattern},
            },
        )
        t0 = time.perf_counter()
        simulate_drone_session(root, cfg)
        print(f"  rendered {root.name} in {time.perf_counter() - t0:.0f} s")
    return root


def frame_of(root: Path):
    from canopy_kit.core.geo import LocalFrame

    return LocalFrame.from_dict(json.loads((root / "truth" / "frame.json").read_text())["frame"])


def accuracy(work: Path, orchards: list[str] | None = None, patterns: tuple = ("nadir",)) -> None:
    from ground_truth import process_flight
    from ground_truth.flight_accuracy import camera_errors, crown_agreement

    print("## accuracy against simulator truth")
    for (kind, rows, trees, seed), pattern in itertools.product(ACCURACY_FLIGHTS, patterns):
        if orchards and kind not in orchards:
            continue
        root = flight(work, kind, rows, trees, seed, pattern)
        truth = pd.read_csv(root / "truth" / "trees.csv")
        result = None
        for seeding in ("imagery", "tree_positions"):  # imagery: the preset's crown_seeds
            out = root / f"gt_{seeding}"
            t0, c0 = time.perf_counter(), time.process_time()
            # The second run reuses SfM, surface and mosaic: only the crowns differ.
            result = process_flight(
                root / "drone",
                out,
                frame=frame_of(root),
                reuse=result,
                seeds=root / "truth" / "trees.csv" if seeding == "tree_positions" else None,
            )
            total, cpu = time.perf_counter() - t0, time.process_time() - c0
            cams = camera_errors(result.model, root / "truth" / "drone_cameras.csv")
            _, m = crown_agreement(result.crowns, truth)
            sfm = result.report["sfm"]
            line = {
                "flight": root.name,
                "pattern": pattern,
                "seeding": result.report.get("crown_seeding", seeding),
                "photos": sfm["total_images"],
                "registered": sfm["registered_images"],
                "reprojection_px": round(sfm["mean_reprojection_error_px"], 3),
                "camera_error_mean_m": round(float(cams["error_m"].mean()), 3),
                "camera_error_max_m": round(float(cams["error_m"].max()), 3),
                "gps_residual_rms_h_m": round(sfm["gps_residual_rms_horizontal_m"], 3),
                "gps_residual_rms_v_m": round(sfm["gps_residual_rms_vertical_m"], 3),
                **{k: (round(v, 3) if isinstance(v, float) else v) for k, v in m.items()},
                "alignment": sfm.get("alignment"),
                "run_wall_s": round(total, 1),
                "run_cpu_s": round(cpu, 1),
                "stage_s": {k: round(v, 1) for k, v in result.report["timings_s"].items()},
            }
            print(json.dumps(line))


def sphere_bias(n_rows: int = 10, n_trees: int = 20) -> None:
    """How wrong is the paper's sphere model, with a perfect diameter?"""
    from canopy_kit.evaluate.stats import agreement
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.orchard import generate_orchard
    from canopy_kit.sim.truth import tree_table

    print("## sphere model against the exact crown volume (perfect diameters)")
    for kind in ("pistachio", "almond"):
        cfg = load_sim_config(kind, {"orchard": {"rows": n_rows, "trees_per_row": n_trees}})
        t = tree_table(generate_orchard(cfg.orchard, np.random.default_rng(7)))
        v = t["crown_volume_m3"].to_numpy()
        for name, d in (
            ("widest extent", t["crown_diameter_m"]),
            ("mean of perpendicular extents", t["crown_diameter_mean_m"]),
        ):
            sphere = np.pi * d.to_numpy() ** 3 / 6
            a = agreement(sphere, v)
            print(
                json.dumps(
                    {
                        "orchard": kind,
                        "trees": len(t),
                        "diameter": name,
                        "bias_pct": round(a.bias_pct, 1),
                        "mape_pct": round(a.mape_pct, 1),
                        "ratio_median": round(float(np.median(sphere / v)), 3),
                        "ratio_p5_p95": [
                            round(float(q), 3) for q in np.percentile(sphere / v, [5, 95])
                        ],
                    }
                )
            )


def speed(work: Path) -> None:
    from ground_truth.exif import read_flight
    from ground_truth.sfm import run_sfm

    print("## speed (SfM on all cores of this machine)")
    print(json.dumps({"cpu_count": os.cpu_count(), "load_average": os.getloadavg()}))
    for kind, rows, trees, seed in SPEED_FLIGHTS:
        root = flight(work, kind, rows, trees, seed)
        photos = read_flight(root / "drone")
        load = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        model = run_sfm(photos, root / "sfm_speed", frame_of(root))
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
        n = len(photos.images)
        # On a shared machine the wall time mostly measures the other jobs: the CPU time
        # (all threads) over the 2 cores is what the SfM would take on an idle machine.
        print(
            json.dumps(
                {
                    "flight": root.name,
                    "photos": n,
                    "registered": model.n_registered,
                    "matching": model.matching,
                    "sfm_wall_s": round(total, 1),
                    "sfm_cpu_s": round(cpu, 1),
                    "sfm_cpu_per_photo_s": round(cpu / n, 2),
                    "idle_2core_estimate_s": round(cpu / min(os.cpu_count() or 1, 2), 1),
                    "load_average_start_end": [round(load, 1), round(os.getloadavg()[0], 1)],
                    "stages_wall_s": {k: round(v, 1) for k, v in model.timings.items()},
                }
            )
        )


def recrown(gt_dir: Path, seeds: Path | None) -> tuple[object, object, pd.DataFrame]:
    """A processed flight read back from disk with its crown stage run again by the current code."""
    from ground_truth.crowns import delineate_crowns, measure_crowns
    from ground_truth.match import read_trees
    from ground_truth.pipeline import load_result
    from ground_truth.raster import sample_bilinear

    result = load_result(gt_dir)
    ox, oy = result.ortho.grid.centers()
    chm = sample_bilinear(result.surface.grid, result.surface.chm, ox, oy)
    xy = read_trees(seeds, result.frame)[["tree_x", "tree_y"]].to_numpy() if seeds else None
    seg = delineate_crowns(result.ortho.rgb, result.ortho.valid, chm, result.ortho.grid, xy)
    return result, seg, measure_crowns(seg, chm)


def figures(work: Path, docs: Path, sources: list[list[str]] | None = None) -> None:
    """Figures for docs/GROUND_TRUTH.md: orthomosaic with crowns, DSM/CHM, one photo.

    ``sources``: [kind, flight root, processed folder, seeds CSV or "-"] per figure; default:
    the accuracy flights' runs seeded by tree positions (run ``--only accuracy`` first).
    The crown stage is run again from the processed rasters, so figures follow crown changes.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from ground_truth.match import read_trees
    from ground_truth.plots import plot_crowns, plot_surface

    docs.mkdir(parents=True, exist_ok=True)
    if not sources:
        sources = [
            [
                kind,
                str(work / f"{kind}_{r}x{t}_s{s}"),
                str(work / f"{kind}_{r}x{t}_s{s}" / "gt_tree_positions"),
                str(work / f"{kind}_{r}x{t}_s{s}" / "truth" / "trees.csv"),
            ]
            for kind, r, t, s in ACCURACY_FLIGHTS
        ]
    for kind, root_s, gt_s, seeds_s in sources:
        root = Path(root_s)
        result, seg, crowns = recrown(Path(gt_s), None if seeds_s == "-" else Path(seeds_s))
        truth = read_trees(root / "truth" / "trees.csv", result.frame)
        truth = truth.assign(
            x=truth["tree_x"], y=truth["tree_y"], diameter=truth["crown_diameter_m"]
        )
        ax = plot_crowns(result.ortho, seg, crowns, truth=truth)
        seeded = (
            "LiDAR tree positions"
            if "run" in seeds_s
            else ("tree positions" if seeds_s != "-" else "CHM maxima")
        )
        ax.set_title(
            f"{kind}: crowns seeded by {seeded} (red, numbered); true widest extent (cyan)"
        )
        ax.figure.savefig(docs / f"ground_truth_{kind}_crowns.png", dpi=80, bbox_inches="tight")
        plt.close(ax.figure)
        axes = plot_surface(result.surface)
        axes[0].figure.savefig(
            docs / f"ground_truth_{kind}_dsm_chm.png", dpi=80, bbox_inches="tight"
        )
        plt.close(axes[0].figure)
        photos = sorted((root / "drone").glob("*.jpg"))
        with Image.open(photos[len(photos) // 2]) as im:
            im.convert("RGB").save(docs / f"ground_truth_{kind}_photo.jpg", quality=85)
        print(f"  figures for {kind} in {docs}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "work" / "bench_ground_truth")
    parser.add_argument("--only", choices=["accuracy", "sphere", "speed", "figures"])
    parser.add_argument("--docs", type=Path, default=REPO / "docs" / "figures")
    parser.add_argument("--orchard", action="append", help="accuracy: only these orchards")
    parser.add_argument(
        "--pattern",
        nargs="+",
        default=["nadir"],
        choices=["nadir", "double-grid", "orbit"],
        help="accuracy: the flight patterns (drone.pattern) to fly each orchard in",
    )
    parser.add_argument(
        "--figure-flight",
        nargs=4,
        action="append",
        metavar=("KIND", "ROOT", "GT_DIR", "SEEDS"),
        help="figures from this processed flight (SEEDS: a trees CSV or -)",
    )
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.only in (None, "sphere"):
        sphere_bias()
    if args.only in (None, "accuracy"):
        accuracy(args.work, args.orchard, tuple(args.pattern))
    if args.only in (None, "speed"):
        speed(args.work)
    if args.only in (None, "figures"):
        figures(args.work, args.docs, args.figure_flight)


if __name__ == "__main__":
    main()
