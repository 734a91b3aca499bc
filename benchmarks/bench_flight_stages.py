"""Photos to crowns, stage by stage, of this code beside another checkout's, on the same flights.

    git worktree add /tmp/old <rev>
    python benchmarks/bench_flight_stages.py FLIGHT [FLIGHT ...] --against /tmp/old --repeats 2

A FLIGHT is a simulated session folder with ``drone/`` and ``truth/frame.json`` (e.g. one that
``bench_ground_truth.py`` or ``bench_hull_flights.py`` rendered, or ``canopy-kit simulate
--drone``). Each run is ``process_flight`` in a fresh process (SfM on one thread, seed 0, so
both codes reconstruct the same model; surface, orthomosaic, crowns and hull as the defaults
say), the two codes alternating so both see the same spells of the machine. Printed: wall
seconds per stage (median of the repeats), CPU seconds of the whole run, and what came out
(crowns, their summed widest diameter and hull volume), which must agree between the codes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _checkout import child_json

STAGES = ("sfm", "surface", "orthomosaic", "crowns", "hull")


def process_once(flight: Path) -> dict:
    """One ``process_flight`` of ``flight``'s photos in its simulated frame: stage times, CPU
    seconds and a summary of the crowns."""
    import numpy as np

    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.core.parallel import cpu_seconds
    from ground_truth.pipeline import process_flight

    data = json.loads((flight / "truth" / "frame.json").read_text())
    frame = LocalFrame.from_dict(data.get("frame", data))
    with tempfile.TemporaryDirectory() as tmp:
        wall, cpu = time.perf_counter(), cpu_seconds()
        result = process_flight(flight / "drone", Path(tmp) / "out", frame=frame, threads=1)
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    crowns = result.crowns
    hull = crowns["hull_volume_m3"] if "hull_volume_m3" in crowns else np.array([np.nan])
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "stages": {k: float(v) for k, v in result.report["timings_s"].items()},
        "crowns": int(len(crowns)),
        "diameter_sum_m": float(crowns["diameter_max_m"].sum()),
        "hull_sum_m3": float(np.nansum(hull)),
    }


def _row(flight: str, code: str, runs: list[dict]) -> str:
    med = statistics.median
    stages = " | ".join(
        f"{med(r['stages'].get(k, float('nan')) for r in runs):.1f}" for k in STAGES
    )
    r0 = runs[0]
    return (
        f"| {flight} | {code} | {len(runs)} | {med(r['wall_s'] for r in runs):.1f} | "
        f"{med(r['cpu_s'] for r in runs):.1f} | {stages} | {r0['crowns']} | "
        f"{r0['diameter_sum_m']:.2f} | {r0['hull_sum_m3']:.1f} | "
        f"{min(r['load'] for r in runs):.1f}-{max(r['load'] for r in runs):.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flights", nargs="*", type=Path)
    parser.add_argument("--against", type=Path, help="another checkout, run alternately")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(process_once(args.child)))
        return
    if not args.flights:
        parser.error("name at least one flight folder (with drone/ and truth/frame.json)")
    for flight in args.flights:
        if not (flight / "drone").is_dir() or not (flight / "truth" / "frame.json").is_file():
            sys.exit(f"{flight}: not a simulated flight (needs drone/ and truth/frame.json)")
    codes = {"this code": None} | ({str(args.against): args.against} if args.against else {})
    print(
        "| flight | code | runs | wall s | CPU s | "
        + " | ".join(f"{k} s" for k in STAGES)
        + " | crowns | sum of widest diameters m | sum of hull volumes m³ | load |"
    )
    print("|" + "---|" * (10 + len(STAGES)))
    for flight in args.flights:
        runs: dict[str, list[dict]] = {name: [] for name in codes}
        for _ in range(args.repeats):
            for name, code in codes.items():
                argv = [__file__, "--child", str(flight)]
                runs[name].append(child_json(argv, code, f"{name} on {flight}"))
        for name in codes:
            print(_row(flight.name, name, runs[name]), flush=True)


if __name__ == "__main__":
    main()
