"""One declaration of a plugin's parameters: its ``__init__`` signature and class docstring.

Types and their constraints come from the ``__init__`` annotations, defaults from the
signature and meanings from the numpydoc ``Parameters`` section of the class docstring::

    def __init__(self, eps: Positive = 0.8, algorithm: Literal["auto", "grid"] = "auto"): ...

:func:`validate_types` (what every plugin's ``validate_params`` starts from) checks each
value against its annotation and its constraints (``annotated_types`` metadata in
``Annotated``: :data:`Positive`, :data:`NonNegative`, ``Annotated[float, Ge(1)]``...), so a
range is declared once, beside the type. :func:`check_type` checks one value (a preset's)
and :func:`check_positive` remains for values that are not plugin parameters.
"""

from __future__ import annotations

import collections.abc
import functools
import inspect
import math
import numbers
import re
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal, get_args, get_origin

from annotated_types import Ge, Gt, Le, Lt, Predicate

from canopy_kit.errors import ConfigError

#: Marks a parameter without a default in :attr:`ParamInfo.default`.
#: The paper's alpha radius (m): the default of every alpha-based estimator. Here, not in
#: canopy_kit.volume, so that the command line's help can show it without loading sklearn.
PAPER_ALPHA_M = 0.9

REQUIRED = inspect.Parameter.empty

_FINITE = Predicate(math.isfinite)
#: A finite number > 0 (a distance, a factor, a count given as a number).
Positive = Annotated[float, Gt(0), _FINITE]
#: An integer > 0.
PositiveInt = Annotated[int, Gt(0)]
#: A finite number >= 0.
NonNegative = Annotated[float, Ge(0), _FINITE]
#: A finite number >= 1 (a factor that may only enlarge).
AtLeastOne = Annotated[float, Ge(1), _FINITE]

_SECTION = re.compile(r"^\s*(\w[\w ]*)\n\s*-{3,}\s*$", re.MULTILINE)


@dataclass(frozen=True)
class ParamInfo:
    """One keyword parameter of a plugin: its annotation, default and meaning."""

    name: str
    type: Any  # the resolved annotation (``Any`` when there is none)
    default: Any  # :data:`REQUIRED` when the parameter has no default
    doc: str = ""
    constraint: str = ""  # the range its annotation declares ("a positive number"), if any

    @property
    def type_name(self) -> str:
        """The annotation as written (``float | None``), with its range (``float > 0``)."""
        name = type_name(self.type)
        return f"{name}, {self.constraint}" if self.constraint else name


def type_name(tp: Any) -> str:
    """Readable name of an annotation."""
    if tp is Any:
        return "any"
    if isinstance(tp, type) and not get_args(tp):
        return tp.__name__
    return str(tp).replace("typing.", "").replace("NoneType", "None")


def init_parameters(cls: type) -> list[inspect.Parameter]:
    """The keyword parameters of ``cls.__init__`` (no ``self``, ``*args`` or ``**kwargs``)."""
    try:
        sig = inspect.signature(cls.__init__)
    except (TypeError, ValueError):
        return []
    return [
        p
        for name, p in sig.parameters.items()
        if name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]


def takes_any_keyword(cls: type) -> bool:
    """Whether ``cls.__init__`` accepts ``**kwargs``."""
    try:
        sig = inspect.signature(cls.__init__)
    except (TypeError, ValueError):
        return True
    return any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())


@functools.lru_cache(maxsize=256)
def annotations(cls: type) -> dict[str, Any]:
    """Resolved ``__init__`` annotations of ``cls`` (``Any`` for what cannot be resolved)."""
    try:
        return typing.get_type_hints(cls.__init__)
    except Exception:  # unresolvable names in a third-party annotation: no type check
        return {}


def docstring_parameters(doc: str | None) -> dict[str, str]:
    """Parameter name -> meaning, from the numpydoc ``Parameters`` section of ``doc``."""
    text = inspect.cleandoc(doc or "")
    sections = list(_SECTION.finditer(text))
    for i, match in enumerate(sections):
        if match.group(1).strip().lower() != "parameters":
            continue
        end = sections[i + 1].start() if i + 1 < len(sections) else len(text)
        return _entries(text[match.end() : end])
    return {}


def _entries(block: str) -> dict[str, str]:
    out: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in block.splitlines():
        if line.strip() and not line[:1].isspace():
            names = line.split(":", 1)[0]
            current = []
            for name in names.split(","):
                out[name.strip().lstrip("*")] = current
        elif current is not None and line.strip():
            current.append(line.strip())
    return {name: " ".join(words) for name, words in out.items()}


def parameters_of(cls: type) -> list[ParamInfo]:
    """Every keyword parameter of plugin class ``cls`` with type, default and meaning."""
    hints = annotations(cls)
    ranges = constraints(cls)
    docs = docstring_parameters(cls.__doc__)
    return [
        ParamInfo(
            p.name,
            hints.get(p.name, Any),
            p.default,
            docs.get(p.name, ""),
            _describe(ranges[p.name]) if p.name in ranges else "",
        )
        for p in init_parameters(cls)
    ]


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _expected(tp: Any) -> str:
    if get_origin(tp) is Literal:
        return f"one of {list(get_args(tp))}"
    return {float: "a number", int: "an integer", bool: "true or false", str: "a string"}.get(
        tp, type_name(tp)
    )


def constraints(cls: type) -> dict[str, list[Any]]:
    """Parameter name -> the ``annotated_types`` constraints of its ``__init__`` annotation
    (also inside ``X | None``); parameters without any are left out."""
    try:
        hints = typing.get_type_hints(cls.__init__, include_extras=True)
    except Exception:  # unresolvable names in a third-party annotation: no constraint
        return {}
    out = {}
    for name, tp in hints.items():
        members = get_args(tp) if get_origin(tp) in (typing.Union, types.UnionType) else (tp,)
        found = [m for t in members if get_origin(t) is Annotated for m in t.__metadata__]
        if found:
            out[name] = found
    return out


_BOUNDS = {Gt: (">", "gt"), Ge: (">=", "ge"), Lt: ("<", "lt"), Le: ("<=", "le")}


def _describe(found: list[Any]) -> str:
    """``[Gt(0), finite]`` -> "a positive number"; ``[Ge(1), finite]`` -> "a number >= 1"."""
    if any(isinstance(c, Gt) and c.gt == 0 for c in found):
        return "a positive number"
    bounds = [
        f"{_BOUNDS[type(c)][0]} {getattr(c, _BOUNDS[type(c)][1])}"
        for c in found
        if type(c) in _BOUNDS
    ]
    return "a number " + " and ".join(bounds) if bounds else "a finite number"


def _holds(value: Any, found: list[Any]) -> bool:
    if not _is_number(value):
        return False
    for c in found:
        if type(c) in _BOUNDS:
            op, attr = _BOUNDS[type(c)]
            bound = getattr(c, attr)
            ok = {
                ">": value > bound,
                ">=": value >= bound,
                "<": value < bound,
                "<=": value <= bound,
            }[op]
            if not ok:
                return False
        elif isinstance(c, Predicate) and not c.func(value):
            return False
    return True


def matches(value: Any, tp: Any) -> bool:
    """Whether ``value`` fits annotation ``tp`` (ints pass as floats; unknown types pass)."""
    origin = get_origin(tp)
    if tp is Any or isinstance(tp, str | typing.TypeVar):
        return True
    if tp is type(None) or tp is None:
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(matches(value, arg) for arg in get_args(tp))
    if origin is Literal:
        return value in get_args(tp)
    if tp is float:
        return _is_number(value)
    if tp is int:
        return _is_int(value)
    if tp is bool:
        return isinstance(value, bool) or type(value).__name__ == "bool_"
    if tp is str:
        return isinstance(value, str)
    if origin in (tuple, list, collections.abc.Sequence) or tp in (tuple, list):
        if isinstance(value, str | bytes) or not hasattr(value, "__len__"):
            return False
        items = list(value)
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(items) == len(args) and all(matches(v, a) for v, a in zip(items, args))
        return not args or all(matches(v, args[0]) for v in items)
    if origin is dict:
        return isinstance(value, dict)
    if isinstance(tp, type):
        return isinstance(value, tp)
    return True


def check_type(value: Any, tp: Any, where: str) -> None:
    """ConfigError naming ``where`` unless ``value`` fits annotation ``tp``."""
    if not matches(value, tp):
        raise ConfigError(f"{where}: expected {_expected(tp)}, got {value!r}")


def check_types(params: dict[str, Any], cls: type, where: str) -> None:
    """Check keyword ``params`` against the ``__init__`` annotations of ``cls``."""
    hints = annotations(cls)
    for key, value in params.items():
        if key in hints:
            check_type(value, hints[key], f"{where}.{key}" if where else key)


def check_positive(
    value: Any, name: str, owner: str | None = None, *, allow_none: bool = False
) -> None:
    """ConfigError naming ``owner: name`` unless ``value`` is a positive finite number."""
    if value is None and allow_none:
        return
    if not _is_number(value) or not math.isfinite(float(value)) or value <= 0:
        prefix = f"{owner}: " if owner else ""
        raise ConfigError(f"{prefix}{name} must be a positive number, got {value!r}")


def check_choice(value: Any, name: str, owner: str | None, choices: tuple[Any, ...]) -> None:
    """ConfigError naming ``owner: name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        prefix = f"{owner}: " if owner else ""
        raise ConfigError(f"{prefix}{name} must be one of {list(choices)}, got {value!r}")


def validate_types(obj: Any, owner: str | None = None) -> None:
    """ConfigError naming the first parameter of ``obj`` whose value misfits its annotation
    or breaks the annotation's constraints (None passes where the annotation allows it)."""
    cls = type(obj)
    hints = annotations(cls)
    ranges = constraints(cls)
    prefix = f"{owner}: " if owner else ""
    for p in init_parameters(cls):
        if not hasattr(obj, p.name):
            continue
        value = getattr(obj, p.name)
        found = ranges.get(p.name)
        if found and not (value is None and matches(None, hints.get(p.name, Any))):
            if not _holds(value, found):
                raise ConfigError(f"{prefix}{p.name} must be {_describe(found)}, got {value!r}")
        if p.name in hints and not matches(value, hints[p.name]):
            raise ConfigError(f"{prefix}{p.name} must be {_expected(hints[p.name])}, got {value!r}")
