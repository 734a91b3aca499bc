"""Plugin registries filled from ``importlib.metadata`` entry points.

Built-in plugins are registered through the same entry points (in pyproject.toml) that a
third-party package uses, so installing a package is all it takes to add a segmenter.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from canopy_kit.errors import PluginError

GROUPS: dict[str, str] = {
    "readers": "canopy_kit.readers",
    "segmenters": "canopy_kit.segmenters",
    "volumes": "canopy_kit.volumes",
    "commands": "canopy_kit.commands",
}


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
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=_group_name(kind)):
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
