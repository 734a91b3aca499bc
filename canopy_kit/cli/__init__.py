"""The ``canopy-kit`` command line: a thin typer layer over the library.

Commands are registered through the ``canopy_kit.commands`` entry-point group (built-ins
included), so a third-party package can add one. A command entry point names either a
function (a command) or a ``typer.Typer`` (a group of commands). Library errors become a
one-line message and an exit code: 2 for bad input, 3 for a processing failure.
"""

from __future__ import annotations

import os
import sys
import warnings

import typer

from canopy_kit.errors import CanopyKitError, InputWarning, strip_ansi

app = typer.Typer(
    name="canopy-kit",
    help="Per-tree canopy volumes from mobile LiDAR orchard drives, checked against drone photos.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _show_version(value: bool) -> None:
    if value:
        from canopy_kit import __version__

        print(f"canopy-kit {__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: bool = typer.Option(
        False, "--version", callback=_show_version, is_eager=True, help="Print the version and exit"
    ),
) -> None:
    """Per-tree canopy volumes from mobile LiDAR orchard drives, checked against drone photos."""


def _register_commands() -> None:
    from canopy_kit import plugins

    for name in plugins.names("commands"):
        try:
            target = plugins.load("commands", name)
        except CanopyKitError as exc:
            # A broken third-party command must not take the whole CLI down.
            print(f"warning: {exc}", file=sys.stderr)
            continue
        if isinstance(target, typer.Typer):
            app.add_typer(target, name=name)
        else:
            app.command(name=name)(target)


_register_commands()


def one_line(message: str) -> str:
    """A message as one line without terminal escapes (a library's text may carry both)."""
    return " ".join(strip_ansi(message).split())


def main() -> None:
    """Console-script entry point: run the app, turning library errors into exit codes.

    Usage errors are handled by typer itself (message and exit code 2). An
    :class:`InputWarning` from the library (a file read in part) is one ``warning:`` line.
    """
    warnings.showwarning = _show_warning
    try:
        app()
    except CanopyKitError as exc:
        print(f"error: {one_line(str(exc))}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except Exception as exc:
        # A bug or an environment failure, not bad input: one line, and the traceback only
        # on request, so a field user never gets a wall of Python.
        if os.environ.get("CANOPY_KIT_DEBUG"):
            raise
        where = type(exc).__name__
        print(
            f"error: processing failed ({where}: {one_line(str(exc))}); set "
            "CANOPY_KIT_DEBUG=1 for the traceback and please report it",
            file=sys.stderr,
        )
        sys.exit(3)


_python_showwarning = warnings.showwarning


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, InputWarning):
        print(f"warning: {one_line(str(message))}", file=sys.stderr)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)
