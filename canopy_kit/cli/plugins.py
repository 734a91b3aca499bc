"""``canopy-kit plugins``: list registered plugins and whether each loads."""

from __future__ import annotations

import typer


def plugins(
    kind: str = typer.Argument(None, help="readers, segmenters, volumes or commands (default: all)"),
) -> None:
    """List registered plugins (entry points) by group, with load errors if any."""
    from rich.table import Table

    from canopy_kit import plugins as registry
    from canopy_kit.cli.common import console

    table = Table("group", "name", "target", "package", "status")
    for info in registry.describe(kind):
        status = "[green]ok" if info.error is None else f"[red]{info.error}"
        table.add_row(info.group, info.name, info.value, info.distribution or "", status)
    console.print(table)
