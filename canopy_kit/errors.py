"""Typed exceptions. Messages name the file, topic, field or parameter and what is wrong."""

from __future__ import annotations


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
