"""``canopy-kit plugins``: list registered plugins and whether each loads, or describe the
parameters of one (``--params NAME``: type, default and meaning of each)."""

from __future__ import annotations

import typer


def plugins(
    kind: str = typer.Argument(
        None, help="readers, segmenters, volumes or commands (default: all)"
    ),
    params: str = typer.Option(
        None,
        "--params",
        metavar="NAME",
        help="Print the parameters of plugin NAME: type, default, meaning",
    ),
) -> None:
    """List registered plugins (entry points) by group, with load errors if any."""
    if params is not None:
        _print_params(kind, params)
        return
    from rich.markup import escape

    from canopy_kit import plugins as registry
    from canopy_kit.cli.tables import Grid, print_grid

    table = Grid(["group", "name", "target", "package", "status"], keys=2, wrap={2, 4})
    for info in registry.describe(kind):
        status = "[green]ok[/]" if info.error is None else f"[red]{escape(str(info.error))}[/]"
        table.add_row(
            info.group.removeprefix("canopy_kit."),
            info.name,
            info.value,
            info.distribution or "",
            status,
        )
    print_grid(table)


def _print_params(kind: str | None, name: str) -> None:
    from rich.markup import escape

    from canopy_kit import plugins as registry
    from canopy_kit.cli.tables import Grid, print_grid
    from canopy_kit.errors import PluginError
    from canopy_kit.plugins.params import REQUIRED

    kinds = [kind] if kind else registry.kinds_of(name)
    if not kinds:
        raise PluginError(f"no plugin named {name!r} among the segmenters, volumes or readers")
    if len(kinds) > 1:
        raise PluginError(
            f"{name!r} names a plugin of several kinds ({', '.join(kinds)}); "
            f"give one: canopy-kit plugins KIND --params {name}"
        )
    rows = registry.parameters(kinds[0], name)
    table = Grid(
        ["parameter", "type", "default", "meaning"],
        keys=1,
        wrap={3},
        title=f"{kinds[0]} plugin {name!r}: {len(rows)} parameter(s)",
    )
    for p in rows:
        default = "required" if p.default is REQUIRED else repr(p.default)
        table.add_row(escape(p.name), escape(p.type_name), escape(default), escape(p.doc or "-"))
    print_grid(table)
    what = getattr(registry.load(kinds[0], name), "measures", "")
    if what:  # a volume estimator says what it measures
        from canopy_kit.cli.common import console

        console.print(f"measures: {escape(what)}")
