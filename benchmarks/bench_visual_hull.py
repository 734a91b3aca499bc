"""Visual-hull crown volumes (ground_truth.visual_hull) of processed drone flights against the
simulator's exact crown volumes, beside the nadir models of the same run.

    .venv/bin/python benchmarks/bench_visual_hull.py [FLIGHT ...] [--close-m 0.45] [--work-size 800]

A FLIGHT is a session folder that ``benchmarks/bench_ground_truth.py --only accuracy`` rendered
and processed (``work/bench_ground_truth/<orchard>_4x10_s1[_double-grid]``, its ``gt_imagery``
output). The registered cameras come from the run's ``cameras.csv``; each photo's vegetation
mask (excess green over one Otsu threshold, as the surface stage uses) is closed with a disk of
``--close-m`` metres at the ground (leaf-cluster gaps are not the crown's outline) and its holes
filled. Prints per flight the bias, MAPE and range of each volume against ``crown_volume_m3``.
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


def cameras_and_photos(root: Path, gt: Path, work_size: int) -> tuple[list, list]:
    """The run's registered cameras (scaled to ``work_size``) and their photos."""
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from ground_truth.camera import PosedCamera

    cameras, rgbs = [], []
    for r in pd.read_csv(gt / "cameras.csv").itertuples():
        with Image.open(root / "drone" / r.image) as im:
            w, h = im.size
            f = min(1.0, work_size / max(w, h))
            rgbs.append(np.asarray(im.convert("RGB").resize((round(w * f), round(h * f)))))
        rotation = Rotation.from_quat([r.qx, r.qy, r.qz, r.qw]).as_matrix().T
        centre = np.array([r.x, r.y, r.z])
        params = (r.focal_px * f, w * f / 2, h * f / 2)
        size = (round(w * f), round(h * f))
        cameras.append(
            PosedCamera(r.image, "SIMPLE_PINHOLE", params, *size, rotation, -rotation @ centre)
        )
    return cameras, rgbs


def silhouettes(rgbs: list, cameras: list, ground_z: float, close_m: float) -> list:
    """Closed, hole-filled vegetation masks (the closing disk is ``close_m`` at the ground)."""
    from scipy.ndimage import binary_closing, binary_fill_holes

    from ground_truth.crowns import vegetation_images

    out = []
    for cam, green in zip(cameras, vegetation_images(rgbs), strict=True):
        gsd = (cam.center[2] - ground_z) / cam.focal
        r = max(int(round(close_m / gsd / 2)), 1)
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        disk = xx**2 + yy**2 <= r * r
        out.append(binary_fill_holes(binary_closing(green > 0.5, disk)).astype(np.float32))
    return out


def main() -> None:
    from scipy.spatial import cKDTree

    from ground_truth.pipeline import load_result
    from ground_truth.visual_hull import crown_hull_volumes

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("flights", nargs="*", type=Path, default=DEFAULT)
    parser.add_argument("--close-m", type=float, default=0.45)
    parser.add_argument("--work-size", type=int, default=800)
    args = parser.parse_args()
    for root in args.flights:
        gt = root / "gt_imagery"
        result = load_result(gt)
        cameras, rgbs = cameras_and_photos(root, gt, args.work_size)
        ground_z = float(np.nanmedian(result.surface.dtm))
        masks = silhouettes(rgbs, cameras, ground_z, args.close_m)
        t0 = time.perf_counter()
        seg, surface = result.segmentation, result.surface
        hull = crown_hull_volumes(
            cameras, masks, seg.labels, seg.grid, result.crowns, surface.dtm, surface.grid
        )
        seconds = time.perf_counter() - t0
        truth = pd.read_csv(root / "truth" / "trees.csv")
        _, nearest = cKDTree(truth[["crown_x", "crown_y"]]).query(result.crowns[["x", "y"]])
        exact = truth["crown_volume_m3"].to_numpy()[nearest]
        print(f"## {root.name}: {len(cameras)} photos, {len(hull)} crowns, hull {seconds:.1f} s")
        for name, v in (
            ("visual hull", hull),
            ("ellipsoid", result.crowns["ellipsoid_volume_m3"].to_numpy()),
            ("envelope", result.crowns["envelope_volume_m3"].to_numpy()),
        ):
            e = (v - exact) / exact * 100
            print(
                f"  {name:12s} bias {e.mean():+6.1f} %  MAPE {np.abs(e).mean():5.1f} %  "
                f"range {e.min():+.0f}..{e.max():+.0f} %"
            )


if __name__ == "__main__":
    main()
