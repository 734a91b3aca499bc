"""Crown delineation on the orthomosaic and canopy height model, and per-crown measures.

Canopy = green (excess-green index above its Otsu threshold) and raised (CHM above
``min_height``): colour alone keeps weeds and merges touching crowns, height alone
keeps trunks and fattens crowns at the edges. Individual crowns come from a
marker-controlled watershed on the smoothed CHM, seeded by its local maxima or by
given tree positions (e.g. the LiDAR stage's trees).

Diameters: ``diameter_max_m`` is the widest extent (maximum Feret diameter) and
``diameter_perp_m`` the extent perpendicular to it. The paper-style sphere
(``sphere_volume_m3 = π d³/6``) uses the widest extent, as the simulator's truth does;
``sphere_volume_mean_m3`` uses the mean of the two perpendicular extents.
``diameter_along_row_m`` and ``diameter_across_row_m`` are the extents along and across the
row direction, which comes from the crowns themselves (``ground_truth.rows``).
``envelope_volume_m3`` is the 2.5-D envelope of ``ground_truth.envelope``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from canopy_kit.config import CROWN_SEEDINGS
from canopy_kit.errors import ProcessingError
from ground_truth.envelope import envelope_volume
from ground_truth.raster import Grid
from ground_truth.row_seeds import RowLayout, row_seeds
from ground_truth.rows import (
    RowDirection,
    directional_extents,
    estimate_row_direction,
    principal_axis,
)

CROWN_COLUMNS = [
    "crown_id",
    "x",
    "y",
    "area_m2",
    "diameter_max_m",
    "diameter_perp_m",
    "diameter_mean_m",
    "diameter_along_row_m",
    "diameter_across_row_m",
    "diameter_equivalent_m",
    "height_m",
    "edge_height_m",
    "outline_height_m",
    "sphere_volume_m3",
    "sphere_volume_mean_m3",
    "ellipsoid_volume_m3",
    "chm_volume_m3",
    "envelope_volume_m3",
    "seed_id",
    "touches_border",
    "shared_outline_fraction",
]


@dataclass
class CrownOptions:
    """Crown delineation settings (metres)."""

    min_height: float = 0.8
    min_area_m2: float = 1.0
    min_tree_spacing_m: float = 2.5
    chm_smoothing_m: float = 0.35
    hole_closing_m: float = 0.3
    median_m: float = 0.5
    relative_height: float = 0.5
    top_window_m: float = 3.0
    raised_reach_m: float = 0.3
    gap_closing_m: float = 0.1
    speck_opening_m: float = 0.25
    seed_snap_m: float = 1.0
    seed_disc_fraction: float = (
        0.3  # seeded: marker discs of this share of the nearest-seed distance
    )
    seed_disc_max_m: float = 1.5
    use_color: bool = True
    # Without seed trees: "rows" (one seed per tree along rows found in the canopy,
    # ``ground_truth.row_seeds``) or "chm_maxima" (local maxima of the smoothed CHM).
    unseeded: str = "rows"
    # planting distance along the row; unset: the crowns' width across the row
    tree_spacing_m: float | None = None
    # the rows' bearing from north (degrees); unset: found in the canopy
    row_bearing_deg: float | None = None


SEEDING_DESCRIPTIONS = {
    "tree_positions": "seeded by the given tree positions (the LiDAR's trees: not independent "
    "of the LiDAR in where crowns are, only in their sizes)",
    "rows": "from the imagery alone: rows found in the canopy, one tree per stretch of row "
    "between the dips of the hedge (independent of the LiDAR)",
    "chm_maxima": "from the imagery alone: one crown per local maximum of the canopy height "
    "model (independent of the LiDAR)",
}


def describe_seeding(seg: CrownSegmentation) -> str:
    """One sentence on how the crowns were seeded, for reports."""
    text = f"Crowns {SEEDING_DESCRIPTIONS.get(seg.seeding, seg.seeding)}"
    if seg.row_layout is not None:
        lay = seg.row_layout
        spacing = "given" if lay.spacing_source == "given" else "the crowns' width across the row"
        text += (
            f"; {len(lay.rows)} rows at a bearing of {lay.bearing_deg:.1f}°, trees "
            f"{lay.spacing_m:.2f} m apart ({spacing})"
        )
    return text + "."


@dataclass
class CrownSegmentation:
    """Crown labels on the orthomosaic grid (0 = not canopy) and the masks behind them."""

    grid: Grid
    labels: np.ndarray
    canopy: np.ndarray
    vegetation: np.ndarray
    exg_threshold: float
    markers: np.ndarray  # (M, 2) marker positions x, y
    marker_seed_ids: np.ndarray  # (M,) seed index per marker, -1 for seeds from the imagery
    seeding: str = "tree_positions"  # "tree_positions", "rows" or "chm_maxima"
    row_layout: RowLayout | None = None  # the rows the seeds were placed along ("rows")


def excess_green(rgb: np.ndarray) -> np.ndarray:
    """Excess-green index 2g − r − b on chromatic coordinates (robust to illumination)."""
    c = rgb.astype(np.float32)
    total = c.sum(axis=-1) + 1e-6
    r, g, b = (c[..., i] / total for i in range(3))
    return 2 * g - r - b


def vegetation_mask(rgb: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, float]:
    """Green pixels by Otsu's threshold on excess green (over the valid cells)."""
    from skimage.filters import threshold_otsu

    exg = excess_green(rgb)
    values = exg[valid]
    if values.size < 100:
        raise ProcessingError("orthomosaic has too few valid cells to find vegetation")
    threshold = float(threshold_otsu(values))
    return (exg > threshold) & valid, threshold


def vegetation_images(rgbs: list[np.ndarray], sigma: float = 0.0) -> list[np.ndarray]:
    """Per photo, 1 where green (excess green above one Otsu threshold for all photos), else 0."""
    from scipy.ndimage import gaussian_filter
    from skimage.filters import threshold_otsu

    exg = [excess_green(rgb) for rgb in rgbs]
    step = max(int(np.sqrt(sum(e.size for e in exg) / 2e6)), 1)
    threshold = float(threshold_otsu(np.concatenate([e[::step, ::step].ravel() for e in exg])))
    out = []
    for e in exg:
        green = (e > threshold).astype(np.float32)
        out.append(gaussian_filter(green, sigma) if sigma > 0 else green)
    return out


def _disk(radius_cells: float) -> np.ndarray:
    r = max(int(np.ceil(radius_cells)), 1)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx**2 + yy**2) <= radius_cells**2 + 1e-9


def _remove_small(mask: np.ndarray, min_cells: int) -> np.ndarray:
    from scipy.ndimage import label

    patches, _ = label(mask)
    sizes = np.bincount(patches.ravel())
    keep = sizes > min_cells
    keep[0] = False
    return keep[patches]


def raised_mask(chm: np.ndarray, resolution: float, options: CrownOptions) -> np.ndarray:
    """Cells in or near the body of a crown: median CHM above ``min_height`` and above
    ``relative_height`` of the highest CHM within ``top_window_m``, widened by ``raised_reach_m``.

    The relative test drops the low skirt that window matching spreads from a crown over
    its dark shadow (measured: about 1.5 m high beside 4 m crowns), which would otherwise
    glue shadowed weeds to the crown.
    """
    from scipy.ndimage import (
        binary_closing,
        binary_dilation,
        binary_fill_holes,
        maximum_filter,
        median_filter,
    )

    # Work on cells of about 0.1 m: the CHM is no finer than that, and filters stay cheap.
    step = max(int(round(0.1 / resolution)), 1)
    full_shape = np.shape(chm)
    chm = np.asarray(chm)[::step, ::step]
    res = resolution * step
    size = max(int(round(options.median_m / res)) | 1, 3)
    smooth = median_filter(np.nan_to_num(chm, nan=0.0), size=size)
    local_top = maximum_filter(smooth, size=max(int(round(options.top_window_m / res)), 1))
    solid = (smooth > options.min_height) & (smooth > options.relative_height * local_top)
    solid = binary_fill_holes(binary_closing(solid, structure=_disk(options.hole_closing_m / res)))
    solid = _remove_small(solid, int(options.min_area_m2 / 2 / res**2))
    raised = binary_dilation(solid, structure=_disk(options.raised_reach_m / res))
    rows = np.minimum(np.arange(full_shape[0]) // step, raised.shape[0] - 1)
    cols = np.minimum(np.arange(full_shape[1]) // step, raised.shape[1] - 1)
    return raised[np.ix_(rows, cols)]


def canopy_mask(
    rgb: np.ndarray, valid: np.ndarray, chm: np.ndarray, grid: Grid, options: CrownOptions
) -> tuple[np.ndarray, np.ndarray, float]:
    """(canopy, vegetation, excess-green threshold) on the orthomosaic grid.

    Porous crowns give a CHM full of holes (the surface found is often deep inside or
    below the crown), so "raised" is decided on the median-filtered CHM and widened by
    ``raised_reach_m``; the colour mask draws the outline.
    """
    from scipy.ndimage import binary_closing, binary_fill_holes, binary_opening

    res = grid.resolution
    raised = raised_mask(chm, res, options)
    if options.use_color:
        vegetation, threshold = vegetation_mask(rgb, valid)
        vegetation = binary_closing(vegetation, structure=_disk(options.gap_closing_m / res))
    else:
        vegetation, threshold = raised & valid, float("nan")
    canopy = raised & vegetation
    canopy = binary_opening(canopy, structure=_disk(options.speck_opening_m / res))
    canopy = binary_fill_holes(canopy)
    canopy = _remove_small(canopy, max(int(options.min_area_m2 / res**2), 1))
    return canopy, vegetation, threshold


def _markers_from_seeds(
    seeds_xy: np.ndarray, canopy: np.ndarray, grid: Grid, snap_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Marker cells for given positions, snapped into the canopy within ``snap_m``."""
    from scipy.ndimage import distance_transform_edt

    _, (ir, ic) = distance_transform_edt(~canopy, return_indices=True)
    r, c = grid.index(seeds_xy[:, 0], seeds_xy[:, 1])
    r, c = np.round(r).astype(int), np.round(c).astype(int)
    inside = (r >= 0) & (r < grid.rows) & (c >= 0) & (c < grid.cols)
    cells, ids = [], []
    for k in np.flatnonzero(inside):
        rr, cc = ir[r[k], c[k]], ic[r[k], c[k]]
        if np.hypot(rr - r[k], cc - c[k]) * grid.resolution <= snap_m:
            cells.append((rr, cc))
            ids.append(k)
    return np.array(cells, int).reshape(-1, 2), np.array(ids, int)


def _markers_from_maxima(
    chm_smooth: np.ndarray, canopy: np.ndarray, grid: Grid, options: CrownOptions
) -> np.ndarray:
    """Local CHM maxima at least ``min_tree_spacing_m`` apart; one per canopy patch at least."""
    from scipy.ndimage import label, maximum_position
    from skimage.feature import peak_local_max

    patches, n = label(canopy)
    spacing = max(int(round(options.min_tree_spacing_m / grid.resolution)), 1)
    peaks = peak_local_max(
        np.where(canopy, chm_smooth, 0.0),
        min_distance=spacing,
        threshold_abs=options.min_height,
        labels=patches,
        exclude_border=False,
    )
    have = set(patches[tuple(peaks.T)].tolist()) if len(peaks) else set()
    missing = [k for k in range(1, n + 1) if k not in have]
    if missing:
        extra = np.array(maximum_position(chm_smooth, patches, missing), int).reshape(-1, 2)
        peaks = np.vstack([peaks.reshape(-1, 2), extra])
    return peaks.reshape(-1, 2)


def _seed_discs(
    markers: np.ndarray, cells: np.ndarray, canopy: np.ndarray, grid: Grid, options: CrownOptions
) -> np.ndarray:
    """Grow each seed marker into a disc (in the canopy) of ``seed_disc_fraction`` of the
    distance to its nearest other seed, at most ``seed_disc_max_m``.

    A single-cell marker that is not on its crown's CHM top (a trunk position under a leaning
    crown, a crown without a clear top) loses the watershed race to a higher neighbour,
    whose flood takes everything above the seed's own height: measured on a simulated
    almond flight, 2 of 11 seeded crowns came out as slivers under 0.4 m. A disc makes each
    given tree own its immediate surroundings; the CHM still decides the boundary beyond.
    """
    from scipy.spatial import cKDTree

    pos = cells.astype(float)
    dist, _ = cKDTree(pos).query(pos, k=2)
    radius = np.minimum(
        options.seed_disc_fraction * dist[:, 1], options.seed_disc_max_m / grid.resolution
    )
    out = markers.copy()
    for k, ((r, c), rad) in enumerate(zip(cells, radius)):
        if markers[r, c] != k + 1 or rad < 1:
            continue
        ri = int(np.ceil(rad))
        r0, r1, c0, c1 = (
            max(r - ri, 0),
            min(r + ri + 1, grid.rows),
            max(c - ri, 0),
            min(c + ri + 1, grid.cols),
        )
        yy, xx = np.mgrid[r0:r1, c0:c1]
        disc = (
            ((yy - r) ** 2 + (xx - c) ** 2 <= rad**2)
            & canopy[r0:r1, c0:c1]
            & (out[r0:r1, c0:c1] == 0)
        )
        out[r0:r1, c0:c1][disc] = k + 1
    return out


def _watershed(
    cells: np.ndarray,
    chm_smooth: np.ndarray,
    canopy: np.ndarray,
    grid: Grid,
    options: CrownOptions,
    discs: bool,
) -> np.ndarray:
    """Marker-controlled watershed on the smoothed CHM from marker cells (label k + 1 for
    cell k), each grown into a seed disc first when ``discs``."""
    from skimage.segmentation import watershed

    if not len(cells):
        return np.zeros(grid.shape, np.int32)
    markers = np.zeros(grid.shape, np.int32)
    for k, (r, c) in enumerate(cells):
        if markers[r, c] == 0:
            markers[r, c] = k + 1
    if discs and len(cells) > 1 and options.seed_disc_fraction > 0:
        markers = _seed_discs(markers, cells, canopy, grid, options)
    return watershed(-chm_smooth, markers, mask=canopy)


def delineate_crowns(
    rgb: np.ndarray,
    valid: np.ndarray,
    chm: np.ndarray,
    grid: Grid,
    seeds_xy: np.ndarray | None = None,
    options: CrownOptions | None = None,
) -> CrownSegmentation:
    """Individual crowns on the orthomosaic grid; ``chm`` must be on the same grid.

    Seeded by ``seeds_xy`` (tree positions, e.g. the LiDAR's) when given; else by the rows
    (``ground_truth.row_seeds``: each crown the canopy of its tree's stretch of row) or by the
    CHM maxima, as ``options.unseeded`` says.
    """
    from scipy.ndimage import gaussian_filter

    opts = options or CrownOptions()
    if opts.unseeded not in CROWN_SEEDINGS:
        raise ValueError(f"unseeded: expected one of {CROWN_SEEDINGS}, got {opts.unseeded!r}")
    canopy, vegetation, threshold = canopy_mask(rgb, valid, chm, grid, opts)
    chm_smooth = gaussian_filter(
        np.nan_to_num(chm, nan=0.0), opts.chm_smoothing_m / grid.resolution
    )
    x, y = grid.centers()
    layout = None
    if seeds_xy is not None and len(seeds_xy):
        seeding = "tree_positions"
        cells, seed_ids = _markers_from_seeds(
            np.asarray(seeds_xy, float), canopy, grid, opts.seed_snap_m
        )
        labels = _watershed(cells, chm_smooth, canopy, grid, opts, discs=True)
    else:
        if opts.unseeded == "rows":
            layout = row_seeds(
                canopy, chm_smooth, grid, opts.tree_spacing_m, bearing_deg=opts.row_bearing_deg
            )
        if layout is not None:
            seeding = "rows"
            labels = np.where(canopy, layout.tree_of(x, y) + 1, 0)
            seed_ids = np.full(len(layout.seeds_xy), -1)
        else:
            seeding = "chm_maxima"
            cells = _markers_from_maxima(chm_smooth, canopy, grid, opts)
            seed_ids = np.full(len(cells), -1)
            labels = _watershed(cells, chm_smooth, canopy, grid, opts, discs=False)
    if layout is not None:
        pos = layout.seeds_xy
    elif len(cells):
        pos = np.column_stack([x[tuple(cells.T)], y[tuple(cells.T)]])
    else:
        pos = np.zeros((0, 2))
    return CrownSegmentation(
        grid,
        labels.astype(np.int32),
        canopy,
        vegetation,
        threshold,
        pos,
        np.asarray(seed_ids, int),
        seeding,
        layout,
    )


def feret_extents(
    rows: np.ndarray, cols: np.ndarray, resolution: float
) -> tuple[float, float, float]:
    """(widest extent, extent perpendicular to it, widest axis angle) of a pixel region, metres.

    Extents of pixel centres plus one cell: unbiased for regions much larger than a cell.
    """
    from canopy_kit.volume.metrics import widest_axis

    pts = np.column_stack([cols, -rows]).astype(float) * resolution
    if len(pts) < 3:
        return resolution, resolution, 0.0
    widest, across, axis = widest_axis(pts)
    return widest + resolution, across + resolution, float(np.arctan2(axis[1], axis[0]))


def shared_outline_fraction(region: np.ndarray, others: np.ndarray) -> float:
    """Share of a crown's outline cells that touch another crown (0: free-standing).

    Where crowns overlap, the aerial view cuts each at the boundary, so its extents measure
    only the visible part. Tried and dropped: a circle fitted through the free outline
    (round-crown assumption) came out 0.3-1.2 m short on simulated almond crowns.
    """
    from scipy.ndimage import binary_dilation, binary_erosion

    outline = region & ~binary_erosion(region, border_value=0)
    n = int(outline.sum())
    if n == 0:
        return 0.0
    return float((outline & binary_dilation(others, structure=np.ones((3, 3), bool))).sum() / n)


def _closed_chm(chm: np.ndarray, resolution: float, radius_m: float = 0.3) -> np.ndarray:
    """Grey closing of the CHM (on cells of about 0.1 m), back on the input grid."""
    from scipy.ndimage import grey_closing

    step = max(int(round(0.1 / resolution)), 1)
    coarse = np.nan_to_num(np.asarray(chm)[::step, ::step], nan=0.0)
    closed = grey_closing(coarse, footprint=_disk(radius_m / (resolution * step)))
    rows = np.minimum(np.arange(chm.shape[0]) // step, closed.shape[0] - 1)
    cols = np.minimum(np.arange(chm.shape[1]) // step, closed.shape[1] - 1)
    return closed[np.ix_(rows, cols)]


def measure_crowns(
    seg: CrownSegmentation, chm: np.ndarray, row_direction: RowDirection | None = None
) -> pd.DataFrame:
    """One row per crown: centre, area, diameters, heights and volume models.

    ``row_direction`` (default: the rows the crowns were seeded along, else estimated from the
    crowns, ``rows.estimate_row_direction``) sets the along- and across-row extents; the
    one used is ``table.attrs["row_direction"]``.
    """
    from scipy.ndimage import binary_erosion, find_objects

    grid, labels = seg.grid, seg.labels
    res = grid.resolution
    x, y = grid.centers()
    surface = _closed_chm(chm, res)  # the crown's top surface without the gaps between leaves
    rows, cells = [], []
    for k, sl in enumerate(find_objects(labels)):
        if sl is None:
            continue
        lab = k + 1
        region = labels[sl] == lab
        rr, cc = np.nonzero(region)
        rr_abs, cc_abs = rr + sl[0].start, cc + sl[1].start
        area = region.sum() * res**2
        d_max, d_perp, _ = feret_extents(rr_abs, cc_abs, res)
        h = np.nan_to_num(chm[sl][region], nan=0.0)
        top = float(np.percentile(h, 95)) if h.size else 0.0
        ring = region & ~binary_erosion(
            region, structure=_disk(max(0.3 / res, 1.0)), border_value=0
        )
        edge = float(np.median(np.nan_to_num(chm[sl][ring], nan=0.0))) if ring.any() else 0.0
        edge = min(max(edge, 0.0), top)
        depth = 2.0 * (top - edge)
        # The envelope's widest level: the CHM right at the outline (cells within 0.15 m).
        rim = region & ~binary_erosion(
            region, structure=_disk(max(0.15 / res, 1.0)), border_value=0
        )
        outline = float(np.median(np.nan_to_num(chm[sl][rim], nan=0.0))) if rim.any() else 0.0
        outline = min(max(outline, 0.0), top)
        d_mean = 0.5 * (d_max + d_perp)
        seed = int(seg.marker_seed_ids[lab - 1]) if lab - 1 < len(seg.marker_seed_ids) else -1
        touches = bool(
            sl[0].start == 0
            or sl[1].start == 0
            or sl[0].stop == grid.rows
            or sl[1].stop == grid.cols
        )
        wide = tuple(slice(max(a.start - 1, 0), a.stop + 1) for a in sl)
        around = labels[wide]
        shared = shared_outline_fraction(around == lab, (around > 0) & (around != lab))
        cx, cy = x[rr_abs, cc_abs], y[rr_abs, cc_abs]
        cells.append((rr_abs, cc_abs, *principal_axis(rr_abs, cc_abs)))
        rows.append(
            {
                "crown_id": lab,
                "x": float(cx.mean()),
                "y": float(cy.mean()),
                "area_m2": float(area),
                "diameter_max_m": d_max,
                "diameter_perp_m": d_perp,
                "diameter_mean_m": d_mean,
                "diameter_equivalent_m": float(2 * np.sqrt(area / np.pi)),
                "height_m": top,
                "edge_height_m": edge,
                "outline_height_m": outline,
                "sphere_volume_m3": np.pi * d_max**3 / 6.0,
                "sphere_volume_mean_m3": np.pi * d_mean**3 / 6.0,
                "ellipsoid_volume_m3": np.pi / 6.0 * d_max * d_perp * depth,
                "chm_volume_m3": float(
                    2.0 * np.sum(np.clip(surface[sl][region] - edge, 0.0, None)) * res**2
                ),
                "envelope_volume_m3": envelope_volume(h, cx, cy, outline, res),
                "seed_id": seed,
                "touches_border": touches,
                "shared_outline_fraction": shared,
            }
        )
    table = pd.DataFrame(rows, columns=CROWN_COLUMNS)
    if row_direction is None and seg.row_layout is not None:  # the rows the crowns came from
        row_direction = RowDirection(seg.row_layout.direction, "canopy_rows", 1.0)
    if row_direction is None:
        row_direction = estimate_row_direction(
            table[["x", "y"]].to_numpy(),
            np.array([c[2] for c in cells]),
            np.array([c[3] for c in cells]),
        )
    extents = [directional_extents(r, c, res, row_direction.vector) for r, c, _, _ in cells]
    table["diameter_along_row_m"] = [e[0] for e in extents]
    table["diameter_across_row_m"] = [e[1] for e in extents]
    table.attrs["row_direction"] = row_direction
    return table
