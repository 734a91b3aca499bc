"""Checks of one run, each pass / warn / fail / info with its threshold (docs/VALIDATION.md).

Most checks need no truth and can fail: crowns several tree or row spacings wide, segments
holding several trunks, crowns unlike the rest of their row, a map whose registration or
GNSS went wrong, LiDAR volumes far from the drone's. Checks against simulator truth are
added when the run has it. ``run_checks`` reads the per-tree table and metrics.json's
content, so it works on a finished run folder as well as inside the pipeline.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
import pandas as pd

from canopy_kit.config import ChecksConfig
from canopy_kit.results.aerial_reference import DEFAULT_MODEL
from canopy_kit.volume.verb import ALPHA_COLUMN

Status = Literal["pass", "warn", "fail", "info"]
STATUSES = ("pass", "warn", "fail", "info")


@dataclass
class Check:
    """One check: its status, the measured value and the threshold it was held to.

    ``status`` may be given as a bool (pass/fail) or None (info).
    """

    name: str
    status: Status | bool | None
    value: str
    threshold: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        if self.status is None:
            self.status = "info"
        elif isinstance(self.status, bool | np.bool_):
            self.status = "pass" if self.status else "fail"
        elif self.status not in STATUSES:
            raise ValueError(
                f"check {self.name!r}: status {self.status!r} is not one of {STATUSES}"
            )

    def as_dict(self) -> dict[str, str]:
        """Plain data for metrics.json."""
        return asdict(self)


def grade(value: float, warn: float, fail: float, lower_is_worse: bool = False) -> Status:
    """``fail`` beyond ``fail``, ``warn`` beyond ``warn``, else ``pass`` (NaN: info)."""
    if not np.isfinite(value):
        return "info"
    if lower_is_worse:
        return "fail" if value < fail else "warn" if value < warn else "pass"
    return "fail" if value > fail else "warn" if value > warn else "pass"


def failed(checks: list[Check]) -> list[Check]:
    """The checks that failed: outputs of such a run should not be trusted."""
    return [c for c in checks if c.status == "fail"]


def format_value(value: float | None, unit: str = "", digits: int = 2) -> str:
    """A number with ``digits`` decimals and its unit; "n/a" when missing or not finite."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}{unit}"


def _listed(names: list[str], limit: int = 8) -> str:
    """The first ``limit`` names, comma-separated, " ..." when there are more."""
    return ", ".join(names[:limit]) + (" ..." if len(names) > limit else "")


def _names(trees: pd.DataFrame, mask: np.ndarray, limit: int = 8) -> str:
    names = trees.loc[mask, "tree_id"].astype(str).tolist() if "tree_id" in trees else []
    return _listed(names, limit)


def _share(n: int, total: int) -> float:
    return n / total if total else 0.0


def _thresholds(
    warn: float, fail: float, unit: str = "", digits: int = 2, below: bool = False
) -> str:
    sign = "<" if below else ">"
    if warn == fail:  # nothing between: beyond it fails
        return f"fail {sign} {fail:.{digits}f}{unit}"
    return f"warn {sign} {warn:.{digits}f}{unit}, fail {sign} {fail:.{digits}f}{unit}"


# -- without truth --------------------------------------------------------------------------
def crown_spacing_checks(
    trees: pd.DataFrame, layout: dict[str, Any], st: ChecksConfig
) -> list[Check]:
    """Crowns far wider than the spacing of the trees along the row or of the rows: merged."""
    out = []
    if "crown_diameter_m" not in trees or not len(trees):
        return out
    diameter = trees["crown_diameter_m"].to_numpy(float)
    if not np.isfinite(diameter).any():
        return out
    for key, what, warn, fail in (
        (
            "tree_spacing_m",
            "tree spacing along the row",
            st.crown_tree_spacing_warn,
            st.crown_tree_spacing_fail,
        ),
        ("row_spacing_m", "row spacing", st.crown_row_spacing_warn, st.crown_row_spacing_fail),
    ):
        spacing = layout.get(key)
        if spacing is None or not np.isfinite(spacing) or spacing <= 0:
            continue
        ratio = diameter / spacing
        worst = float(np.nanmax(ratio))
        status = grade(worst, warn, fail)
        source = layout.get("tree_spacing_source", "") if key == "tree_spacing_m" else "fitted rows"
        note = f"{what} {spacing:.1f} m (from {source})"
        wide = ratio > warn
        if wide.any():
            note += f"; wider than {warn:g}x: {_names(trees, wide)} (merged trees?)"
        out.append(
            Check(
                f"widest crown over the {what}",
                status,
                f"{worst:.2f}x",
                _thresholds(warn, fail, "x"),
                note,
            )
        )
    return out


def trunk_checks(trees: pd.DataFrame, layout: dict[str, Any], st: ChecksConfig) -> list[Check]:
    """Segments standing on several detected trunks hold several trees."""
    if "n_trunks" not in trees or not layout.get("trunks"):
        return []
    n = trees["n_trunks"].to_numpy(int)
    worst = int(n.max()) if len(n) else 0
    status: Status = (
        "fail"
        if worst >= st.trunks_per_segment_fail
        else "warn"
        if worst >= st.trunks_per_segment_warn
        else "pass"
    )
    many = n >= st.trunks_per_segment_warn
    note = f"{layout['trunks']} trunks found in the stem band, {int((n > 0).sum())} trees stand on one or more"
    if many.any():
        note += f"; on {st.trunks_per_segment_warn} or more: {_names(trees, many)}"
    return [
        Check(
            "most trunks under one segmented tree",
            status,
            str(worst),
            f"warn ≥ {st.trunks_per_segment_warn}, fail ≥ {st.trunks_per_segment_fail}",
            note,
        )
    ]


TRUNKS_SEEN_SHARE = 0.5  # trunks must stand under this share of trees to judge splits by them


def split_crown_check(trees: pd.DataFrame, layout: dict[str, Any], st: ChecksConfig) -> list[Check]:
    """Segments with no trunk of their own closer to a neighbour than the tree spacing allows:
    a crown cut in two (its other piece holds the trunk). Judged only where trunks are seen
    under most trees; a tree whose trunk is hidden stands a full spacing from its
    neighbours and is not counted."""
    spacing = layout.get("tree_spacing_m")
    if "n_trunks" not in trees or not layout.get("trunks") or len(trees) < 2:
        return []
    if layout.get("tree_spacing_source") != "trunks" or not spacing or not np.isfinite(spacing):
        return []
    from canopy_kit.results.tree_table import flagged

    n = trees["n_trunks"].to_numpy(int)
    name = "segments on no trunk, closer to a neighbour than the tree spacing (split crowns?)"
    counted = f"{layout['trunks']} trunks found in the stem band under {len(trees)} trees"
    if (n > 0).mean() < TRUNKS_SEEN_SHARE:
        note = f"{counted}: trunks seen under {int((n > 0).sum())} trees only, not judged"
        return [Check(name, None, "n/a", "", note)]
    from scipy.spatial import cKDTree

    xy = trees[["x", "y"]].to_numpy(float)
    nearest = cKDTree(xy).query(xy, k=2)[0][:, 1]  # the nearest other tree (memory O(n))
    split = (n == 0) & (nearest < st.trunkless_neighbour_ratio * spacing)
    note = f"{counted}; tree spacing {spacing:.1f} m"
    if split.any():
        note += f"; on no trunk, a neighbour within {st.trunkless_neighbour_ratio:g}x: "
        note += _names(trees, split)
        missed = split & flagged(trees, "trunk_flags").to_numpy()
        if missed.any():  # segment.trunk_feet: a row whose trunks the sensor barely saw
            note += (
                f"; {int(np.sum(missed))} of them in rows whose trunks' feet are barely "
                "sampled: there trunks were more likely missed (trees joined) than crowns split"
            )
    return [
        Check(
            name,
            grade(int(split.sum()), st.split_crowns_warn, st.split_crowns_fail),
            str(int(split.sum())),
            _thresholds(st.split_crowns_warn, st.split_crowns_fail, "", 0),
            note,
        )
    ]


def map_edge_check(trees: pd.DataFrame, layout: dict[str, Any], st: ChecksConfig) -> list[Check]:
    """Trees whose crown reaches the map's outline: the scan may end inside them (a clipped
    plot, a drive that stopped short), cutting their crowns and volumes."""
    from canopy_kit.segment.layout import EDGE_DISTANCE_M

    if "trees_at_map_edge" not in layout or not len(trees):
        return []
    names = list(layout["trees_at_map_edge"])
    share = _share(len(names), len(trees))
    warn, fail = st.crowns_at_map_edge_share_warn, st.crowns_at_map_edge_share_fail
    note = ""
    if names:
        note = f"within {EDGE_DISTANCE_M:g} m of the map's outline: {_listed(names)}"
    return [
        Check(
            "crowns reaching the map's edge (cut by the scan's end?)",
            grade(share, warn, fail),
            f"{len(names)} ({100 * share:.0f} %)",
            _thresholds(100 * warn, 100 * fail, " %", 0),
            note,
        )
    ]


def ceiling_check(segmentation: dict[str, Any], st: ChecksConfig) -> list[Check]:
    """Trees whose tops a set ``preprocess.max_canopy_height`` cut (map points above it in
    their footprints); a band from the data cuts none (``segment.preprocess.canopy_ceiling``)."""
    band = segmentation.get("canopy_band_m")
    if not band or "canopy_ceiling_source" not in segmentation:
        return []
    cut = list(segmentation.get("cut_at_ceiling", []))
    source = segmentation["canopy_ceiling_source"]
    note = f"canopy band {band[0]:g}-{band[1]:.1f} m above ground ({'from the data' if source == 'data' else source})"
    if cut:
        note += f"; cut: {_listed(cut)}: raise the limit or unset it"
    return [
        Check(
            "crowns cut at the canopy band's top",
            grade(len(cut), st.crowns_cut_at_ceiling_warn, st.crowns_cut_at_ceiling_fail),
            str(len(cut)),
            _thresholds(st.crowns_cut_at_ceiling_warn, st.crowns_cut_at_ceiling_fail, "", 0),
            note,
        )
    ]


def trunk_feet_check(segmentation: dict[str, Any]) -> list[Check]:
    """Rows of a wall cut at its trunks' midpoints whose stem band's foot holds too few
    points beside their canopy: trunks probably missed, trees joined to their neighbours
    (``segment.trunk_feet``; only with ``cut = "trunk-midpoints"``). Warns, never fails:
    the rule reads the sampling, not the trunks themselves."""
    feet = segmentation.get("trunk_feet")
    if not feet or not feet.get("rows"):
        return []
    rows = feet["rows"]
    missed = [r for r in rows if r.get("trunks_missed")]
    share = 100 * float(feet.get("min_foot_share", float("nan")))
    lo, hi = feet.get("foot_band_m", (float("nan"), float("nan")))
    shares = ", ".join(
        f"r{r['row']} {format_value(100 * r['foot_share'] if r['foot_share'] is not None else None, ' %', 1)}"
        for r in rows
    )
    note = f"foot points ({lo:g}-{hi:g} m) per canopy point: {shares}"
    if missed:
        note += f"; trees of these rows flagged in trunk_flags: {_listed(feet.get('flagged_trees', []))}"
    return [
        Check(
            "rows whose trunks' feet are barely sampled (trunks missed, trees joined?)",
            "warn" if missed else "pass",
            f"{len(missed)} of {len(rows)}",
            f"warn: a row's foot below {share:g} % of its canopy",
            note,
        )
    ]


def table_checks(trees: pd.DataFrame, st: ChecksConfig) -> list[Check]:
    """Trees found, volumes flagged unreliable, crowns unlike the others of their row."""
    from canopy_kit.results.tree_table import flagged

    n = len(trees)
    out = [Check("trees segmented", n > 0, str(n), "fail < 1")]
    for column, name, warn, fail in (
        (
            "volume_flags",
            "volumes flagged as unreliable",
            st.flagged_volume_share_warn,
            st.flagged_volume_share_fail,
        ),
        (
            "segment_flags",
            (
                "crowns unlike the others of their row (below 0.5x the median diameter "
                "with no trunk of its own, or above 1.6x: fragments or merged trees?)"
            ),
            st.crown_outlier_share_warn,
            st.crown_outlier_share_fail,
        ),
    ):
        if column not in trees:
            continue
        odd = flagged(trees, column).to_numpy()
        share = _share(int(odd.sum()), n)
        out.append(
            Check(
                name,
                grade(share, warn, fail),
                f"{int(odd.sum())} ({100 * share:.0f} %)",
                _thresholds(100 * warn, 100 * fail, " %", 0),
                _names(trees, odd, 12),
            )
        )
    if "volume_interval_flags" in trees:  # not an error of the run: trees to trust less
        marked = flagged(trees, "volume_interval_flags").to_numpy()
        bounds = trees.get("volume_low_m3", pd.Series(0.0, index=trees.index))
        none = marked & bounds.isna().to_numpy()  # no interval at all (the flag says why)
        wide = marked & ~none
        notes = []
        if wide.any():
            notes.append(f"{_names(trees, wide, 12)}: see volume_low_m3 / volume_high_m3")
        if none.any():
            notes.append(f"no interval: {_names(trees, none, 12)} (volume_interval_flags says why)")
        out.append(
            Check(
                "volumes with a wide interval or none (sparse, deeply lobed or interwoven "
                "crowns, missed trunks)",
                None,
                f"{int(marked.sum())} ({100 * _share(int(marked.sum()), n):.0f} %)",
                "",
                "; ".join(notes),
            )
        )
    if "crown_contact" in trees:
        out.append(touching_crowns_check(trees))
    return out


def touching_crowns_check(trees: pd.DataFrame) -> Check:
    """Trees whose crowns interweave with a neighbour's (``crown_contact`` at or above
    ``segment.contact.TOUCHING_CONTACT``): information, naming them. Where the segmentation
    draws their border sets their volume's error; their interval is widened for it
    (``volume.interwoven``; docs/VOLUMES.md "Touching crowns")."""
    from canopy_kit.segment.contact import TOUCHING_CONTACT
    from canopy_kit.volume.interwoven import HELD_OUT_RUNS, UNWIDENED_HELD, WIDENED_HELD

    touching = (trees["crown_contact"] >= TOUCHING_CONTACT).to_numpy()
    names = _names(trees, touching, 12)
    return Check(
        "crowns interwoven with a neighbour's (their border, so their volume, uncertain)",
        None,
        f"{int(touching.sum())} ({100 * _share(int(touching.sum()), len(trees)):.0f} %)",
        f"crown_contact >= {TOUCHING_CONTACT:g}",
        f"{names}: their interval is widened for where the segmentation drew the border (on "
        f"{HELD_OUT_RUNS} it then held {WIDENED_HELD} such trees, {UNWIDENED_HELD} before)"
        if names
        else "",
    )


def map_checks(mapping: dict[str, Any], st: ChecksConfig) -> list[Check]:
    """Map quality from the mapping diagnostics: ICP registrations rejected, GNSS fixes
    rejected and the GNSS bias the pose graph had to absorb, the quality flags."""
    out = []
    if mapping.get("source") == "map file":  # made elsewhere: no registration or GNSS to judge
        trajectory = mapping.get("trajectory_file")
        out.append(
            Check(
                "map made elsewhere (registration, GNSS, drive)",
                None,
                "not judged",
                "",
                f"map file {mapping.get('map_file', '')}; "
                + (f"trajectory {trajectory}" if trajectory else "not judged: no trajectory"),
            )
        )
    registered = mapping.get("sweeps_registered")
    if registered:
        rejected = int(mapping.get("registrations_rejected", 0))
        share = _share(rejected, int(registered) + rejected)
        out.append(
            Check(
                "ICP registrations rejected (correction too large)",
                grade(
                    share,
                    st.rejected_registrations_share_warn,
                    st.rejected_registrations_share_fail,
                ),
                f"{rejected} of {int(registered) + rejected} ({100 * share:.1f} %)",
                _thresholds(
                    100 * st.rejected_registrations_share_warn,
                    100 * st.rejected_registrations_share_fail,
                    " %",
                    0,
                ),
            )
        )
    gnss = mapping.get("gnss") or {}
    if "rejected_share" in gnss:
        share = float(gnss["rejected_share"])
        out.append(
            Check(
                "GNSS fixes rejected",
                grade(share, st.gnss_rejected_share_warn, st.gnss_rejected_share_fail),
                f"{100 * share:.1f} %",
                _thresholds(
                    100 * st.gnss_rejected_share_warn, 100 * st.gnss_rejected_share_fail, " %", 0
                ),
            )
        )
    if "bias_rms_m" in gnss and np.isfinite(gnss["bias_rms_m"]):
        bias = float(gnss["bias_rms_m"])
        out.append(
            Check(
                "GNSS bias absorbed by the pose graph (RMS)",
                grade(bias, st.gnss_bias_rms_warn_m, st.gnss_bias_rms_fail_m),
                format_value(bias, " m"),
                _thresholds(st.gnss_bias_rms_warn_m, st.gnss_bias_rms_fail_m, " m", 1),
                f"{gnss.get('mode_changes', 0)} receiver mode changes",
            )
        )
    flags = list(mapping.get("quality_flags", []))
    if flags:
        out.append(
            Check("map quality flags", "warn", str(len(flags)), "warn ≥ 1", ", ".join(flags))
        )
    rig = imu_mount_check(mapping)
    if rig is not None:
        out.append(rig)
    return out


def imu_mount_check(mapping: dict[str, Any]) -> Check | None:
    """Pass when the drive puts the IMU where the rig says (hand-eye on the rotations)."""
    ext = mapping.get("extrinsics", {})
    if "difference_deg" not in ext or ext.get("mode") == "calibrate":
        return None
    angle = float(ext["difference_deg"])
    tolerance_deg = float(ext.get("tolerance_deg", 2.0))
    return Check(
        "IMU mount agrees with the drive (gyro vs LiDAR rotations)",
        angle <= tolerance_deg,
        f"{angle:.2f}°",
        f"fail > {tolerance_deg:g}°",
        f"mount from {mapping.get('rig', {}).get('sources', {}).get('imu', '?')}",
    )


def aerial_checks(metrics: dict[str, Any], trees: pd.DataFrame, st: ChecksConfig) -> list[Check]:
    """LiDAR trees matched to drone crowns, crowns of plausible size, volume disagreement.

    The disagreement is the MAPE of the alpha-shape volume against the flight's recommended
    aerial volume (``metrics["aerial"]["reference_column"]``: the visual hull of an oblique
    flight, else the height-aware ellipsoid, bias -4 % to +1 % against true crowns); the
    other aerial models are information beside it. Against the paper's sphere (biased +28 %
    to +85 %) a large MAPE is expected of an honest run, so that row is information beside a
    reference and warns at most without one.
    """
    from canopy_kit.results.aerial_reference import MODEL_NAMES
    from canopy_kit.results.tree_table import comparable_aerial_sphere

    aerial = metrics.get("aerial")
    if not aerial:
        return []
    out = aerial_match_checks(aerial, len(trees), st)
    if ALPHA_COLUMN not in trees or "aerial_sphere_volume_m3" not in trees:
        return out
    usable = comparable_aerial_sphere(trees).notna() & trees[ALPHA_COLUMN].notna()
    reference = aerial.get("reference_column", "aerial_" + DEFAULT_MODEL)
    if reference not in trees:
        reference = "aerial_" + DEFAULT_MODEL
    models = [(f"aerial_{m}", name) for m, name in MODEL_NAMES.items()]
    models.sort(key=lambda m: m[0] != reference)  # the reference first
    for column, model in [*models, ("aerial_sphere_volume_m3", "paper's sphere")]:
        if column in trees:
            ok = usable & trees[column].notna()
            out.append(aerial_volume_check(trees, ok, column, model, st, reference))
    return out


def aerial_match_checks(aerial: dict[str, Any], n: int, st: ChecksConfig) -> list[Check]:
    """Shares of the ``n`` LiDAR trees matched to an aerial crown, and of the matched crowns
    of a plausible size (the others are fragments or merged neighbours)."""
    matched = int(aerial.get("matched_trees", 0))
    compared = int(aerial.get("compared_trees", matched))
    threshold = _thresholds(
        100 * st.aerial_matched_share_warn, 100 * st.aerial_matched_share_fail, " %", 0, below=True
    )
    return [
        Check(
            "LiDAR trees matched to an aerial crown",
            grade(
                _share(matched, n),
                st.aerial_matched_share_warn,
                st.aerial_matched_share_fail,
                lower_is_worse=True,
            ),
            f"{matched}/{n}",
            threshold,
        ),
        Check(
            "matched aerial crowns of plausible size",
            grade(
                _share(compared, matched) if matched else float("nan"),
                st.aerial_matched_share_warn,
                st.aerial_matched_share_fail,
                lower_is_worse=True,
            ),
            f"{compared}/{matched}",
            threshold,
            "others are fragments or merged neighbours: flagged in the table, left out of the "
            "comparison"
            if compared < matched
            else "",
        ),
    ]


def aerial_volume_check(
    trees: pd.DataFrame,
    ok: pd.Series,
    column: str,
    model: str,
    st: ChecksConfig,
    reference: str = "aerial_" + DEFAULT_MODEL,
) -> Check:
    """MAPE of the alpha-shape volume against one aerial volume ``column`` on the trees ``ok``
    (information with fewer than two). Only the flight's ``reference`` model can fail a run;
    another model beside it is information, and the paper's sphere, biased itself, warns at
    most when there is no reference."""
    from canopy_kit.evaluate import stats

    name = f"alpha shape vs aerial {model} volume (MAPE)"
    if ok.sum() < 2:
        return Check(name, "info", "n/a", "", f"{int(ok.sum())} trees comparable")
    lidar, drone = trees.loc[ok, ALPHA_COLUMN].to_numpy(), trees.loc[ok, column].to_numpy()
    mape = stats.mape(lidar, drone)
    status = grade(mape, st.aerial_mape_warn_pct, st.aerial_mape_fail_pct)
    note = f"{int(ok.sum())} trees, bias {stats.mean_percent_bias(lidar, drone):+.1f} %"
    threshold = _thresholds(st.aerial_mape_warn_pct, st.aerial_mape_fail_pct, " %", 0)
    has_reference = reference in trees
    if column == "aerial_sphere_volume_m3":  # biased itself: never fails a run
        if has_reference:
            status, threshold = "info", "none (the flight's reference is held to it)"
            note += "; the sphere itself is biased +28 % to +85 %: for information"
        else:
            status = "warn" if status == "fail" else status
            note += "; the sphere itself is biased +28 % to +85 %: warns at most"
    elif column != reference and has_reference:
        status, threshold = "info", "none (the flight's reference is held to it)"
        note += "; not the flight's recommended aerial model: for information"
    elif column == reference:
        note += "; the flight's recommended aerial reference"
    return Check(name, status, format_value(mape, " %", 1), threshold, note)


# -- against simulator truth ----------------------------------------------------------------
def true_volume_name(evaluation: dict[str, Any]) -> str:
    """What a simulated session's true volume is: the drawn crown, or on a fruiting wall each
    tree's cut between the midpoints to its neighbours' trunks."""
    if evaluation.get("volume_truth", "crown") == "crown":
        return "true crown volume, the simulator's drawn envelope"
    return "true volume, the wall between the midpoints to the neighbours' trunks"


def truth_checks(evaluation: dict[str, Any]) -> list[Check]:
    """Mapping, segmentation and volumes against a simulated session's truth."""
    return (
        mapping_truth_checks(evaluation.get("mapping", {}))
        + segmentation_truth_checks(evaluation.get("segmentation"))
        + volume_truth_checks(evaluation)
    )


def mapping_truth_checks(mapping: dict[str, Any]) -> list[Check]:
    """The trajectory's ATE and drift, the map against the true surfaces, the absolute
    position error (``evaluation["mapping"]``)."""
    out = []
    if "not_judged" in mapping:  # a map made elsewhere (canopy_kit.mapping.map_source)
        out.append(
            Check(
                "trajectory ATE RMSE (vs true odometry)",
                None,
                "not judged",
                "",
                mapping["not_judged"],
            )
        )
    if "ate_rmse_m" in mapping:
        out.append(
            Check(
                "trajectory ATE RMSE (vs true odometry)",
                mapping["ate_rmse_m"] <= 0.20,
                format_value(mapping["ate_rmse_m"], " m", 3),
                "fail > 0.20 m",
            )
        )
    if "drift_percent" in mapping:
        out.append(
            Check(
                "drift (% of path length)",
                mapping["drift_percent"] <= 0.5,
                format_value(mapping["drift_percent"], " %", 3),
                "fail > 0.5 %",
            )
        )
    if "map_aligned" in mapping:
        d = mapping["map_aligned"]
        out.append(
            Check(
                "map points to true surfaces, after alignment (median)",
                d["median_m"] <= 0.05,
                format_value(d["median_m"], " m", 3),
                "fail > 0.05 m",
                f"90 % within {format_value(d['p90_m'], ' m', 3)}",
            )
        )
    if "georeferenced" in mapping:
        g = mapping["georeferenced"]
        out.append(
            Check(
                "absolute position error of the trajectory (GNSS-limited)",
                None,
                format_value(g["horizontal_rmse_m"], " m", 2),
                "",
                f"vertical {format_value(g['vertical_rmse_m'], ' m', 2)}",
            )
        )
    return out


def segmentation_truth_checks(seg: dict[str, Any] | None) -> list[Check]:
    """Trees segmented one-to-one, and rows and labels right (``evaluation["segmentation"]``)."""
    if not seg:
        return []
    return [
        Check(
            "trees segmented one-to-one (IoU ≥ 0.5)",
            seg["success_rate"] >= 0.95,
            f"{seg['n_correct']}/{seg['n_truth']} ({100 * seg['success_rate']:.0f} %)",
            "fail < 95 %",
            f"merged {seg['n_merged']}, split {seg['n_split']}, missed {seg['n_missed']}",
        ),
        Check(
            "row and label correct",
            seg["label_accuracy"] >= 0.95,
            f"{100 * seg['label_accuracy']:.0f} %",
            "fail < 95 % of matched trees",
        ),
    ]


def volume_truth_checks(evaluation: dict[str, Any]) -> list[Check]:
    """The recommended volume against its measurand and its interval's coverage, then the
    alpha shape's, convex hull's and recommended volume's errors against the true crowns."""
    out = []
    recommended = evaluation.get("recommended_volume")
    own = evaluation.get("volumes", {}).get("recommended_vs_measurand")
    if isinstance(own, dict) and "mape_pct" in own:
        out.append(
            Check(
                f"{recommended} (recommended) volume vs its measurand on the complete foliage "
                "(MAPE)",
                None,
                format_value(own["mape_pct"], " %", 1),
                "",
                f"bias {format_value(own['bias_pct'], ' %', 1)}",
            )
        )
    held = evaluation.get("volumes", {}).get("recommended_interval")
    if isinstance(held, dict) and (held.get("n") or held.get("no_interval")):
        out.append(interval_check(recommended, held))
    for method, v in evaluation.get("volumes", {}).items():
        if (
            isinstance(v, dict)
            and "mape_pct" in v
            and method in ("alpha_shape", "convex_hull", recommended)
        ):
            out.append(
                Check(
                    f"{method}{' (recommended)' if method == recommended else ''} volume vs "
                    f"{true_volume_name(evaluation)} (MAPE)",
                    None,
                    format_value(v["mape_pct"], " %", 1),
                    "",
                    f"bias {format_value(v['bias_pct'], ' %', 1)}",
                )
            )
    return out


def run_checks(
    metrics: dict[str, Any], trees: pd.DataFrame, settings: ChecksConfig | None = None
) -> list[Check]:
    """Every check of a run, from its metrics (metrics.json's content) and per-tree table."""
    st = settings or ChecksConfig()
    layout = metrics.get("layout", {})
    checks = table_checks(trees, st)
    checks += crown_spacing_checks(trees, layout, st)
    checks += trunk_checks(trees, layout, st)
    checks += split_crown_check(trees, layout, st)
    checks += ceiling_check(metrics.get("segmentation", {}), st)
    checks += trunk_feet_check(metrics.get("segmentation", {}))
    checks += map_edge_check(trees, layout, st)
    checks += map_checks(metrics.get("mapping", {}), st)
    checks += aerial_checks(metrics, trees, st)
    checks += truth_checks(metrics.get("evaluation", {}))
    # a warning that a check of its own carries (Segmentation.carried_warnings) is not repeated
    segmentation = metrics.get("segmentation", {})
    carried = set(segmentation.get("carried_warnings", []))
    carried.add(segmentation.get("trunk_feet", {}).get("warning"))  # runs from before the list
    checks += [
        Check("warning", "warn", "", "", str(w))
        for w in metrics.get("warnings", [])
        if w not in carried
    ]
    return checks


def summary(checks: list[Check]) -> dict[str, int]:
    """How many checks have each status."""
    return {s: sum(1 for c in checks if c.status == s) for s in STATUSES}


def interval_check(recommended: str, held: dict[str, Any]) -> Check:
    """Whether the recommended volume's interval held each matched tree's measurand: on the
    tree families it holds ≥ 90 % (docs/VOLUMES.md), below that a run warns (never fails: on
    a few trees one miss is 10-30 %). The interval covers what the drive loses and, on an
    interwoven crown, where the border was drawn (``volume.interwoven``), not every crown the
    segmentation cut wrongly: the note gives the misses' IoU with their true tree, and how
    many trees claim no interval (not counted; information only when none does)."""
    name = f"{recommended} (recommended) interval holds its measurand"
    notes = []
    ious = [v for v in held.get("missed_iou", []) if np.isfinite(v)]
    if ious:
        span = f"{min(ious):.2f}-{max(ious):.2f}" if len(ious) > 1 else f"{ious[0]:.2f}"
        whose = "their IoU" if len(ious) > 1 else "its IoU"
        notes.append(
            f"{len(ious)} missed, {whose} with the true tree {span} "
            "(the interval covers what the drive loses and an interwoven crown's border, not "
            "every segmentation cut)"
        )
    if held.get("no_interval"):
        k = held["no_interval"]
        notes.append(
            f"{k} {'tree claims' if k == 1 else 'trees claim'} no interval, not counted "
            "(volume_interval_flags says why)"
        )
    if not held["n"]:
        return Check(name, None, "0/0", "warn < 90 %", "; ".join(notes))
    share = held["held"] / held["n"]
    return Check(
        name,
        "warn" if share < 0.9 else "pass",
        f"{held['held']}/{held['n']} ({100 * share:.0f} %)",
        "warn < 90 %",
        "; ".join(notes),
    )
