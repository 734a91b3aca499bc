"""Ground surface: a plane with along-row and cross-row slope plus gentle smooth bumps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Terrain:
    """Analytic height field ``z(x, y)`` in the local frame (smooth, so the robot's pitch is too)."""

    row_direction: tuple[float, float]
    slope_along: float
    slope_across: float
    bump_amplitudes: tuple[float, ...] = ()
    bump_wavevectors: tuple[tuple[float, float], ...] = ()
    bump_phases: tuple[float, ...] = ()

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        row_direction: np.ndarray,
        slope_deg: float,
        cross_slope_deg: float,
        amplitude: float,
        wavelength: float,
        n_waves: int = 4,
    ) -> Terrain:
        """Plane plus ``n_waves`` random sinusoids of about ``wavelength`` metres."""
        amps, kvecs, phases = [], [], []
        for _ in range(n_waves):
            lam = wavelength * rng.uniform(0.6, 1.6)
            ang = rng.uniform(0, np.pi)
            kvecs.append((2 * np.pi / lam * np.cos(ang), 2 * np.pi / lam * np.sin(ang)))
            amps.append(amplitude * rng.uniform(0.4, 1.0) / np.sqrt(n_waves))
            phases.append(rng.uniform(0, 2 * np.pi))
        d = np.asarray(row_direction, float)
        return cls(
            (float(d[0]), float(d[1])),
            float(np.tan(np.radians(slope_deg))),
            float(np.tan(np.radians(cross_slope_deg))),
            tuple(amps),
            tuple(kvecs),
            tuple(phases),
        )

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height at local (x, y)."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        dx, dy = self.row_direction
        along = x * dx + y * dy
        across = x * dy - y * dx  # positive to the right of the row direction
        z = self.slope_along * along + self.slope_across * across
        for a, (kx, ky), ph in zip(self.bump_amplitudes, self.bump_wavevectors, self.bump_phases):
            z = z + a * np.sin(kx * x + ky * y + ph)
        return z
