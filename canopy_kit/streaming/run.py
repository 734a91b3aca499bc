"""``run_stream``: one session in streaming mode, trees written as they are emitted.

``trees.live.csv`` grows by one line per emitted tree (for whoever watches the drive); its
row and label are provisional: the rows seen so far, numbered at the moment the tree
left (a tree emitted later may stand before it in its row);
at the end the same files as the batch table are written atomically: ``trees.csv``,
``trees.parquet``, ``trees.geojson``, ``config.toml`` and ``metrics.json``. No map and no
report: streaming keeps only a window of the map.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.config import PipelineConfig, write_config
from canopy_kit.core.atomic import atomic_write_json
from canopy_kit.streaming.engine import StreamedTree, StreamSettings, TreeStream
from canopy_kit.volume.metrics import POSITION_AND_SIZE

Progress = Callable[[str, float, float], None]
LIVE_COLUMNS = [
    "index",
    "provisional_label",
    "provisional_row",
    *POSITION_AND_SIZE,
    "emitted_at_s",
    "emission_delay_s",
]


def run_stream(
    config: PipelineConfig,
    bag: str | Path,
    out: str | Path,
    settings: StreamSettings | None = None,
    progress: Progress | None = None,
    on_tree: Callable[[StreamedTree], None] | None = None,
    orchard: str | None = None,
) -> Any:
    """Stream ``bag`` through the pipeline; returns a :class:`canopy_kit.results.outputs.Results`
    (``orchard`` names the orchard in the provenance, default the bag's stem)."""
    from canopy_kit.io.bag import require_bag
    from canopy_kit.results.outputs import Results, write_trees
    from canopy_kit.results.provenance import provenance

    bag, out = require_bag(bag), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stream = TreeStream(config, bag, settings, progress)
    started, wall, cpu = time.time(), time.perf_counter(), time.process_time()
    live = out / "trees.live.csv"
    with live.open("w") as fh:
        fh.write(",".join(LIVE_COLUMNS) + "\n")
        t0 = None
        for tree in stream:
            t0 = t0 if t0 is not None else stream.georef.trajectory()[0][0]
            fh.write(",".join(_live_cells(tree, t0)) + "\n")
            fh.flush()
            if on_tree is not None:
                on_tree(tree)
    trees = final_table(stream)
    metrics = stream_metrics(stream, trees)
    metrics["timing"] = {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}
    metrics["provenance"] = provenance(
        bag, config.name, started, metrics["timing"]["wall_s"], orchard
    )
    files = {"trees.live.csv": live}
    files.update(write_trees(trees, out, metrics["provenance"]))
    files["config.toml"] = write_config(
        _config_used(config, stream.source.topics), out / "config.toml"
    )
    files["metrics.json"] = atomic_write_json(out / "metrics.json", metrics)
    return Results(out, trees, metrics, files, list(metrics["warnings"]))


def _config_used(config: PipelineConfig, topics: object | None) -> PipelineConfig:
    """``config`` with the topics the stream read (see ``mapping.pipeline.config_used``)."""
    from dataclasses import replace

    from canopy_kit.mapping.pipeline import config_used

    return (
        config if topics is None else replace(config, mapping=config_used(config.mapping, topics))
    )  # type: ignore[arg-type]


def _live_cells(tree: StreamedTree, t0: float) -> list[str]:
    v = tree.values
    cells = [
        tree.index,
        tree.label,
        tree.row,
        tree.x,
        tree.y,
        tree.lat,
        tree.lon,
        v["n_points"],
        v["height_m"],
        v["crown_diameter_m"],
        tree.emitted_at - t0,
        tree.emitted_at - tree.passed_at,
    ]
    return [
        ""
        if isinstance(c, float) and not np.isfinite(c)
        else (f"{c:.8f}" if isinstance(c, float) else str(c))
        for c in cells
    ]


def final_table(stream: TreeStream) -> pd.DataFrame:
    """Every emitted tree placed with the whole drive's GNSS fit and labelled as in batch."""
    from canopy_kit.results.tree_table import FIRST_COLUMNS
    from canopy_kit.segment.rows import assign_rows, driving_direction_from_trajectory

    if not stream.trees:
        return pd.DataFrame(columns=FIRST_COLUMNS)
    table = pd.DataFrame([t.values for t in stream.trees])
    odo = table[["x", "y"]].to_numpy(float)
    t, traj = stream.georef.trajectory()
    fit = stream.georef.fit(stream.source.gnss, None)
    if fit is not None:
        xy = odo @ fit[:2, :2].T + fit[:2, 3]
        traj_xy = traj[:, :2] @ fit[:2, :2].T + fit[:2, 3]
        lat, lon, _ = stream.georef.frame.to_wgs84(np.column_stack([xy, np.zeros(len(xy))]))
    else:
        xy, traj_xy = odo, traj[:, :2]
        lat, lon = np.full(len(xy), np.nan), np.full(len(xy), np.nan)
    direction = driving_direction_from_trajectory(traj_xy) if len(traj_xy) > 1 else None
    rows = assign_rows(xy, stream.config.rows, direction, "trajectory")
    first = t[0] if len(t) else 0.0
    table = table.rename(columns={"segment": "region_segment"})
    table["x_odometry"], table["y_odometry"] = odo[:, 0], odo[:, 1]
    table["x"], table["y"], table["lat"], table["lon"] = xy[:, 0], xy[:, 1], lat, lon
    table["tree_id"], table["label"] = rows.tree_ids, rows.labels
    table["row"], table["index_in_row"] = rows.row, rows.index_in_row
    table["emitted_at_s"] = [tr.emitted_at - first for tr in stream.trees]
    table["emission_delay_s"] = [tr.emitted_at - tr.passed_at for tr in stream.trees]
    table["segment"] = np.arange(len(table))  # emission order
    table = table.sort_values(["row", "index_in_row", "segment"], kind="stable")
    rest = [c for c in table.columns if c not in FIRST_COLUMNS]
    return table[[c for c in FIRST_COLUMNS if c in table.columns] + rest].reset_index(drop=True)


def stream_metrics(stream: TreeStream, trees: pd.DataFrame) -> dict[str, Any]:
    """Counts, the window's size, emission delays and warnings of a streaming run."""
    from dataclasses import asdict

    delay = trees["emission_delay_s"].to_numpy(float) if len(trees) else np.zeros(0)
    frame = stream.georef.frame
    return {
        "n_trees": int(len(trees)),
        "preset": stream.config.name,
        "segmenter": stream.config.segment.method,
        "mode": "stream",
        "scans": stream.source.n_scans,
        "streaming": {
            **stream.stats,
            "settings": asdict(stream.settings),
            "points_offered": stream.window.n_offered,
            "alley_lines": len(stream.layout.lines),
            "emission_delay_s": {
                "median": float(np.median(delay)) if len(delay) else None,
                "max": float(delay.max()) if len(delay) else None,
            },
        },
        "frame": frame.to_dict() if frame is not None else None,
        "warnings": list(stream.warnings),
    }
