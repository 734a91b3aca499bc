"""``canopy-kit plugins``: list registered plugins and whether each loads."""

from __future__ import annotations

import typer


def plugins(
    kind: str = typer.Argument(None, help="readers, segmenters, volumes or commands (default: all)"),
) -> None:
    """List registered plugins (entry points) by group, with load errors if any."""
    from rich.markup import escape

    from canopy_kit import plugins as registry
    from canopy_kit.cli.tables import Grid, print_grid

    table = Grid(["group", "name", "target", "package", "status"], keys=2, wrap={2, 4})
    for info in registry.describe(kind):
        status = "[green]ok[/]" if info.error is None else f"[red]{escape(str(info.error))}[/]"
        table.add_row(info.group.removeprefix("canopy_kit."), info.name, info.value, info.distribution or "", status)
    print_grid(table)
