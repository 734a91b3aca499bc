"""Typed exceptions. Messages name the file, topic, field or parameter and what is wrong."""

from __future__ import annotations

import re


class CanopyKitError(Exception):
    """Base class of every error canopy-kit raises on purpose."""

    exit_code = 3


class InputError(CanopyKitError, ValueError):
    """An input file, topic, field or argument is missing, malformed or unusable."""

    exit_code = 2


class MessageError(InputError):
    """One message of a topic is malformed; a reader may skip it and count it instead."""


class ConfigError(InputError):
    """A preset or config value is unknown, of the wrong type or out of range."""


class PluginError(CanopyKitError):
    """A plugin is not registered or its entry point cannot be loaded."""

    exit_code = 2


class ProcessingError(CanopyKitError, RuntimeError):
    """Valid input that a processing stage could not turn into a result."""

    exit_code = 3


class InputWarning(UserWarning):
    """An input was usable but not whole (e.g. a file cut short): the result is partial.

    Readers issue it with :func:`warnings.warn`; the CLI prints it as one ``warning:`` line
    and ``canopy-kit info`` lists it under ``warnings``.
    """


_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]")  # terminal control sequences (CSI)
# Open3D's C++ errors: "[Open3D Error] (void open3d::f(int)) /path/to/file.cpp:123: text"
_OPEN3D_TAG = re.compile(r"\[Open3D [A-Za-z]+\]\s*(?:\(.*\)\s+)?(?:\S+\.(?:cpp|cc|h|hpp):\d+:\s*)?")
_SOURCE_PATH = re.compile(r"\S+\.(?:cpp|cc|h|hpp):\d+:\s*")


def strip_ansi(text: str) -> str:
    """``text`` without terminal colour and cursor escapes."""
    return _ANSI.sub("", text)


def foreign_message(text: str) -> str:
    """Another library's message as one plain line for ours: no ANSI colours, no Open3D
    ``[Open3D Error] (function) file.cpp:123:`` prefix, lines joined by ``; ``."""
    text = _SOURCE_PATH.sub("", _OPEN3D_TAG.sub("", strip_ansi(str(text))))
    return "; ".join(part.strip() for part in text.splitlines() if part.strip())


class MissingExtraError(CanopyKitError, ImportError):
    """A stage needs a package of an optional extra (``pip install 'canopy-kit[extra]'``)."""
