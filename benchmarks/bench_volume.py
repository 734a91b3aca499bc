"""Per-tree time of every volume method next to Open3D's alpha shape + get_volume.

Crowns are seeded synthetic porous ellipsoids (points denser towards the shell, 2 cm
noise), each measured complete and as seen from one alley. Every method runs on the same
points; Open3D's exceptions (non-watertight meshes) are counted as failures. Prints one
markdown table; docs/BENCHMARKS.md quotes it.

    .venv/bin/python benchmarks/bench_volume.py            # 10k, 50k, 200k points
    .venv/bin/python benchmarks/bench_volume.py --sizes 10000 --trees 1   # quick look
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable

import numpy as np

from canopy_kit.volume import estimator

METHODS = ("convex_hull", "alpha_shape", "alpha_hull", "voxel", "slices", "mirror")


def crown(n: int, seed: int, one_sided: bool) -> np.ndarray:
    """``n`` points of a porous ellipsoidal crown (semi-axes drawn per tree), optionally
    only those facing a sensor line 4 m away at 1.5 m height."""
    rng = np.random.default_rng(seed)
    axes = rng.uniform([1.5, 1.4, 1.2], [2.5, 2.2, 1.8])
    out: list[np.ndarray] = []
    while sum(map(len, out)) < n:
        d = rng.normal(size=(2 * n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts = d * axes * rng.uniform(0, 1, (2 * n, 1)) ** 0.25 + [0, 0, 1.0 + axes[2]]
        if one_sided:
            normal = d / axes
            sensor = np.column_stack(
                [pts[:, 0], np.full(len(pts), -axes[1] - 2.0), np.full(len(pts), 1.5)]
            )
            pts = pts[((sensor - pts) * normal).sum(axis=1) > 0]
        out.append(pts + rng.normal(scale=0.02, size=pts.shape))
    return np.concatenate(out)[:n]


def open3d_alpha_volume(xyz: np.ndarray, alpha: float) -> float:
    """Open3D's alpha-shape mesh volume; raises when the mesh is not watertight."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pc, alpha)
    return float(mesh.get_volume())


def timed(fn: Callable[[], float], repeats: int) -> tuple[float, float | None, str | None]:
    """Median seconds over ``repeats`` runs, the value (None on failure) and the error."""
    times, value, error = [], None, None
    for _ in range(repeats):
        start = time.perf_counter()
        try:
            value = fn()
        except RuntimeError as exc:  # Open3D's get_volume on a non-watertight mesh
            error = f"{type(exc).__name__}"
        times.append(time.perf_counter() - start)
    return float(np.median(times)), (None if error else value), error


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    parser.add_argument("--trees", type=int, default=3, help="crowns per size and scan kind")
    parser.add_argument("--alpha", type=float, default=0.9)
    args = parser.parse_args()

    estimators = {
        m: estimator(m, alpha=args.alpha) if m in ("alpha_shape", "alpha_hull") else estimator(m)
        for m in METHODS
    }
    rows = []
    for n in args.sizes:
        repeats = 3 if n <= 20_000 else 1
        times: dict[str, list[float]] = {m: [] for m in (*METHODS, "open3d")}
        fails = {m: 0 for m in times}
        agree_o3d, agree_fast = [], []
        for kind in ("complete", "one-sided"):
            for t in range(args.trees):
                pts = crown(n, seed=1000 * t + n % 997, one_sided=kind == "one-sided")
                values = {}
                for m, est in estimators.items():
                    sec, res, _ = timed(lambda est=est, pts=pts: est(pts), repeats)
                    times[m].append(sec)
                    fails[m] += res is None or not res.valid
                    values[m] = res.volume_m3 if res is not None else None
                sec, v, _ = timed(lambda pts=pts: open3d_alpha_volume(pts, args.alpha), repeats)
                times["open3d"].append(sec)
                fails["open3d"] += v is None
                if v is not None:
                    agree_o3d.append(abs(values["alpha_shape"] / v - 1))
                agree_fast.append(values["alpha_hull"] / values["alpha_shape"] - 1)
        rows.append(
            (
                n,
                {m: float(np.median(s)) for m, s in times.items()},
                fails,
                2 * args.trees,
                agree_o3d,
                agree_fast,
            )
        )

    print(
        f"Volume estimators, alpha = {args.alpha} m, median seconds per tree over "
        f"{args.trees} complete + {args.trees} one-sided synthetic crowns "
        f"({platform.processor() or platform.machine()}, numpy {np.__version__})\n"
    )
    head = [
        "points",
        *METHODS,
        "open3d alpha",
        "open3d failures",
        "alpha_hull speed-up",
        "alpha_shape speed-up",
    ]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for n, med, fails, total, _, _ in rows:
        cells = [f"{n:,}"] + [f"{med[m]:.3f}" for m in METHODS] + [f"{med['open3d']:.3f}"]
        cells += [
            f"{fails['open3d']}/{total}",
            f"{med['open3d'] / med['alpha_hull']:.0f}×",
            f"{med['open3d'] / med['alpha_shape']:.1f}×",
        ]
        print("| " + " | ".join(cells) + " |")
    print()
    for n, _, fails, total, agree_o3d, agree_fast in rows:
        ours = sum(fails[m] for m in METHODS)
        o3d = (
            f"max |alpha_shape / open3d - 1| = {max(agree_o3d):.1e} on {len(agree_o3d)} "
            f"watertight meshes"
            if agree_o3d
            else "open3d failed on every crown"
        )
        print(
            f"- {n:,} points: canopy-kit failures {ours}/{total * len(METHODS)}; {o3d}; "
            f"alpha_hull / alpha_shape - 1 from {min(agree_fast):+.1%} to {max(agree_fast):+.1%}"
        )


if __name__ == "__main__":
    main()
