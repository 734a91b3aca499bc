"""Trellis of a fruiting wall: posts, horizontal wires and a drip irrigation line per row.

Trellised apple and pear walls and super-high-density hedgerows hang their trees on wires
strung between posts (wood or concrete, about 0.1 m thick, every 8-12 m, taller than the
wall) and water them through a drip line near the ground. None of it is canopy: in the
scene it is material ``TRELLIS`` with the per-point truth label ``TRELLIS_ID`` (-2, as every
non-tree label below 0). Wires are a few millimetres thick, so the LiDAR returns few points
from them; posts return many.

Posts stand on each row's line (the row's offset across the rows), from
``trellis_end_overhang`` before the first tree to as far after the last, every
``trellis_post_spacing`` m in between (evenly, so both end posts are anchors). Wires and
the drip line run from end post to end post at fixed heights above the ground at each post.
End posts may lean outward along the row by ``trellis_end_post_lean_deg`` (anchor posts
braced against the wires' pull, as many trellises set them): their tops stand that far
beyond their feet, and the wires meet them on their axis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canopy_kit.sim.config import OrchardSpec
from canopy_kit.sim.terrain import Terrain

TRELLIS_ID = -2  # per-point truth label of trellis returns: not a tree, not the ground


@dataclass(frozen=True)
class RowTrellis:
    """One row's trellis: post bases (P, 3) with their height and radius, and the wires and
    the drip line as polylines through the posts (each (P, 3)) with their radii."""

    row: int
    post_bases: np.ndarray
    post_height: float
    post_radius: float
    wires: tuple[np.ndarray, ...]
    wire_radius: float
    drip_line: np.ndarray | None
    drip_radius: float
    # per post, the horizontal offset (x, y) of its top from its foot (P, 2); None: upright
    post_lean: np.ndarray | None = None

    @property
    def post_tops(self) -> np.ndarray:
        """Top centre of every post (P, 3)."""
        return self.post_at(self.post_height)

    def post_at(self, height: float) -> np.ndarray:
        """The posts' axes at ``height`` above their feet (P, 3)."""
        points = self.post_bases + np.array([0.0, 0.0, height])
        if self.post_lean is not None:
            points[:, :2] += self.post_lean * (height / self.post_height)
        return points


def build_trellis(
    spec: OrchardSpec,
    row_along: dict[int, tuple[float, float]],
    row_offsets: np.ndarray,
    d: np.ndarray,
    right: np.ndarray,
    terrain: Terrain,
) -> list[RowTrellis]:
    """The trellis of every row, from the along-row span of its trees (``row_along``: first
    and last trunk per row); empty when ``spec.trellis_post_spacing`` is 0."""
    if spec.trellis_post_spacing <= 0:
        return []
    out = []
    for row, (first, last) in sorted(row_along.items()):
        a0 = first - spec.trellis_end_overhang
        a1 = last + spec.trellis_end_overhang
        n_bays = max(1, round((a1 - a0) / spec.trellis_post_spacing))
        along = np.linspace(a0, a1, n_bays + 1)
        xy = along[:, None] * d + row_offsets[row] * right
        ground = terrain.height(xy[:, 0], xy[:, 1])
        bases = np.column_stack([xy, ground])
        lean = np.zeros((len(bases), 2))
        reach = spec.trellis_post_height * np.tan(np.radians(spec.trellis_end_post_lean_deg))
        lean[0], lean[-1] = -reach * np.asarray(d[:2]), reach * np.asarray(d[:2])  # outward
        posts = RowTrellis(
            row,
            bases,
            spec.trellis_post_height,
            spec.trellis_post_radius,
            (),
            spec.trellis_wire_radius,
            None,
            spec.drip_line_radius,
            lean if reach > 0 else None,
        )
        wires = tuple(posts.post_at(h) for h in spec.trellis_wire_heights)
        drip = posts.post_at(spec.drip_line_height)
        out.append(
            replace(posts, wires=wires, drip_line=drip if spec.drip_line_height > 0 else None)
        )
    return out


def trellis_cylinders(trellis: list[RowTrellis]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The trellis as groups of cylinders ``(p0 (K, 3), p1 (K, 3), radius (K,))``: posts from
    10 cm below the ground to their tops, and every span of a wire or the drip line."""
    groups = []
    for t in trellis:
        below = t.post_at(-0.1)
        groups.append((below, t.post_tops, np.full(len(below), t.post_radius)))
        lines = [(w, t.wire_radius) for w in t.wires]
        if t.drip_line is not None:
            lines.append((t.drip_line, t.drip_radius))
        for line, radius in lines:
            groups.append((line[:-1], line[1:], np.full(len(line) - 1, radius)))
    return groups
