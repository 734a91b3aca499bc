"""Human names with units for the per-tree table's columns: the one place the report gets them."""

from __future__ import annotations

import re

from canopy_kit.volume.verb import ALPHA_COLUMN, CONVEX_HULL_COLUMN, volume_column

# snake_case column of trees.csv -> what the report's table header says
COLUMN_LABELS: dict[str, str] = {
    "tree_id": "Tree ID",
    "label": "Label in row",
    "row": "Row",
    "index_in_row": "Position in row",
    "segment": "Segment",
    "x": "x east (local) [m]",
    "y": "y north (local) [m]",
    "lat": "Latitude [°]",
    "lon": "Longitude [°]",
    "n_points": "LiDAR points",
    "height_m": "Tree height [m]",
    "crown_base_height_m": "Crown base height [m]",
    "crown_diameter_m": "Crown diameter (max) [m]",
    "crown_diameter_mean_m": "Crown diameter (mean) [m]",
    "projected_area_m2": "Crown projected area [m²]",
    "sphere_volume_m3": "Sphere volume from the crown diameter [m³]",
    CONVEX_HULL_COLUMN: "Convex-hull volume [m³]",
    ALPHA_COLUMN: "Alpha-shape volume [m³]",
    volume_column("alpha_hull"): "Alpha-hull volume [m³]",
    volume_column("voxel"): "Voxel volume [m³]",
    volume_column("slices"): "Slice volume [m³]",
    volume_column("mirror"): "Mirrored-crown volume [m³]",
    "volume_alpha_auto_m3": "Alpha-shape volume, automatic α [m³]",
    "volume_adaptive_alpha_m3": "Adaptive-α volume [m³]",
    "volume_foliage_envelope_m3": "Foliage-envelope volume [m³]",
    "volume_enclosing_ellipsoid_m3": "Enclosing-ellipsoid volume [m³]",
    "volume_measurand": "What the recommended volume measures",
    "volume_without_voids_m3": "Recommended volume without enclosed empty space [m³]",
    "volume_method": "Recommended estimator (its interval below)",
    "volume_low_m3": "Volume interval, low [m³]",
    "volume_high_m3": "Volume interval, high [m³]",
    "scan_coverage": "Crown seen around (share of sectors)",
    "surface_fill": "Points' surface fill (dense ≥ 2, sparse < 1.2)",
    "volume_interval_flags": "Volume interval flags",
    "crown_kind": "Crown kind the interval took (dense, thin, mixed, sparse)",
    "volume_flags": "Volume flags",
    "segment_flags": "Segment flags",
    "crown_contact": "Crown touching a neighbour's (share; ≥ 0.08: border uncertain)",
    "n_trunks": "Trunks detected",
    "aerial_diameter_m": "Drone crown diameter (max) [m]",
    "aerial_diameter_mean_m": "Drone crown diameter (mean) [m]",
    "aerial_diameter_across_row_m": "Drone crown extent across the row [m]",
    "aerial_diameter_along_row_m": "Drone crown extent along the row [m]",
    "aerial_sphere_volume_m3": "Drone sphere volume [m³]",
    "aerial_ellipsoid_volume_m3": "Drone ellipsoid volume [m³]",
    "aerial_chm_volume_m3": "Drone canopy-height-model volume [m³]",
    "aerial_envelope_volume_m3": "Drone 2.5-D envelope volume [m³]",
    "aerial_hull_volume_m3": "Drone visual-hull volume [m³]",
    "aerial_height_m": "Drone tree height [m]",
    "aerial_match_distance_m": "Drone crown match distance [m]",
    "aerial_flag": "Drone crown flag",
    "aerial_crown_flag": "Drone crown flag from the imagery alone",
    "truth_id": "Simulator tree",
    "truth_tree_id": "Simulator tree",
    "truth_label": "Simulator label",
    "truth_row": "Simulator row",
    "truth_iou": "Point IoU with the simulator tree",
    "true_crown_volume_m3": "True crown volume: the simulator's drawn envelope [m³]",
    "true_measurand_m3": "True volume as the recommended estimator defines it, on the complete foliage [m³]",
    "true_sphere_volume_m3": "True sphere volume (simulator) [m³]",
    "true_crown_diameter_m": "True crown diameter (simulator) [m]",
    "true_height_m": "True height (simulator) [m]",
}

_UNITS = [("_pct", "%"), ("_m3", "m³"), ("_m2", "m²"), ("_m", "m"), ("_s", "s"), ("_deg", "°")]
# error_<method>_vs_<reference>_pct: the relative error of a volume column against a reference
_ERROR = re.compile(r"error_(?P<method>.+)_vs_(?P<ref>true|aerial|measurand)_pct")
_REFERENCES = {
    "true": "true crown (drawn envelope)",
    "aerial": "drone sphere",
    "measurand": "its measurand on the complete foliage",
}
_METHODS = {"alpha": "alpha shape"}


def column_label(column: str) -> str:
    """The header for ``column``: its entry in ``COLUMN_LABELS``, else the name in words with
    the unit its suffix says (``foo_bar_m3`` -> ``Foo bar [m³]``)."""
    if column in COLUMN_LABELS:
        return COLUMN_LABELS[column]
    error = _ERROR.fullmatch(column)
    if error:
        method = error["method"]
        name = _METHODS.get(method, method.replace("_", " "))
        return f"{_words(name)} vs {_REFERENCES[error['ref']]}: error [%]"
    for suffix, unit in _UNITS:
        if column.endswith(suffix) and len(column) > len(suffix):
            return f"{_words(column[: -len(suffix)])} [{unit}]"
    return _words(column)


def _words(name: str) -> str:
    text = re.sub(r"_+", " ", name).strip()
    return text[:1].upper() + text[1:]
