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
    for renderable in _renderables(facts):
        console.print(renderable)
    for w in facts.get("warnings", []):
        console.print(f"[yellow]warning[/]: {w}", markup=True, highlight=False)


def _renderables(facts: dict[str, Any]) -> list[Any]:
    from rich.table import Table

    summary = Table(show_header=False, box=None, pad_edge=False)
    summary.add_column(style="bold")
    summary.add_column()
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
        summary.add_row(key, text if len(text) < 200 else text[:197] + "...")
    out: list[Any] = [summary]
    if "bounds" in facts:
        bounds = Table("axis", "min", "max", "extent", title="bounds")
        for i, axis in enumerate("xyz"):
            lo, hi = facts["bounds"]["min"][i], facts["bounds"]["max"][i]
            bounds.add_row(axis, f"{lo:.3f}", f"{hi:.3f}", f"{hi - lo:.3f}")
        out.append(bounds)
    if "attributes" in facts:
        attrs = Table("attribute", "dtype", "extra bytes", title="attributes")
        for a in facts["attributes"]:
            attrs.add_row(a["name"], a["dtype"], "yes" if a.get("extra") else "")
        out.append(attrs)
    if "topics" in facts:
        topics = Table("topic", "type", "messages", "role", title="topics")
        for t in facts["topics"]:
            topics.add_row(t["name"], t["type"], str(t["count"]), t.get("role", ""))
        out.append(topics)
    return out
