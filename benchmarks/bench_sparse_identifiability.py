"""How much of a sparse crown's envelope its foliage determines, with no scan at all (issue 25).

A sparse young crown's true volume is the envelope the simulator draws its leaf clusters in.
Here every leaf cluster of every crown is known exactly (the six vertices of each flattened
octahedron, ``canopy_kit.sim.scene.leaf_cluster_vertices``): no occlusion, no segmentation,
no sensor. Whatever error an estimator makes on these points is a floor for what it can do on
any scan of the same trees. Printed per crown form, as estimate / true envelope volume
(5th, 50th, 95th percentile) and the mean absolute error:

- ``convex_hull`` of all vertices;
- ``efron``: the hull of the vertices thinned to 0.2 m, corrected for its sample
  (``canopy_kit.volume.hull.sample_corrected_hull``, what ``adaptive_alpha`` takes for a
  sparse crown);
- ``ellipsoid``: the minimum-volume enclosing ellipsoid of all vertices
  (``canopy_kit.volume.ellipsoid``, the ``enclosing_ellipsoid`` estimator);
- ``hull x g(n)``: the hull times a factor fitted on the cluster count n (log-linear,
  leave-one-out over the crowns of every form printed, pooled): what a calibration on n
  could give with n known exactly (a scan sees only part of it) and the form unknown.

The forms: the simulator's sparse young tree (``crown_form = "sparse"``: the drawn crown
scaled by ``sparse_crown_scale``, foliage by ``sparse_foliage_scale``), and, for contrast,
full-size crowns of each form with the same thinned foliage, which no estimator was tuned on.

    .venv/bin/python benchmarks/bench_sparse_identifiability.py [--seeds 401 ... 410]
"""

from __future__ import annotations

import argparse

import numpy as np

FORMS = ("sparse", "ellipsoid", "lobed", "vase", "hedged")


def crowns(form: str, seed: int, rows: int = 2, trees_per_row: int = 8) -> list[dict]:
    """Envelope volume and estimates for every crown of one simulated orchard."""
    from canopy_kit.sim.config import OrchardSpec
    from canopy_kit.sim.orchard import generate_orchard
    from canopy_kit.sim.scene import leaf_cluster_vertices
    from canopy_kit.volume.ellipsoid import enclosing_ellipsoid
    from canopy_kit.volume.hull import hull_volume, sample_corrected_hull

    spec = OrchardSpec(crown_form=form, rows=rows, trees_per_row=trees_per_row)
    rng = np.random.default_rng(seed)
    orchard = generate_orchard(spec, rng)
    foliage = spec.sparse_foliage_scale
    out = []
    for tree in orchard.trees:
        verts = leaf_cluster_vertices(
            tree,
            rng,
            spec.foliage_density_shell * foliage,
            spec.foliage_density_core * foliage,
            spec.leaf_cluster_size_range,
            spec.leaf_penetration_m,
        )
        if len(verts) < 5 * 6:  # fewer than five clusters: no volume to speak of
            continue
        true = tree.crown.volume
        out.append(
            {
                "clusters": len(verts) // 6,
                "convex_hull": hull_volume(verts) / true,
                "efron": sample_corrected_hull(verts, 0.2).volume_m3 / true,
                "ellipsoid": enclosing_ellipsoid(verts).volume / true,
            }
        )
    return out


def calibrated_on_count(hull: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Hull / true times a factor fitted on log(cluster count), leave-one-out."""
    y, x = -np.log(hull), np.log(clusters)
    out = np.empty(len(hull))
    for i in range(len(hull)):
        keep = np.arange(len(hull)) != i
        out[i] = hull[i] * np.exp(np.polyval(np.polyfit(x[keep], y[keep], 1), x[i]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(401, 411)))
    parser.add_argument("--forms", nargs="+", default=list(FORMS), choices=FORMS)
    args = parser.parse_args()
    print("estimate / true envelope volume on complete, exact foliage: p5 / median / p95, MAPE %")
    print("| crowns | n | clusters (median) | convex_hull | efron | ellipsoid | hull x g(n) |")
    print("|---|---|---|---|---|---|---|")
    rows = {form: [r for seed in args.seeds for r in crowns(form, seed)] for form in args.forms}
    pooled = [r for form in args.forms for r in rows[form]]
    fitted = calibrated_on_count(
        np.array([r["convex_hull"] for r in pooled]), np.array([r["clusters"] for r in pooled])
    )
    for r, value in zip(pooled, fitted, strict=True):
        r["hull x g(n)"] = value
    for form in args.forms:
        clusters = np.median([r["clusters"] for r in rows[form]])
        cells = []
        for key in ("convex_hull", "efron", "ellipsoid", "hull x g(n)"):
            ratio = np.array([r[key] for r in rows[form]])
            p5, p50, p95 = np.percentile(ratio, [5, 50, 95])
            mape = 100 * np.mean(np.abs(ratio - 1))
            cells.append(f"{p5:.2f} / {p50:.2f} / {p95:.2f}, {mape:.1f}")
        label = "sparse young" if form == "sparse" else f"{form}, sparse foliage"
        print(f"| {label} | {len(rows[form])} | {clusters:.0f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
