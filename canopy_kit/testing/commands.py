"""Conformance rules for command plugins (``canopy_kit.commands``): each a named check.

A command is a function typer turns into a click command, or a ``typer.Typer`` group. The
rules are what the CLI promises a user of every command, built-in or installed: it says
what it does, every option and argument says what it is, and ``--help`` (of the group and
of each subcommand) runs and exits 0. ``check_command(my_command)`` runs them all.
"""

from __future__ import annotations

import inspect
from collections.abc import Iterator
from typing import Any

from canopy_kit.testing.estimators import Check, _run


def _click_command(command: Any) -> Any:
    """The click command typer builds from a function or a Typer group."""
    import typer
    from typer.main import get_command

    if isinstance(command, typer.Typer):
        return get_command(command)
    app = typer.Typer(add_completion=False)
    app.command()(command)
    return get_command(app)


def _commands(click_command: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple, Any]]:
    """``(argv prefix, command)`` of the command and of every subcommand under it."""
    yield path, click_command
    for name, sub in sorted(getattr(click_command, "commands", {}).items()):
        yield from _commands(sub, (*path, name))


def check_is_a_command(command: Any) -> None:
    import typer

    assert isinstance(command, typer.Typer) or inspect.isfunction(command), (
        f"a command is a function or a typer.Typer, not {type(command).__name__}"
    )


def check_says_what_it_does(command: Any) -> None:
    for path, cmd in _commands(_click_command(command)):
        text = (cmd.help or "").strip()
        where = " ".join(path) or "the command"
        assert text, f"{where} has no help text (a docstring or Typer(help=...))"


def check_every_parameter_documented(command: Any) -> None:
    for path, cmd in _commands(_click_command(command)):
        for param in cmd.params:
            if param.name == "help":
                continue
            assert (getattr(param, "help", None) or "").strip(), (
                f"{' '.join(path) or 'the command'}: parameter {param.name!r} has no help"
            )


def check_help_runs(command: Any) -> None:
    from click.testing import CliRunner

    runner = CliRunner()
    root = _click_command(command)
    for path, _ in _commands(root):
        result = runner.invoke(root, [*path, "--help"])
        where = " ".join(path) or "the command"
        assert result.exit_code == 0, f"{where} --help exited {result.exit_code}: {result.output}"


COMMAND_RULES = (
    ("is_a_command", check_is_a_command),
    ("says_what_it_does", check_says_what_it_does),
    ("every_parameter_documented", check_every_parameter_documented),
    ("help_runs", check_help_runs),
)


def command_checks() -> list[Check]:
    """Every rule of the command contract."""
    return [Check(name, func) for name, func in COMMAND_RULES]


def check_command(command: Any) -> None:
    """Run every command rule on a command plugin; AssertionError naming each broken one."""
    _run(command, command_checks())
