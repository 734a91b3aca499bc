"""Crown forms: how a form reshapes the star-shaped radius of a ``CrownEnvelope``.

Every form is a radius function ``r(u) = form.shape(u, base)`` applied to the envelope's
base radius (superellipsoid × smooth lobes) along world unit directions ``u`` seen from the
envelope's centre. The region stays ``|p - c| <= r(u)``, so ``V = 1/3 ∮ r³ dΩ`` still holds;
forms with kinks in ``r`` ask the quadrature for more nodes (``quadrature_nodes``).

- ``LobedForm``: sharp lobes along the scaffold limbs with concave hollows between them,
- ``VaseForm``: open centre, the radius seen from the trunk top small near straight up,
- ``HedgedForm``: flat pruned faces (planes) on both row sides and a flat top.

The ellipsoid (today's crowns) and the sparse young tree have no form (``form=None``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

FORM_NAMES = ("ellipsoid", "lobed", "vase", "hedged", "sparse")
CROWN_FORMS = (*FORM_NAMES, "mix")


class CrownForm(Protocol):
    """The one interface of a crown form."""

    name: str
    quadrature_nodes: tuple[int, int]  # (Gauss-Legendre nodes per hemisphere, φ nodes)

    def shape(self, u: np.ndarray, base: np.ndarray) -> np.ndarray:
        """The form's radius along unit directions ``u`` (N, 3) from the base radius (N,)."""

    def scaled(self, factor: float) -> CrownForm:
        """The form of the envelope scaled by ``factor`` about its centre."""

    def with_axis_ratios(self, across: float, up: float) -> CrownForm:
        """The form after the across-row and upper semi-axes changed by these ratios."""


class RelativeForm:
    """A form defined relative to the base radius: scaling or stretching the base keeps it."""

    def scaled(self, factor: float) -> RelativeForm:
        """Scale-free: the same form."""
        return self

    def with_axis_ratios(self, across: float, up: float) -> RelativeForm:
        """Relative to the base: the same form."""
        return self


@dataclass(frozen=True)
class LobedForm(RelativeForm):
    """``r = base · (h + (1 - h) · smoothmax_i exp(k (u·d_i - 1)))``: lobes along ``d_i``.

    ``hollow`` (h) is the radius left between lobes as a fraction of the base radius;
    ``sharpness`` (k) sets the lobes' angular width; the smooth maximum is a 6-norm, so the
    radius has no kinks and the hollows are concave creases rounded off.
    """

    directions: tuple[tuple[float, float, float], ...]
    hollow: float = 0.5
    sharpness: float = 6.0
    name: str = "lobed"
    quadrature_nodes: tuple[int, int] = (128, 384)

    def shape(self, u: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Lobed radius along ``u`` from the base radius."""
        bumps = np.exp(self.sharpness * (u @ np.asarray(self.directions).T - 1.0))
        peak = np.sum(bumps**6, axis=1) ** (1.0 / 6.0)
        return base * (self.hollow + (1.0 - self.hollow) * np.minimum(peak, 1.0))


@dataclass(frozen=True)
class VaseForm(RelativeForm):
    """``r = base · (1 - depth · t²)``, ``t = clip((u_z - opening) / (1 - opening), 0, 1)``.

    An open centre above the trunk top, which is the envelope's centre, low in the crown:
    up to the elevation ``asin(opening)`` the radius is the base's, above it the radius
    falls to ``(1 - depth)`` of the base straight up (the hollow, C¹ at its edge).
    """

    depth: float = 0.9
    opening: float = 0.65
    name: str = "vase"
    quadrature_nodes: tuple[int, int] = (128, 384)

    def shape(self, u: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Vase radius along ``u`` from the base radius."""
        t = np.clip((u[:, 2] - self.opening) / (1.0 - self.opening), 0.0, 1.0)
        return base * (1.0 - self.depth * t * t)


@dataclass(frozen=True)
class HedgedForm:
    """``r = min(base, distance along u to each pruning plane)``.

    Planes ``n · (p - c) = offset`` with world unit normals: the two row sides (horizontal
    normals ± across the row) and the top (normal up). ``r`` has kinks where a plane cuts the
    base surface, so the quadrature uses twice the nodes each way (error measured in the tests).
    """

    normals: tuple[tuple[float, float, float], ...]
    offsets: tuple[float, ...]
    name: str = "hedged"
    quadrature_nodes: tuple[int, int] = (192, 768)

    def shape(self, u: np.ndarray, base: np.ndarray) -> np.ndarray:
        """The base radius cut at the pruning planes."""
        r = base
        for n, off in zip(self.normals, self.offsets):
            cos = u @ np.asarray(n)
            dist = np.full(len(u), np.inf)
            ahead = cos > 1e-12
            dist[ahead] = off / cos[ahead]
            r = np.minimum(r, dist)
        return r

    def scaled(self, factor: float) -> HedgedForm:
        """The planes' offsets scaled with the crown."""
        return HedgedForm(self.normals, tuple(o * factor for o in self.offsets))

    def with_axis_ratios(self, across: float, up: float) -> HedgedForm:
        """Side planes follow the across semi-axis, the top plane the upper one."""
        offsets = tuple(
            o * (up if n[2] > 0.5 else across) for n, o in zip(self.normals, self.offsets)
        )
        return HedgedForm(self.normals, offsets)


def hedge_planes(
    right: np.ndarray,
    center: tuple[float, float, float],
    row_line: float,
    half_width: float,
    top: float,
) -> HedgedForm:
    """Pruning planes ``half_width`` either side of the row line and ``top`` above the centre.

    ``right`` is the horizontal unit vector across the rows, ``row_line`` the row's offset
    along it; the planes are placed relative to ``center`` (the crown may sit off the line).
    A plane never comes closer to the centre than a quarter of ``half_width`` (a crown leaning
    past its hedge line is cut there), so the crown stays star-shaped about its centre.
    """
    r = np.array([right[0], right[1], 0.0])
    off = float(np.dot(np.asarray(center[:2]), right[:2])) - row_line
    floor = 0.25 * half_width
    return HedgedForm(
        (tuple(r.tolist()), tuple((-r).tolist()), (0.0, 0.0, 1.0)),
        (max(half_width - off, floor), max(half_width + off, floor), top),
    )
