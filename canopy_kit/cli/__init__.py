"""The ``canopy-kit`` command line: a thin typer layer over the library.

Commands are registered through the ``canopy_kit.commands`` entry-point group (built-ins
included), so a third-party package can add one. A command entry point names either a
function (a command) or a ``typer.Typer`` (a group of commands). Library errors become a
one-line message and an exit code: 2 for bad input, 3 for a processing failure, 130 for
Ctrl-C (with one line saying what was written).

Help is click's plain text (``rich_markup_mode=None``): paragraphs wrap at any width and
nothing in a help text is read as markup (``[ground_truth]`` stays as written), so help
texts are plain sentences, without RST or rich markup.
"""

from __future__ import annotations

import errno
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
    rich_markup_mode=None,
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
            target = plugins.create("commands", name)
        except CanopyKitError as exc:
            # A broken third-party command must not take the whole CLI down.
            print(f"warning: {exc}", file=sys.stderr)
            continue
        if isinstance(target, typer.Typer):
            target.rich_markup_mode = None  # the same plain help as the built-in commands
            for command in target.registered_commands:
                if command.short_help is None and command.callback is not None:
                    command.short_help = summary(command.help or command.callback.__doc__)
            short = summary(target.info.help)
            app.add_typer(target, name=name, **({"short_help": short} if short else {}))
        else:
            app.command(name=name, short_help=summary(target.__doc__))(target)


def summary(doc: object) -> str | None:
    """A help text's first paragraph as one line: the command lists show it whole (click
    would cut it at 45 characters or at the first full stop, "Abedi et al.")."""
    if not isinstance(doc, str) or not doc.strip():
        return None
    import inspect

    return " ".join(inspect.cleandoc(doc).split("\n\n")[0].split())


_register_commands()


def one_line(message: str) -> str:
    """A message as one line without terminal escapes (a library's text may carry both)."""
    return " ".join(strip_ansi(message).split())


def main() -> None:
    """Console-script entry point: run the app, turning library errors into exit codes.

    Usage errors are handled by typer itself (message and exit code 2). An
    :class:`InputWarning` from the library (a file read in part) is one ``warning:`` line.
    """
    from canopy_kit.cli import common

    warnings.showwarning = _show_warning
    common.interrupt_notes.clear()
    try:
        app()
    except CanopyKitError as exc:
        print(f"error: {one_line(str(exc))}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        print(common.interrupted_line(), file=sys.stderr)
        sys.exit(130)
    except SystemExit as exc:
        # typer turns Ctrl-C inside a command into a silent exit 130
        if exc.code == 130 and _interrupted(exc):
            print(common.interrupted_line(), file=sys.stderr)
        raise
    except OSError as exc:
        if exc.errno not in PATH_ERRORS or not exc.filename or os.environ.get("CANOPY_KIT_DEBUG"):
            _processing_failed(exc)
        # A path that is not what the command needs (a file for a folder, a folder it may
        # not write): the user's to fix, not a bug.
        print(f"error: {exc.filename}: {exc.strerror}", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:
        _processing_failed(exc)


# A path's kind or permissions: the user's to fix (the folders a command writes are checked
# before it runs; these are the paths a command could not check beforehand).
PATH_ERRORS = {errno.EEXIST, errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM, errno.EROFS}


def _interrupted(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is among the exceptions that led to ``exc``."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def _processing_failed(exc: Exception) -> None:
    # A bug or an environment failure, not bad input: one line, and the traceback only
    # on request, so a field user never gets a wall of Python.
    if os.environ.get("CANOPY_KIT_DEBUG"):
        raise exc
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
