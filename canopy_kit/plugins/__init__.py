"""Plugin registries filled from ``importlib.metadata`` entry points.

Built-in plugins are registered through the same entry points (in pyproject.toml) that a
third-party package uses, so installing a package is all it takes to add a segmenter.
:func:`create` is the one factory for every registry: load, check the keyword parameters
against the class signature, instantiate, ``validate_params()``; :func:`parameters`
describes a plugin's parameters (``canopy_kit.plugins.params``). Every kind is built there:
segmenters and volume estimators from a preset's parameters, readers, world models from a
session folder, commands (functions or typer groups, taken as they are). The rules each
kind must keep are checked by ``canopy_kit.testing`` (``check_segmenter``,
``check_volume_estimator``, ``check_reader``, ``check_world``, ``check_command``).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from canopy_kit.errors import ConfigError, PluginError
from canopy_kit.plugins.params import (
    ParamInfo,
    check_types,
    init_parameters,
    parameters_of,
    takes_any_keyword,
)

GROUPS: dict[str, str] = {
    "readers": "canopy_kit.readers",
    "segmenters": "canopy_kit.segmenters",
    "volumes": "canopy_kit.volumes",
    "commands": "canopy_kit.commands",
    "worlds": "canopy_kit.worlds",  # exact world models of session generators (truth.load_world)
}


#: How an error message calls a plugin of each kind.
LABELS: dict[str, str] = {
    "readers": "reader",
    "segmenters": "segmenter",
    "volumes": "volume method",
    "commands": "command",
    "worlds": "world model",
}

__all__ = [
    "GROUPS",
    "ParamInfo",
    "PluginInfo",
    "create",
    "describe",
    "kinds_of",
    "load",
    "names",
    "parameters",
]


@dataclass(frozen=True)
class PluginInfo:
    """One registered entry point and whether it loads."""

    group: str
    name: str
    value: str
    distribution: str | None
    error: str | None = None


def _group_name(kind: str) -> str:
    if kind in GROUPS:
        return GROUPS[kind]
    if kind in GROUPS.values():
        return kind
    raise PluginError(f"unknown plugin kind {kind!r}; expected one of {sorted(GROUPS)}")


def _entry_points(kind: str) -> dict[str, EntryPoint]:
    """The entry points of a kind, read once per search path (a scan of every installed
    distribution takes about 20 ms; a run asks for them a few dozen times)."""
    return dict(_read_entry_points(_group_name(kind), entry_points, tuple(sys.path)))


@functools.lru_cache(maxsize=64)
def _read_entry_points(
    group: str, finder: Callable[..., Any], search_path: tuple[str, ...]
) -> dict[str, EntryPoint]:
    found: dict[str, EntryPoint] = {}
    for ep in finder(group=group):
        found.setdefault(ep.name, ep)
    return found


def names(kind: str) -> list[str]:
    """Names registered under a plugin kind (``readers``, ``segmenters``, ``volumes``...)."""
    return sorted(_entry_points(kind))


def load(kind: str, name: str) -> Any:
    """Load the object a plugin entry point names; clear error when missing or broken."""
    eps = _entry_points(kind)
    if name not in eps:
        known = ", ".join(sorted(eps)) or "none"
        raise PluginError(f"no {kind} plugin named {name!r} (registered: {known})")
    return load_entry_point(eps[name])


def load_entry_point(ep: EntryPoint) -> Any:
    """Load one entry point, turning import failures into a :class:`PluginError`."""
    try:
        return ep.load()
    except Exception as exc:  # any import-time failure of third-party code
        raise PluginError(
            f"plugin {ep.name!r} in group {ep.group!r} ({ep.value}) failed to load: "
            f"{type(exc).__name__}: {exc}"
        ) from exc


def describe(kind: str | None = None, *, check: bool = True) -> list[PluginInfo]:
    """List registered plugins, optionally trying to load each to report errors."""
    kinds = [kind] if kind else list(GROUPS)
    rows: list[PluginInfo] = []
    for k in kinds:
        for name, ep in sorted(_entry_points(k).items()):
            error = None
            if check:
                try:
                    load_entry_point(ep)
                except PluginError as exc:
                    error = str(exc)
            dist = ep.dist.name if ep.dist is not None else None
            rows.append(PluginInfo(_group_name(k), name, ep.value, dist, error))
    return rows


def _label(kind: str) -> str:
    short = {v: k for k, v in GROUPS.items()}.get(kind, kind)
    return LABELS.get(short, short)


def create(
    kind: str,
    name: str,
    params: dict[str, Any] | None = None,
    *,
    where: str = "",
    validate: bool = True,
) -> Any:
    """An instance of plugin ``name`` of ``kind`` configured with keyword ``params``.

    An unknown key is a ConfigError naming it and listing the accepted parameters; with
    ``validate`` the values are checked against the ``__init__`` annotations and the
    instance's ``validate_params()`` runs. ``where`` (``segment.params``) prefixes messages.
    """
    target = load(kind, name)
    params = dict(params or {})
    prefix = f"{where}: " if where else ""
    label = _label(kind)
    if not isinstance(target, type):
        if params:
            raise ConfigError(
                f"{prefix}{label} {name!r} is not a class and takes no "
                f"parameters, got {sorted(params)}"
            )
        return target
    accepted = [p.name for p in init_parameters(target)]
    unknown = sorted(set(params) - set(accepted))
    if unknown and not takes_any_keyword(target):
        raise ConfigError(
            f"{prefix}{label} {name!r} has no parameter {unknown[0]!r} "
            f"(parameters: {', '.join(accepted) or 'none'})"
        )
    if validate:
        check_types(params, target, where or name)
    instance = target(**params)
    if validate and callable(getattr(instance, "validate_params", None)):
        instance.validate_params()
    return instance


def parameters(kind: str, name: str) -> list[ParamInfo]:
    """The parameters of plugin ``name``: type, default and meaning of each."""
    target = load(kind, name)
    return parameters_of(target) if isinstance(target, type) else []


def kinds_of(name: str) -> list[str]:
    """The plugin kinds (other than commands) that have a plugin called ``name``."""
    return [k for k in GROUPS if k != "commands" and name in _entry_points(k)]
