"""Render nadir drone photos of the orchard scene by ray casting, one ray per pixel.

Textures are procedural and evaluated at the 3-D hit point in world coordinates, so a
patch of soil or a leaf cluster looks the same from every camera (feature matching
needs that). Lighting is a sun with cast shadows (a second ray towards the sun) plus a
sky term dimmed under cover (a third ray straight up), then vignetting, sensor noise
and an sRGB tone curve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.core.extras import needs_extra
from canopy_kit.sim.scene import FOLIAGE, GRASS, GROUND, TRELLIS, WOOD, Scene
from canopy_kit.sim.terrain import Terrain

_SEEDS = {
    "soil": 11,
    "grain": 12,
    "pebble": 13,
    "cover": 14,
    "weed": 15,
    "grass": 16,
    "bark": 17,
    "leaf": 18,
    "leaf_fine": 19,
}


@dataclass(frozen=True)
class PinholeView:
    """A camera for rendering: centre, world-from-camera rotation (x right, y down, z forward)."""

    position: np.ndarray
    rotation: np.ndarray
    focal_px: float
    width: int
    height: int

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) unit ray directions in the world frame through the pixel centres."""
        u = (np.arange(self.width) + 0.5 - self.width / 2.0) / self.focal_px
        v = (np.arange(self.height) + 0.5 - self.height / 2.0) / self.focal_px
        uu, vv = np.meshgrid(u, v)
        d = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d @ self.rotation.T


def _hash(seed: int, *coords: np.ndarray) -> np.ndarray:
    """Integer lattice coordinates to uniform floats in [0, 1) (a small avalanche hash)."""
    h = np.full(np.shape(coords[0]), (seed * 0x9E3779B1) & 0xFFFFFFFF, np.uint32)
    for k, c in zip((0x85EBCA6B, 0xC2B2AE35, 0x27D4EB2F), coords):
        h ^= c.view(np.uint32) * np.uint32(k)  # int32 lattice indices, reinterpreted
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return h.astype(np.float32) * np.float32(1.0 / 4294967296.0)


def _smooth(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def value_noise2(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1) with unit lattice spacing."""
    x, y = np.asarray(x, np.float32), np.asarray(y, np.float32)
    xf, yf = np.floor(x), np.floor(y)
    u, v = _smooth(x - xf), _smooth(y - yf)
    xi, yi = xf.astype(np.int32), yf.astype(np.int32)
    a, b = _hash(seed, xi, yi), _hash(seed, xi + 1, yi)
    c, d = _hash(seed, xi, yi + 1), _hash(seed, xi + 1, yi + 1)
    return (a + (b - a) * u) * (1 - v) + (c + (d - c) * u) * v


def value_noise3(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 3-D value noise in [0, 1) with unit lattice spacing; ``p`` is (N, 3)."""
    p = np.asarray(p, np.float32)
    f = np.floor(p)
    w = _smooth(p - f)
    i = f.astype(np.int32)
    out = np.zeros(len(p), np.float32)
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1 - w[:, 2]
                out += wx * wy * wz * _hash(seed, i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
    return out


def fbm2(x: np.ndarray, y: np.ndarray, scale: float, octaves: int, seed: int) -> np.ndarray:
    """Multi-octave 2-D noise in about [0, 1]; ``scale`` is the largest feature size in metres."""
    total = np.zeros(np.shape(x), np.float32)
    amp, norm, freq = 1.0, 0.0, 1.0 / scale
    for k in range(octaves):
        # Offset each octave so lattice lines do not line up.
        total += amp * value_noise2(x * freq + 17.3 * k, y * freq - 31.7 * k, seed + 101 * k)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t[:, None]


def _rgb(*c: float) -> np.ndarray:
    return np.array(c, np.float32)


def soil_albedo(p: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Dry soil with clods and pebbles, weedy cover in the alleys (``across``: m from a row line)."""
    x, y = p[:, 0], p[:, 1]
    base = fbm2(x, y, 2.5, 5, _SEEDS["soil"])
    col = _mix(_rgb(0.22, 0.17, 0.12), _rgb(0.48, 0.39, 0.29), np.clip(base * 1.8 - 0.4, 0, 1))
    grain = fbm2(x, y, 0.16, 3, _SEEDS["grain"])
    col *= (0.65 + 0.7 * grain)[:, None]
    pebble = value_noise2(x / 0.06, y / 0.06, _SEEDS["pebble"])
    col = np.where((pebble > 0.88)[:, None], col * 1.5, col)
    col = np.where((pebble < 0.06)[:, None], col * 0.6, col)
    # Cover crop and weeds: patchy, more towards the alley centre, none in the tree strip.
    alley = np.clip((np.abs(across) - 1.0) / 1.5, 0, 1)
    cover = fbm2(x, y, 5.0, 3, _SEEDS["cover"]) * alley
    clumps = fbm2(x, y, 0.3, 3, _SEEDS["weed"])
    cover = np.clip((cover + 0.45 * clumps - 0.72) * 5.0, 0, 1)
    weed = _mix(
        _rgb(0.30, 0.27, 0.13), _rgb(0.08, 0.15, 0.04), fbm2(x, y, 2.0, 2, _SEEDS["weed"] + 7)
    )
    weed *= (0.6 + 0.8 * clumps)[:, None]
    return _mix(col, weed, cover)


def grass_albedo(p: np.ndarray, shade: np.ndarray, height_above: np.ndarray) -> np.ndarray:
    """Blades between straw and green, darker towards the base."""
    t = np.clip(
        (shade - 0.7) / 0.6 + 0.3 * (value_noise2(p[:, 0], p[:, 1], _SEEDS["grass"]) - 0.5), 0, 1
    )
    col = _mix(_rgb(0.42, 0.38, 0.20), _rgb(0.14, 0.24, 0.07), t)
    return col * np.clip(0.7 + 1.5 * height_above, 0.7, 1.1)[:, None]


def bark_albedo(p: np.ndarray) -> np.ndarray:
    """Grey-brown bark with vertical streaks."""
    streak = value_noise3(p * np.array([25.0, 25.0, 2.0]), _SEEDS["bark"])
    return _rgb(0.20, 0.16, 0.12) * (0.6 + 0.7 * streak)[:, None]


def leaf_albedo(p: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """Leaf clusters: per-cluster tone from ``shade``, plus hue and fine variation in 3-D."""
    hue = value_noise3(p / 0.6, _SEEDS["leaf"])
    col = _mix(_rgb(0.055, 0.12, 0.030), _rgb(0.12, 0.17, 0.035), hue)
    fine = value_noise3(p / 0.05, _SEEDS["leaf_fine"])
    return col * (shade * (0.7 + 0.6 * fine))[:, None]


def _srgb_lut() -> np.ndarray:
    lin = np.linspace(0.0, 1.0, 4096)
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


_SRGB_LUT = _srgb_lut()


def _vignetting(width: int, height: int, strength: float) -> np.ndarray:
    """Radial fall-off: 1 at the centre, ``1 - strength`` in the corners."""
    x = (np.arange(width, dtype=np.float32) + 0.5 - width / 2) / (width / 2)
    y = (np.arange(height, dtype=np.float32) + 0.5 - height / 2) / (height / 2)
    r2 = (x[None, :] ** 2 * width**2 + y[:, None] ** 2 * height**2) / (width**2 + height**2)
    return 1.0 - strength * r2


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards the sun (azimuth clockwise from north, local x east, y north)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


class DroneRenderer:
    """Ray-casts colour images of a scene; build once, render many views."""

    def __init__(
        self,
        scene: Scene,
        terrain: Terrain,
        row_lines: tuple[np.ndarray, np.ndarray],
        sun_elevation_deg: float,
        sun_azimuth_deg: float,
    ) -> None:
        self.scene = scene
        self.terrain = terrain
        self._raycaster = scene.raycasting_scene()
        self.sun = sun_direction(sun_elevation_deg, sun_azimuth_deg)
        # Row lines as (unit across-row vector, across offsets of the rows).
        self._right, self._row_offsets = row_lines

    def _across_nearest_row(self, xy: np.ndarray) -> np.ndarray:
        c = xy @ self._right
        k = np.abs(c[:, None] - self._row_offsets[None, :]).argmin(axis=1)
        return c - self._row_offsets[k]

    def render(
        self,
        view: PinholeView,
        rng: np.random.Generator,
        exposure: float = 1.25,
        noise: float = 0.008,
        vignetting: float = 0.22,
    ) -> np.ndarray:
        """An (H, W, 3) uint8 sRGB image seen from ``view``."""
        with needs_extra("open3d"):
            import open3d as o3d

        dirs = view.ray_directions().reshape(-1, 3)
        n = len(dirs)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = view.position
        rays[:, 3:] = dirs
        hit = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        normals = hit["primitive_normals"].numpy().astype(np.float32)
        miss = ~np.isfinite(t_hit)
        if miss.any():  # beyond the meshed ground: intersect the terrain height field
            t_hit[miss] = self._terrain_hit(view.position, dirs[miss])
            normals[miss] = (0.0, 0.0, 1.0)
            prim[miss] = -1
        p = view.position + dirs * t_hit[:, None]
        flip = np.sum(normals * dirs, axis=1) > 0
        normals[flip] *= -1.0
        material = np.where(prim >= 0, self.scene.material[np.maximum(prim, 0)], GROUND)
        material = np.where(material == TRELLIS, WOOD, material)  # posts look like bark
        shade = np.where(prim >= 0, self.scene.shade[np.maximum(prim, 0)], 1.0).astype(np.float32)

        albedo = np.zeros((n, 3), np.float32)
        for mat in (GROUND, GRASS, WOOD, FOLIAGE):
            sel = np.flatnonzero(material == mat)
            if len(sel) == 0:
                continue
            q = p[sel]
            if mat == GROUND:
                albedo[sel] = soil_albedo(q, self._across_nearest_row(q[:, :2]))
            elif mat == GRASS:
                above = q[:, 2] - self.terrain.height(q[:, 0], q[:, 1])
                albedo[sel] = grass_albedo(q, shade[sel], above)
            elif mat == WOOD:
                albedo[sel] = bark_albedo(q)
            else:
                albedo[sel] = leaf_albedo(q, shade[sel])

        # Grass tufts are crossed blades: light them like the ground they cover, and start
        # their shadow and sky rays clear of their own tuft.
        grass = material == GRASS
        normals[grass] = (0.0, 0.0, 1.0)
        start = p + 0.01 * normals
        start[grass] += 0.15 * self.sun
        lit = self._visible(start, self.sun)
        start[grass] += (0.0, 0.0, 0.3)
        sky = self._visible(start, np.array([0.0, 0.0, 1.0]))
        cos_sun = np.clip(normals @ self.sun.astype(np.float32), 0.0, None)
        # Leaves pass some light through: a little sun on their far side.
        cos_sun = np.where(material == FOLIAGE, np.maximum(cos_sun, 0.3 * lit), cos_sun)
        irradiance = 1.0 * cos_sun * lit + 0.28 * np.where(sky, 1.0, 0.45)
        radiance = albedo * irradiance[:, None] * exposure

        img = radiance.reshape(view.height, view.width, 3)
        img *= _vignetting(view.width, view.height, vignetting)[..., None]
        img += noise * rng.standard_normal(img.shape, dtype=np.float32)
        # sRGB tone curve through a lookup table on 4096 linear levels.
        levels = np.round(np.clip(img, 0.0, 1.0) * 4095.0).astype(np.int32)
        return _SRGB_LUT[levels]

    def _visible(self, origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
        with needs_extra("open3d"):
            import open3d as o3d

        rays = np.empty((len(origins), 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = direction
        occluded = self._raycaster.test_occlusions(o3d.core.Tensor(rays), tnear=0.005).numpy()
        return ~occluded.astype(bool)

    def _terrain_hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance along each ray to the terrain surface (fixed-point iteration)."""
        z = np.full(len(dirs), float(self.terrain.height(origin[0], origin[1])))
        for _ in range(3):
            t = (z - origin[2]) / np.minimum(dirs[:, 2], -1e-6)
            q = origin + dirs * t[:, None]
            z = self.terrain.height(q[:, 0], q[:, 1])
        return (z - origin[2]) / np.minimum(dirs[:, 2], -1e-6)
