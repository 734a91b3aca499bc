"""Batch, streaming and store figures: throughput, peak memory, query time.

    .venv/bin/python benchmarks/bench_batch.py throughput [--sessions 4 --rows 2 --trees-per-row 3]
    .venv/bin/python benchmarks/bench_batch.py memory [--rows 2 4 --trees-per-row 4]
    .venv/bin/python benchmarks/bench_batch.py store [--trees 100000 --sessions 10]

``throughput``: the same small simulated sessions batch-processed on a LocalCluster of 1 and
of 2 single-threaded workers (no report, as a lab batch would run); sessions per hour.
``memory``: ``canopy-kit run`` and ``canopy-kit run --stream`` on sessions of different
lengths, each in a fresh process (peak resident memory of that process alone; mapping
single-process in both modes). ``store``: a synthetic orchard of N trees visited M times
(GNSS offsets, growth, a few removed trees), ingested through ``OrchardStore.ingest``;
then the growth, row-growth, changes, one-tree history and Parquet export timed.
Simulated sessions go to ``out/bench_batch/`` and are reused.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "out" / "bench_batch"
LIDAR = {"columns": 512}


def simulate(name: str, rows: int, trees_per_row: int, session_seed: int = 0) -> Path:
    """A pistachio session (cached under ``out/bench_batch``); returns its folder."""
    from canopy_kit.sim import load_sim_config, simulate_session

    root = OUT / "sim" / name
    if (root / "truth" / "trees.csv").exists():
        return root
    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 11,
            "session_seed": session_seed,
            "lidar": LIDAR,
            "orchard": {"rows": rows, "trees_per_row": trees_per_row},
        },
    )
    simulate_session(root, cfg, overwrite=True)
    return root


# -- throughput -------------------------------------------------------------------------------
def throughput(args: argparse.Namespace) -> None:
    from canopy_kit.pipeline.batch import SessionSpec, run_batch

    sims = [
        simulate(f"tp_{args.rows}x{args.trees_per_row}_{k}", args.rows, args.trees_per_row, k)
        for k in range(args.sessions)
    ]
    specs = [
        SessionSpec(
            f"s{k}", sim / "session", "bench", dt.date(2025, 1, 1 + k), "adaptive", report=False
        )
        for k, sim in enumerate(sims)
    ]
    rows = []
    for workers in args.workers:
        out = Path(tempfile.mkdtemp(prefix="bench_batch_"))
        cpu0 = os.times()
        rep = run_batch(specs, out, n_workers=workers, store="")
        cpu1 = os.times()
        assert rep.ok, rep.failures
        task_wall = [o.wall_s for o in rep.outcomes.values()]
        rows.append(
            {
                "workers": workers,
                "sessions": len(specs),
                "wall_s": rep.wall_s,
                "sessions_per_hour": 3600 * len(specs) / rep.wall_s,
                "mean_task_s": sum(task_wall) / len(task_wall),
                "load_1min": os.getloadavg()[0],
                "parent_cpu_s": (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system),
            }
        )
        shutil.rmtree(out, ignore_errors=True)
    print(
        f"\nBatch throughput: {args.sessions} pistachio sessions of {args.rows} rows x "
        f"{args.trees_per_row} trees, {os.cpu_count()} cores\n"
    )
    print("| workers | wall (s) | sessions / hour | mean time per session (s) | load (1 min) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['workers']} | {r['wall_s']:.0f} | {r['sessions_per_hour']:.0f} | "
            f"{r['mean_task_s']:.0f} | {r['load_1min']:.1f} |"
        )
    print(json.dumps(rows))


# -- memory -----------------------------------------------------------------------------------
CHILD = r"""
import json, resource, sys, time
from pathlib import Path
from canopy_kit.config import load_preset
mode, bag, out = sys.argv[1:4]
config = load_preset("adaptive")
config.mapping.workers = 1
t0, c0 = time.perf_counter(), time.process_time()
if mode == "stream":
    from canopy_kit.streaming import run_stream
    r = run_stream(config, bag, out)
    extra = {"window_peak_points": r.metrics["streaming"]["peak_window_points"],
             "window_peak_mb": r.metrics["streaming"]["peak_window_mb"]}
else:
    from canopy_kit.pipeline import run
    r = run(config, bag, out, use_cache=False)
    extra = {"map_points": r.metrics["mapping"]["map_points"]}
print(json.dumps({"mode": mode, "n_trees": len(r.trees), "wall_s": time.perf_counter() - t0,
                  "cpu_s": time.process_time() - c0,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **extra}))
"""


def memory(args: argparse.Namespace) -> None:
    import pandas as pd

    rows = []
    for n_rows in args.rows:
        sim = simulate(f"mem_{n_rows}x{args.trees_per_row}", n_rows, args.trees_per_row)
        duration = json.loads((sim / "truth" / "frame.json").read_text())["duration_s"]
        for mode in ("batch", "stream"):
            out = OUT / "runs" / f"{mode}_{n_rows}x{args.trees_per_row}"
            shutil.rmtree(out, ignore_errors=True)
            proc = subprocess.run(
                [sys.executable, "-c", CHILD, mode, str(sim / "session"), str(out)],
                capture_output=True,
                text=True,
                check=True,
            )
            rec = json.loads(proc.stdout.strip().splitlines()[-1])
            rows.append({"rows": n_rows, "drive_s": duration, **rec})
            if mode == "stream":  # trees and volumes against the batch run just before
                b = pd.read_csv(OUT / "runs" / f"batch_{n_rows}x{args.trees_per_row}" / "trees.csv")
                s = pd.read_csv(out / "trees.csv")
                both = b.merge(s, on="tree_id", suffixes=("_b", "_s"))  # r<row>-<label>: unique
                rel = (both["volume_alpha_m3_s"] / both["volume_alpha_m3_b"] - 1).abs()
                rows[-1]["same_labels"] = len(both) == len(b) == len(s)
                rows[-1]["max_alpha_diff_pct"] = 100 * float(rel.max()) if len(rel) else None
    print(f"\nPeak memory, batch vs streaming: pistachio, {args.trees_per_row} trees per row\n")
    print(
        "| rows | drive (s) | mode | trees | peak RSS (MB) | map / window peak (points) | "
        "wall (s) | CPU (s) | stream vs batch: labels, max alpha diff |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        pts = r.get("map_points", r.get("window_peak_points"))
        cmp = (
            f"{'same' if r['same_labels'] else 'DIFFER'}, {r['max_alpha_diff_pct']:.2f} %"
            if "same_labels" in r
            else ""
        )
        print(
            f"| {r['rows']} | {r['drive_s']:.0f} | {r['mode']} | {r['n_trees']} | "
            f"{r['peak_rss_mb']:.0f} | {pts:,} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | {cmp} |"
        )
    print(json.dumps(rows))


# -- store ------------------------------------------------------------------------------------
def store(args: argparse.Namespace) -> None:
    import numpy as np
    import pandas as pd

    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.store import OrchardStore, SessionRecord, changes, export, growth, row_growth

    rng = np.random.default_rng(0)
    per_row = 200
    n_rows = args.trees // per_row
    layout = np.array([[r * 6.0, i * 5.0] for r in range(n_rows) for i in range(per_row)])
    base = rng.uniform(15.0, 40.0, len(layout))
    frame = LocalFrame.at(37.281, -120.42)
    gone = rng.choice(len(layout), size=max(1, len(layout) // 1000), replace=False)
    tmp = Path(tempfile.mkdtemp(prefix="bench_store_"))
    path = tmp / "orchard.duckdb"
    ingest_s = []
    with OrchardStore(path) as db:
        for k in range(args.sessions):
            keep = np.ones(len(layout), bool)
            if k >= args.sessions // 2:
                keep[gone] = False
            shift = rng.normal(0, 1.0, 2)
            xy = layout[keep] + shift + rng.normal(0, 0.1, (keep.sum(), 2))
            lat, lon, _ = frame.to_wgs84(np.column_stack([xy, np.zeros(len(xy))]))
            vol = base[keep] * (1 + 0.05 * k) * rng.normal(1, 0.03, keep.sum())
            table = pd.DataFrame(
                {
                    "segment": np.arange(len(xy)),
                    "label": "L0",
                    "row": np.repeat(np.arange(n_rows), per_row)[keep],
                    "lat": lat,
                    "lon": lon,
                    "n_points": 5000,
                    "height_m": 4.0,
                    "crown_diameter_m": 4.0,
                    "volume_convex_hull_m3": 1.05 * vol,
                    "volume_alpha_m3": vol,
                    "volume_flags": "",
                }
            )
            t0, c0 = time.perf_counter(), time.process_time()
            db.ingest(
                SessionRecord(f"v{k:02d}", "big", dt.date(2025, 1, 1) + dt.timedelta(30 * k)), table
            )
            ingest_s.append((time.perf_counter() - t0, time.process_time() - c0))
        n_obs = db.one("SELECT count(*) FROM observations")[0]
        tid = int(db.one("SELECT min(tree_id) FROM trees")[0])
        timings = {}
        for name, fn in [
            ("growth (every tree x session)", lambda: growth(db)),
            ("row growth (per row x session)", lambda: row_growth(db)),
            ("changes (events)", lambda: changes(db)),
            (
                "one tree's history",
                lambda: db.query(
                    "SELECT s.date, v.volume_m3 FROM volumes v JOIN sessions s USING (session_id) "
                    "WHERE v.tree_id = ? AND v.method = 'alpha_shape' ORDER BY s.date",
                    [tid],
                ),
            ),
            ("export growth to Parquet", lambda: export(db, "growth", tmp / "growth.parquet")),
        ]:
            best, best_cpu = np.inf, np.inf
            for _ in range(3):
                t0, c0 = time.perf_counter(), time.process_time()
                res = fn()
                best = min(best, time.perf_counter() - t0)
                best_cpu = min(best_cpu, time.process_time() - c0)
            rows_out = (
                len(res)
                if hasattr(res, "__len__") and not isinstance(res, Path)
                else len(pd.read_parquet(res))
            )
            timings[name] = (best, best_cpu, rows_out)
    size_mb = path.stat().st_size / 1e6
    shutil.rmtree(tmp, ignore_errors=True)
    print(
        f"\nStore: {len(layout):,} trees x {args.sessions} sessions ({n_obs:,} observations, "
        f"{size_mb:.0f} MB on disk)\n"
    )
    wall, cpu = np.array(ingest_s).T
    print(
        f"Ingest (align + match + write, one transaction each): median {np.median(wall):.1f} s "
        f"wall ({np.median(cpu):.1f} s CPU), max {wall.max():.1f} s per session; "
        f"load (1 min) {os.getloadavg()[0]:.1f}\n"
    )
    print("| query | best of 3, wall (s) | CPU (s) | rows |")
    print("|---|---|---|---|")
    for name, (sec, cpu_s, n) in timings.items():
        print(f"| {name} | {sec:.3f} | {cpu_s:.3f} | {n:,} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("throughput")
    p.add_argument("--sessions", type=int, default=4)
    p.add_argument("--rows", type=int, default=2)
    p.add_argument("--trees-per-row", type=int, default=3)
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p = sub.add_parser("memory")
    p.add_argument("--rows", type=int, nargs="+", default=[2, 4])
    p.add_argument("--trees-per-row", type=int, default=4)
    p = sub.add_parser("store")
    p.add_argument("--trees", type=int, default=100_000)
    p.add_argument("--sessions", type=int, default=10)
    args = parser.parse_args()
    {"throughput": throughput, "memory": memory, "store": store}[args.what](args)


if __name__ == "__main__":
    main()
