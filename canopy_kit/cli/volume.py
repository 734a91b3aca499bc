"""``canopy-kit volume``: one tree's canopy volume from a point-cloud file."""

from __future__ import annotations

from pathlib import Path

import typer

from canopy_kit.plugins.params import PAPER_ALPHA_M


def volume(
    cloud: str = typer.Argument(
        ..., help="LAS/LAZ/PLY/PCD file holding one tree's points only, in metres"
    ),
    method: str = typer.Option(
        None,
        "--method",
        "-m",
        help="volume plugin: foliage_envelope (what the adaptive preset recommends; the "
        "default without --config), convex_hull, alpha_shape (the paper's), alpha_hull, "
        "voxel, slices, mirror, ... (see 'canopy-kit plugins volumes')",
    ),
    alpha: float = typer.Option(
        None,
        "--alpha",
        "-a",
        help=f"alpha radius in metres for alpha-based methods (default {PAPER_ALPHA_M:g})",
    ),
    voxel_size: float = typer.Option(
        None,
        "--voxel-size",
        min=0.0,
        help="thin the points to this voxel grid first, as a run "
        "measures its trees (volume.voxel_size, 0.1 m); "
        "0: every point (the default without --config)",
    ),
    config: str = typer.Option(
        None,
        "--config",
        help="a run's config.toml (or a preset name): measure as that run did, with its "
        "recommended estimator, that estimator's parameters and its voxel size; "
        "--method, --alpha and --voxel-size override",
    ),
    json: bool = typer.Option(False, "--json", help="print the result as JSON"),
    mesh: Path = typer.Option(
        None,
        "--mesh",
        help="also write the measured solid as a mesh (.ply, .stl, .obj, .vtp, .vtk; "
        "convex_hull and alpha_shape draw theirs)",
    ),
) -> None:
    """Estimate the canopy volume of the points in CLOUD with one volume method, say what that
    volume measures, and warn when the estimators disagree beyond every tree family measured
    (docs/VOLUMES.md).

    CLOUD must hold one tree and nothing else: every point counts, so ground, trunk-height
    clutter or a neighbour's crown inflate the volume and the height. canopy-kit's own
    outputs are whole orchards (map.laz of run, segmented.laz of segment); cut a tree out of
    them first (e.g. with PDAL or CloudCompare), or let run --export-trees write each tree's
    points as such a file. Those files (trees/<tree_id>.laz) give that tree's trees.csv
    volume with the run's settings: --voxel-size 0.1 and its method's --alpha.
    """
    from canopy_kit.cli.common import console, print_json
    from canopy_kit.io.clouds import read_cloud
    from canopy_kit.volume import estimator, tree_metrics
    from canopy_kit.volume.one_tree import not_one_tree

    method, params, voxel_size = _settings(method, alpha, voxel_size, config)
    est = estimator(method, **params)  # ConfigError names a parameter the method lacks
    points = read_cloud(cloud)
    measured = points.xyz
    if voxel_size > 0:  # as a run measures its trees
        from canopy_kit.core.voxel import voxel_representatives

        measured = measured[voxel_representatives(measured, voxel_size)[0]]
    result, surface = est.with_surface(measured) if mesh is not None else (est(measured), None)
    if mesh is not None:
        _write_mesh(mesh, surface, result)
    warnings = []
    several = not_one_tree(points)
    if several:
        warnings.append(
            f"{cloud} may not be one tree: {'; '.join(several)}. Every point is measured as "
            "one crown; cut one tree out first (e.g. run --export-trees)"
        )
    metrics = tree_metrics(points.xyz, volume_m3=result.volume_m3 if result.valid else None)
    what = result.extra.get("measurand") or getattr(est, "measures", "")
    disagree = _disagreement(result, measured) if result.valid else None
    if disagree:
        warnings.append(disagree)
    if json:
        print_json(
            {
                "cloud": str(cloud),
                **result.as_dict(),
                "measures": what,
                "disagreement": disagree,
                "warnings": warnings,
                "metrics": metrics.as_dict(),
                "mesh": None if mesh is None else str(mesh),
            }
        )
        return
    status = "[green]valid" if result.valid else f"[red]invalid: {result.reason}"
    console.print(
        f"{cloud}: {result.volume_m3:.3f} m³ by {result.method} "
        f"{result.params} from {result.n_points} points ({status}[/])"
    )
    if what:
        console.print(f"measures: {what}")
    if mesh is not None:
        console.print(f"mesh of the measured solid: {mesh}")
    for warning in warnings:
        console.print(f"[yellow]warning: {warning}[/]")
    console.print(
        f"height {metrics.height_m:.2f} m, crown diameter max "
        f"{metrics.crown_diameter_max_m:.2f} m / mean {metrics.crown_diameter_mean_m:.2f} m, "
        f"sphere volume {metrics.sphere_volume_m3:.2f} m³"
    )


DEFAULT_METHOD = "foliage_envelope"


def _write_mesh(path: Path, surface, result) -> None:
    """The solid behind ``result`` as a mesh file; InputError when there is none to write."""
    from canopy_kit.errors import InputError
    from canopy_kit.volume.mesh_export import write_surface
    from canopy_kit.volume.verb import DRAWN_METHODS

    if surface is None:
        why = result.reason if not result.valid else f"{result.method} draws no surface"
        raise InputError(
            f"--mesh {path}: no solid to write ({why}); the methods that draw theirs: "
            f"{', '.join(DRAWN_METHODS)}"
        )
    write_surface(path, surface)


def _settings(
    method: str | None, alpha: float | None, voxel_size: float | None, config: str | None
) -> tuple[str, dict, float]:
    """The method, its parameters and the voxel size: the options, else the run's config
    (its recommended estimator, that estimator's parameters, volume.voxel_size), else the
    defaults (foliage_envelope, every point)."""
    params: dict = {}
    if config is not None:
        from canopy_kit.config import load_preset

        volume = load_preset(config).volume
        method = method or volume.recommended
        params = dict(volume.params.get(method, {}))
        voxel_size = volume.voxel_size if voxel_size is None else voxel_size
    if alpha is not None:
        params["alpha"] = alpha
    return method or DEFAULT_METHOD, params, 0.0 if voxel_size is None else voxel_size


def _disagreement(result, xyz) -> str | None:
    """The flag of :func:`canopy_kit.volume.uncertainty.disagreement` for ``result`` against
    the estimators it is compared with on the tree families (measured here), else None."""
    from canopy_kit.volume import estimate_volume
    from canopy_kit.volume.uncertainty import AGREEMENT, disagreement

    wanted = {b for (a, b, _) in AGREEMENT if a == result.method}
    wanted |= {m for pair in AGREEMENT for m in pair[:2] if result.method in pair[:2]}
    wanted.discard(result.method)
    others = {}
    for other in sorted(wanted):
        r = estimate_volume(xyz, other)
        if r.valid:
            others[other] = r.volume_m3
    found = disagreement(
        result.method, result.volume_m3, others, result.extra.get("crown_kind", "")
    )
    return None if found is None else found.flag
