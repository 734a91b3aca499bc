"""``canopy-kit info PATH``: what a bag or point-cloud file holds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer


def info(
    path: Path = typer.Argument(
        ..., help="A ROS1 .bag, a ROS2 bag folder, or a LAS/LAZ/PLY/PCD file"
    ),
    json_output: bool = typer.Option(False, "--json", help="Print the facts as JSON"),
) -> None:
    """Show what a bag (topics, types, counts, time span) or point cloud (points,
    attributes, bounds computed from the points, CRS) holds, and what is wrong with it."""
    from canopy_kit.cli.common import console, print_json
    from canopy_kit.io.info import describe_path

    facts = describe_path(path)
    if json_output:
        print_json(facts)
        return
    from canopy_kit.cli.tables import print_grid

    for grid in grids(facts):
        print_grid(grid)
    for w in facts.get("warnings", []):
        console.print(f"[yellow]warning[/]: {w}", markup=True, highlight=False)
    unusable = why_run_cannot_use(facts)
    if unusable:
        console.print(
            f"[bold red]canopy-kit run cannot use this bag[/]: {unusable}",
            markup=True,
            highlight=False,
        )


MIN_SWEEPS = 2  # what mapping needs at the least (canopy_kit.mapping.frontend)


def why_run_cannot_use(facts: dict[str, Any]) -> str | None:
    """Why ``canopy-kit run`` (and ``map``) would refuse the bag ``facts`` describe, from
    what info sees (its LiDAR topic and its count), else None; None for a point cloud."""
    from rich.markup import escape

    from canopy_kit.io.bag import LIDAR_TYPES

    if facts.get("kind") != "bag":
        return None
    name = facts.get("lidar_topic")
    if not name:
        return f"it has no LiDAR topic ({' or '.join(LIDAR_TYPES)})"
    count = next((t["count"] for t in facts.get("topics", []) if t["name"] == name), None)
    if count is not None and count < MIN_SWEEPS:
        return (
            f"its LiDAR topic {escape(name)} has {count} message{'s' if count != 1 else ''}; "
            f"mapping needs at least {MIN_SWEEPS} sweeps"
        )
    return None


def grids(facts: dict[str, Any]) -> list[Any]:
    """The facts as tables (:class:`canopy_kit.cli.tables.Grid`): summary, bounds,
    attributes, topics."""
    from rich.markup import escape

    from canopy_kit.cli.tables import Grid

    summary = Grid(["fact", "value"], header=False, wrap={1})
    skip = {"topics", "attributes", "bounds", "header_bounds", "warnings"}
    for key, value in facts.items():
        if key in skip:
            continue
        if isinstance(value, float):
            value = f"{value:.3f}"
        elif isinstance(value, list):
            value = ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
        elif value is None:
            value = "-"
        text = str(value)
        summary.add_row(f"[bold]{key}[/]", escape(text if len(text) < 200 else text[:197] + "..."))
    out: list[Any] = [summary]
    if "bounds" in facts:
        bounds = Grid(["axis", "min", "max", "extent"], title="bounds", right={1, 2, 3})
        for i, axis in enumerate("xyz"):
            lo, hi = facts["bounds"]["min"][i], facts["bounds"]["max"][i]
            bounds.add_row(axis, f"{lo:.3f}", f"{hi:.3f}", f"{hi - lo:.3f}")
        out.append(bounds)
    if "attributes" in facts:
        attrs = Grid(["attribute", "dtype", "extra bytes"], title="attributes")
        for a in facts["attributes"]:
            attrs.add_row(escape(a["name"]), a["dtype"], "yes" if a.get("extra") else "")
        out.append(attrs)
    if "topics" in facts:
        topics = Grid(["topic", "type", "messages", "role"], title="topics", right={2})
        for t in facts["topics"]:
            topics.add_row(escape(t["name"]), t["type"], str(t["count"]), t.get("role", ""))
        out.append(topics)
    return out
