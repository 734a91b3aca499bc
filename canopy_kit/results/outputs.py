"""What a run writes besides its report: summary metrics (:func:`run_metrics`) and the
per-tree table's files (:func:`write_tree_tables`, :func:`write_trees`), shared by the
pipeline, batch and streaming runs; :class:`Results` is what each of them returns."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from canopy_kit.config import PipelineConfig, write_config
from canopy_kit.core.atomic import atomic_path
from canopy_kit.results.aerial_reference import recommended_aerial_column
from canopy_kit.results.tree_table import comparable_aerial_sphere, flagged
from canopy_kit.volume.verb import PAPER_VOLUME_COLUMNS


@dataclass
class Results:
    """What a run produced: the per-tree table, metrics and where the files are."""

    out_dir: Path
    trees: pd.DataFrame
    metrics: dict[str, Any]
    files: dict[str, Path]
    warnings: list[str] = field(default_factory=list)
    cache_hits: list[str] = field(default_factory=list)


def run_metrics(ctx: Any, trees: pd.DataFrame) -> dict[str, Any]:
    """Summary numbers of the run (mapping diagnostics, counts, agreement, evaluation)."""
    from canopy_kit.evaluate import stats
    from canopy_kit.results.checks import Check, run_checks
    from canopy_kit.results.checks import summary as checks_summary

    m: dict[str, Any] = {
        "n_trees": int(len(trees)),
        "preset": ctx.config.name,
        "segmenter": ctx.config.segment.method,
    }
    warnings = list(getattr(ctx.mapping, "warnings", []))
    warnings += list(getattr(ctx.segmentation, "warnings", []))
    m["mapping"] = dict(getattr(ctx.mapping, "diagnostics", {}))
    m["segmentation"] = ctx.segmentation.summary()
    m["flagged_volumes"] = int(flagged(trees, "volume_flags").sum())
    m["flagged_segments"] = int(flagged(trees, "segment_flags").sum())
    if ctx.aerial is not None and "aerial_sphere_volume_m3" in trees:
        matched = trees["aerial_sphere_volume_m3"].notna()
        ok = comparable_aerial_sphere(trees).notna()
        m["aerial"] = {
            "matched_trees": int(matched.sum()),
            "compared_trees": int(ok.sum()),
            "implausible_crowns": int((matched & ~ok).sum()),
            **dict(getattr(ctx.aerial, "diagnostics", {})),
        }
        report = getattr(ctx.aerial, "report", None) or {}
        m["aerial"]["reference_column"] = recommended_aerial_column(report)
        offset = report.get("seed_offset")
        if offset:  # the LiDAR map's georeferencing against the drone's (docs/GROUND_TRUTH.md)
            m["aerial"]["seed_offset"] = offset  # crowns minus LiDAR trees
        for col in PAPER_VOLUME_COLUMNS:
            if col in trees and ok.any():
                good = ok & trees[col].notna()
                sphere = trees.loc[good, "aerial_sphere_volume_m3"].to_numpy()
                m["aerial"][col] = stats.agreement(
                    trees.loc[good, col].to_numpy(), sphere
                ).as_dict()
    if ctx.layout is not None:
        m["layout"] = ctx.layout.as_dict()
    if ctx.evaluation:
        m["evaluation"] = ctx.evaluation
    m["warnings"] = warnings
    m["checks"] = [c.as_dict() for c in run_checks(m, trees, ctx.config.checks)]
    m["checks_summary"] = checks_summary([Check(**c) for c in m["checks"]])
    return m


def config_used(ctx: Any) -> PipelineConfig:
    """The run's config with what the mapping resolved filled in (the topics it read): written
    as config.toml and shown in the report, so a run with that file reads the same topics."""
    from dataclasses import replace

    from canopy_kit.config import MappingConfig

    mapping = getattr(ctx.mapping, "config", None)
    if isinstance(mapping, MappingConfig):
        return replace(ctx.config, mapping=mapping)
    return ctx.config


def write_tree_tables(
    ctx: Any, trees: pd.DataFrame, out: Path, provenance: dict[str, Any] | None = None
) -> dict[str, Path]:
    """trees.csv, trees.parquet, trees.geojson, config.toml and what ``canopy-kit evaluate``
    needs besides them (segmentation.json, crowns, rows, trees.gpkg): the outputs of every
    run, batch ones included."""
    from canopy_kit.segment.export import write_segmentation_summary

    files = write_trees(trees, out, provenance)
    files["config.toml"] = write_config(config_used(ctx), out / "config.toml")
    rig = getattr(ctx.mapping, "rig", None)
    if rig is not None:
        from canopy_kit.mapping.outputs import RIG_TOML, write_rig

        files[RIG_TOML] = write_rig(rig, out / RIG_TOML)
    files.update(
        {
            p.name: p
            for p in write_segmentation_summary(
                out, ctx.segmentation, trees=trees, provenance=provenance
            ).values()
        }
    )
    return files


TREES_CSV_TITLE = "canopy-kit per-tree table"


def write_trees(
    trees: pd.DataFrame, out: Path, provenance: dict[str, Any] | None = None
) -> dict[str, Path]:
    """The per-tree table as trees.csv (rounded to each column's meaning, ``provenance`` in
    its CSVW sidecar trees.csv-metadata.json: ``canopy_kit.io.csv_table``), trees.parquet
    (full precision, ``provenance`` in its schema metadata) and trees.geojson (none when no
    tree has a WGS84 position)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from canopy_kit.io.csv_table import write_csv_table
    from canopy_kit.segment.export import write_geojson

    files: dict[str, Path] = {}
    files.update(write_csv_table(trees, out / "trees.csv", provenance, TREES_CSV_TITLE))
    table = pa.Table.from_pandas(trees, preserve_index=False)
    if provenance:
        meta = dict(table.schema.metadata or {})
        meta[b"provenance"] = json.dumps(provenance).encode()
        table = table.replace_schema_metadata(meta)
    with atomic_path(out / "trees.parquet") as tmp:
        pq.write_table(table, tmp)
    files["trees.parquet"] = out / "trees.parquet"
    written = write_geojson(out, {"trees.geojson": trees_geojson(trees, provenance)})
    files.update({p.name: p for p in written.values()})
    return files


def trees_geojson(trees: pd.DataFrame, provenance: dict[str, Any] | None = None) -> str | None:
    """Tree positions as an RFC 7946 FeatureCollection (WGS84 ``[lon, lat]``, the table's
    columns as properties); None when no tree has a position (a map without a CRS)."""
    from canopy_kit.io import geojson

    if "lat" not in trees or "lon" not in trees or not trees["lat"].notna().any():
        return None
    features = [
        geojson.feature(geojson.point(rec["lon"], rec["lat"]), rec)
        for rec in trees.to_dict(orient="records")
        if pd.notna(rec["lon"]) and pd.notna(rec["lat"])
    ]
    return geojson.feature_collection(features, provenance)
