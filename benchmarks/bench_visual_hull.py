"""Visual-hull crown volumes (``ground_truth.multiview.hull_stage``, as ``process_flight`` runs
it) of processed drone flights against the simulator's exact crown volumes, beside the nadir
models of the same run.

    .venv/bin/python benchmarks/bench_visual_hull.py [FLIGHT ...]

A FLIGHT is a session folder that ``benchmarks/bench_ground_truth.py --only accuracy`` rendered
and processed (``work/bench_ground_truth/<orchard>_4x10_s1[_double-grid]``, its ``gt_imagery``
output). The registered cameras come from the run's ``cameras.csv``; the silhouettes and the
carving are the library's (``ground_truth.silhouettes``, ``ground_truth.visual_hull``). Prints
per flight the hull stage's time and the bias, MAPE and range of each volume against
``crown_volume_m3`` (each crown against the nearest true crown).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
DEFAULT = [
    REPO / "work" / "bench_ground_truth" / "pistachio_4x10_s1",
    REPO / "work" / "bench_ground_truth" / "pistachio_4x10_s1_double-grid",
]
MODELS = ("hull_volume_m3", "sphere_volume_m3", "ellipsoid_volume_m3", "envelope_volume_m3")


def registered_cameras(gt: Path, size: tuple[int, int]) -> list:
    """The run's registered cameras (``cameras.csv``) at the photos' full ``size``."""
    from scipy.spatial.transform import Rotation

    from ground_truth.camera import PosedCamera

    w, h = size
    cameras = []
    for r in pd.read_csv(gt / "cameras.csv").itertuples():
        rotation = Rotation.from_quat([r.qx, r.qy, r.qz, r.qw]).as_matrix().T
        centre = np.array([r.x, r.y, r.z])
        cameras.append(
            PosedCamera(
                r.image, "SIMPLE_PINHOLE", (r.focal_px, w / 2, h / 2), w, h, rotation,
                -rotation @ centre,
            )
        )  # fmt: skip
    return cameras


def model_errors(crowns: pd.DataFrame, truth: pd.DataFrame) -> dict[str, np.ndarray]:
    """Per model, each crown's volume error (%) against its nearest true crown's volume."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(truth[["crown_x", "crown_y"]]).query(crowns[["x", "y"]])
    exact = truth["crown_volume_m3"].to_numpy()[nearest]
    return {m: (crowns[m].to_numpy() - exact) / exact * 100 for m in MODELS if m in crowns}


def print_errors(errors: dict[str, np.ndarray]) -> None:
    for name, e in errors.items():
        e = e[np.isfinite(e)]
        print(
            f"  {name:20s} n {len(e):3d}  bias {e.mean():+6.1f} %  MAPE {np.abs(e).mean():5.1f} %"
            f"  range {e.min():+.0f}..{e.max():+.0f} %"
        )


def print_one_to_one(crowns: pd.DataFrame, truth: pd.DataFrame) -> None:
    """The hull's bias and MAPE over the crowns one-to-one with a true tree (within 1.5 m,
    crowns cut by the mosaic border left out), as ``bench_hull_flights.py`` reports them."""
    from ground_truth.flight_accuracy import crown_agreement

    table, m = crown_agreement(crowns, truth)
    e = (table["hull_volume_m3"] / table["volume_true_m3"] - 1) * 100
    e = e[np.isfinite(e)]
    print(
        f"  one-to-one {m['matched']}/{m['trees']}: hull bias {e.mean():+.1f} %  MAPE"
        f" {e.abs().mean():.1f} %  range {e.min():+.0f}..{e.max():+.0f} %"
    )


def main() -> None:
    from ground_truth.exif import read_flight
    from ground_truth.multiview import flight_views, hull_stage
    from ground_truth.pipeline import load_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("flights", nargs="*", type=Path, default=DEFAULT)
    parser.add_argument("--outline-margin-m", type=float, default=None)
    parser.add_argument(
        "--max-outline-excess",
        type=float,
        default=None,
        help="the outline rule's limit (HullOptions.max_outline_excess; inf: grow every crown)",
    )
    args = parser.parse_args()
    for root in args.flights:
        gt = root / "gt_imagery"
        result = load_result(gt)
        flight = read_flight(root / "drone")
        cameras = registered_cameras(gt, flight.size)
        t0 = time.perf_counter()
        seg, surface = result.segmentation, result.surface
        crowns = result.crowns.copy()
        from ground_truth.visual_hull import HullOptions

        given = {}
        if args.outline_margin_m is not None:
            given["outline_margin_m"] = args.outline_margin_m
        if args.max_outline_excess is not None:
            given["max_outline_excess"] = args.max_outline_excess
        opts = HullOptions(**given)
        hulls = hull_stage(flight, cameras, seg, crowns, surface, opts)
        crowns["hull_volume_m3"], grown = hulls.volumes, hulls.grown
        seconds = time.perf_counter() - t0
        views = flight_views(cameras)["views"]
        print(
            f"## {root.name}: {len(cameras)} photos ({views}), {len(crowns)} crowns, hull {seconds:.1f} s,"
            f" margin {opts.outline_margin_m} m on {grown} crowns (max outline excess {opts.max_outline_excess})"
        )
        truth = pd.read_csv(root / "truth" / "trees.csv")
        print_errors(model_errors(crowns, truth))
        print_one_to_one(crowns, truth)


if __name__ == "__main__":
    main()
