"""``canopy-kit run BAG --stream``: print each tree as the drive passes it."""

from __future__ import annotations

import time
from pathlib import Path

from canopy_kit.config import PipelineConfig

LIVE_TABLE = "trees.live.csv"  # the trees as they come (canopy_kit.streaming.run)


def run_streaming(
    config: PipelineConfig,
    bag: Path,
    out: Path,
    extra_inputs: Path | None = None,
    orchard: str | None = None,
) -> None:
    """Stream one session, one line per emitted tree, then where the table is."""
    from canopy_kit.cli.common import console, progress_bar
    from canopy_kit.errors import InputError

    if extra_inputs is not None:
        raise InputError(
            f"{extra_inputs}: --stream takes neither --drone-images nor --truth "
            "(run without --stream to check the trees against them)"
        )
    from canopy_kit.streaming import run_stream
    from canopy_kit.volume.verb import volume_column

    method = config.volume.methods[0] if config.volume.methods else None
    shown = []

    def show(tree) -> None:
        if not shown and method:  # said with the first tree: a refused bag prints no more
            console.print(
                f"streaming {bag}: one line per tree as the robot passes it (V: {method}); "
                "labels are provisional (the rows seen so far), trees.csv has the final ones"
            )
        shown.append(tree.index)
        v = tree.values
        volume = f"  V {v[volume_column(method)]:.2f} m³" if method else ""
        where = (
            f"{tree.lat:.7f}, {tree.lon:.7f}"
            if tree.lat == tree.lat
            else f"x {v['x']:.1f}, y {v['y']:.1f} (odometry)"
        )
        console.print(
            f"tree {tree.index:4d}  {tree.label:>5s}  {where}  "
            f"h {v['height_m']:.2f} m  d {v['crown_diameter_m']:.2f} m{volume}"
        )

    started = time.time()
    try:
        with progress_bar(transient=True) as progress:
            results = run_stream(config, bag, out, progress=progress, on_tree=show, orchard=orchard)
    except BaseException:
        if not shown:
            _drop_empty_live_table(out / LIVE_TABLE, started)
        raise
    m = results.metrics
    s = m["streaming"]
    console.print(
        f"[green]done[/]: {m['n_trees']} trees streamed ({m['segmenter']}); window peak "
        f"{s['peak_window_points']:,} points ({s['peak_window_mb']:.0f} MB), emission delay "
        f"median {s['emission_delay_s']['median'] or 0:.1f} s"
    )
    for w in results.warnings:
        console.print(f"  [yellow]warning[/]: {w}")
    console.print(f"  trees: {results.files['trees.csv']}")


def _drop_empty_live_table(path: Path, since: float) -> None:
    """Remove the live table a stream that stopped before its first tree wrote (its header
    only): a refused run leaves nothing behind. Never a table with a tree or an older one."""
    try:
        if path.stat().st_mtime >= since - 1 and len(path.read_text().splitlines()) <= 1:
            path.unlink()
    except (OSError, UnicodeDecodeError):
        pass
