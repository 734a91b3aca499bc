"""Star-shaped crown envelopes with an exactly computable volume.

A crown is the region ``|p - c| <= r(u)`` around a centre ``c``, where the radius in unit
direction ``u`` is a superellipsoid (separate upper and lower vertical semi-axes) times a
smooth lobe perturbation, optionally reshaped by a crown form (``canopy_kit.sim.crown_forms``:
lobed, vase, hedged). Because the region is star-shaped, its volume is the sphere
integral ``V = 1/3 ∮ r(u)³ dΩ``, evaluated by Gauss-Legendre quadrature per hemisphere to
far better than 0.1 %.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from canopy_kit.sim.crown_forms import CrownForm


@dataclass(frozen=True)
class CrownEnvelope:
    """One crown: centre, semi-axes (along, across, up, down), yaw, exponent, lobes and form."""

    center: tuple[float, float, float]
    semi_axes: tuple[float, float, float, float]
    yaw: float
    exponent: float
    lobe_directions: tuple[tuple[float, float, float], ...] = ()
    lobe_amplitudes: tuple[float, ...] = ()
    lobe_sharpness: float = 4.0
    form: CrownForm | None = None

    @property
    def form_name(self) -> str:
        """The crown form's name (``ellipsoid`` without a form)."""
        return "ellipsoid" if self.form is None else self.form.name

    def scaled(self, factor: float) -> CrownEnvelope:
        """The same shape scaled about its centre."""
        a, b, cu, cd = self.semi_axes
        return CrownEnvelope(
            self.center,
            (a * factor, b * factor, cu * factor, cd * factor),
            self.yaw,
            self.exponent,
            self.lobe_directions,
            self.lobe_amplitudes,
            self.lobe_sharpness,
            None if self.form is None else self.form.scaled(factor),
        )

    def moved(self, center: tuple[float, float, float]) -> CrownEnvelope:
        """The same shape around another centre."""
        return CrownEnvelope(
            tuple(map(float, center)),
            self.semi_axes,
            self.yaw,
            self.exponent,
            self.lobe_directions,
            self.lobe_amplitudes,
            self.lobe_sharpness,
            self.form,
        )

    def with_semi_axes(self, semi_axes: tuple[float, float, float, float]) -> CrownEnvelope:
        """The same lobes, orientation and form with other semi-axes."""
        form = self.form
        if form is not None:
            form = form.with_axis_ratios(
                semi_axes[1] / self.semi_axes[1], semi_axes[2] / self.semi_axes[2]
            )
        return CrownEnvelope(
            self.center,
            tuple(map(float, semi_axes)),
            self.yaw,
            self.exponent,
            self.lobe_directions,
            self.lobe_amplitudes,
            self.lobe_sharpness,
            form,
        )

    def radius(self, u: np.ndarray) -> np.ndarray:
        """Envelope radius along unit directions ``u`` (N, 3) given in the world frame."""
        u = np.asarray(u, dtype=np.float64)
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        lx = cy * u[:, 0] + sy * u[:, 1]
        ly = -sy * u[:, 0] + cy * u[:, 1]
        lz = u[:, 2]
        a, b, cu, cd = self.semi_axes
        c = np.where(lz >= 0, cu, cd)
        p = self.exponent
        base = (np.abs(lx / a) ** p + np.abs(ly / b) ** p + np.abs(lz / c) ** p) ** (-1.0 / p)
        r = base * self._lobe_factor(u)
        return r if self.form is None else self.form.shape(u, r)

    def _lobe_factor(self, u: np.ndarray) -> np.ndarray:
        if not self.lobe_amplitudes:
            return np.ones(len(u))
        k = self.lobe_sharpness
        dirs = np.asarray(self.lobe_directions)
        amps = np.asarray(self.lobe_amplitudes)
        mean = (1.0 - np.exp(-2.0 * k)) / (2.0 * k)  # mean of exp(k(u·d - 1)) over the sphere
        bumps = np.exp(k * (u @ dirs.T - 1.0)) - mean
        return np.maximum(1.0 + bumps @ amps, 0.3)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of points inside the envelope."""
        d = np.asarray(points, dtype=np.float64) - np.asarray(self.center)
        rho = np.linalg.norm(d, axis=1)
        inside = rho == 0
        nz = ~inside
        inside[nz] = rho[nz] <= self.radius(d[nz] / rho[nz, None])
        return inside

    def relative_depth(self, points: np.ndarray) -> np.ndarray:
        """``|p - c| / r(u)``: 0 at the centre, 1 on the envelope, >1 outside."""
        d = np.asarray(points, dtype=np.float64) - np.asarray(self.center)
        rho = np.linalg.norm(d, axis=1)
        out = np.zeros(len(d))
        nz = rho > 0
        out[nz] = rho[nz] / self.radius(d[nz] / rho[nz, None])
        return out

    @cached_property
    def volume(self) -> float:
        """Exact envelope volume (m³) by quadrature of ``r³/3`` over the sphere."""
        return volume_by_quadrature(self)

    def surface_points(self, n: int = 20000) -> np.ndarray:
        """Points on the envelope along ``n`` near-uniform (Fibonacci) directions."""
        u = fibonacci_sphere(n)
        return np.asarray(self.center) + u * self.radius(u)[:, None]

    @cached_property
    def _surface(self) -> np.ndarray:
        return self.surface_points(20000)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box of the envelope (from a dense surface sampling, padded 1 %)."""
        s = self._surface
        c = np.asarray(self.center)
        lo, hi = s.min(axis=0), s.max(axis=0)
        return c + (lo - c) * 1.01, c + (hi - c) * 1.01

    @cached_property
    def horizontal_extents(self) -> tuple[float, float]:
        """(widest horizontal extent, extent perpendicular to it), in metres."""
        from canopy_kit.volume.metrics import widest_extents

        return widest_extents(self._surface[:, :2])

    @property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest z of the envelope."""
        z = self._surface[:, 2]
        return float(z.min()), float(z.max())

    def footprint(self, n: int = 720) -> np.ndarray:
        """Horizontal outline (convex hull of the projected envelope), (M, 2) counter-clockwise."""
        from scipy.spatial import ConvexHull

        xy = self._surface[:, :2]
        return xy[ConvexHull(xy).vertices]


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` near-uniform unit vectors (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def volume_by_quadrature(
    envelope: CrownEnvelope, n_mu: int | None = None, n_phi: int | None = None
) -> float:
    """``1/3 ∮ r³ dΩ`` with Gauss-Legendre in cos θ per hemisphere and a uniform φ rule.

    Node counts default to 96 × 384, or to the crown form's ``quadrature_nodes``.
    """
    default = (96, 384) if envelope.form is None else envelope.form.quadrature_nodes
    n_mu = default[0] if n_mu is None else n_mu
    n_phi = default[1] if n_phi is None else n_phi
    x, w = np.polynomial.legendre.leggauss(n_mu)
    phi = np.linspace(0.0, 2.0 * np.pi, n_phi, endpoint=False)
    total = 0.0
    for lo, hi in ((-1.0, 0.0), (0.0, 1.0)):
        mu = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
        wmu = 0.5 * (hi - lo) * w
        mm, pp = np.meshgrid(mu, phi, indexing="ij")
        s = np.sqrt(1.0 - mm**2)
        u = np.column_stack([(s * np.cos(pp)).ravel(), (s * np.sin(pp)).ravel(), mm.ravel()])
        r3 = envelope.radius(u).reshape(mm.shape) ** 3
        total += float(np.sum(r3 * wmu[:, None]) * (2.0 * np.pi / n_phi))
    return total / 3.0
