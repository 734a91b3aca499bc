"""The per-tree table of a run: the volume stage's rows with positions in WGS84, crowns
unlike the others, trunks and aerial truth joined (:func:`tree_table`), and the helpers that
read it (:func:`flagged`, :func:`comparable_aerial_sphere`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.config import GroundTruthConfig, VolumeConfig
from canopy_kit.volume.metrics import POSITION_AND_SIZE
from canopy_kit.volume.verb import PAPER_VOLUME_COLUMNS, volume_column

FIRST_COLUMNS = [
    "tree_id",
    "label",
    "row",
    *POSITION_AND_SIZE,
    *PAPER_VOLUME_COLUMNS,
]


def tree_table(ctx: Any) -> pd.DataFrame:
    """The final per-tree table of ``ctx`` (a ``pipeline.RunContext``): LiDAR results,
    positions in WGS84, crowns unlike the others (``segment_flags``) and aerial truth if any."""
    from canopy_kit.segment.qa import crown_outliers

    trees = ctx.trees.copy()
    if ctx.layout is None:
        trees["segment_flags"] = crown_outliers(trees)
    else:  # the trunks tell a small tree from a fragment
        trunks = ctx.layout.trunks_per_segment(trees["segment"].to_numpy())
        trees["segment_flags"] = crown_outliers(trees.assign(n_trunks=trunks))
        trees["n_trunks"] = trunks
    seg, cloud = ctx.segmentation, getattr(ctx.mapping, "map", None)
    if cloud is not None and len(seg.labels) == len(cloud):
        trees = with_crown_contact(trees, cloud.xyz, seg.labels, ctx.config.volume)
    feet = getattr(ctx.segmentation, "trunk_feet", None) or {}
    if feet:  # a wall cut at its trunks' midpoints: the rows whose trunks were probably missed
        trees = with_trunk_flags(trees, feet)
    frame = getattr(ctx.mapping, "frame", None)
    if frame is not None and len(trees):
        xyz = np.column_stack([trees["x"], trees["y"], np.zeros(len(trees))])
        xyz = xyz + ctx.mapping.map.origin - frame.origin
        lat, lon, _ = frame.to_wgs84(xyz)
        trees["lat"], trees["lon"] = lat, lon
    else:
        trees["lat"], trees["lon"] = np.nan, np.nan
    if ctx.aerial is not None:
        trees = join_aerial(trees, ctx.aerial, ctx.config.ground_truth)
    rest = [c for c in trees.columns if c not in FIRST_COLUMNS]
    return trees[[c for c in FIRST_COLUMNS if c in trees.columns] + rest].reset_index(drop=True)


def with_crown_contact(
    trees: pd.DataFrame, xyz: np.ndarray, labels: np.ndarray, volume: VolumeConfig
) -> pd.DataFrame:
    """``trees`` with ``crown_contact`` (the share of each crown touching another tree's,
    ``segment.contact``, from the points ``xyz`` and their segment ``labels``) and the
    recommended interval of interwoven crowns widened for their border
    (``volume.interwoven``): there the border, not the drive, sets the error. Unchanged
    without a ``segment`` column or on a wall (cut at its trunks, it touches by design)."""
    from canopy_kit.segment.contact import TOUCHING_CONTACT, crown_contact
    from canopy_kit.volume.interwoven import widen_for_contact

    if "segment" not in trees or getattr(volume, "interval_kind", "") == "wall":
        return trees
    share = crown_contact(xyz, labels)
    trees = trees.assign(
        crown_contact=np.array([share.get(int(s), np.nan) for s in trees["segment"]], float)
    )
    rec = volume.recommended
    return widen_for_contact(trees, rec, volume_column(rec), TOUCHING_CONTACT)


TRUNKS_MISSED_NOTE = (
    "its row's trunk feet barely sampled: trunks probably missed, the tree may hold a "
    "neighbour (volume too large)"
)


def trunk_flags(trees: pd.DataFrame, feet: dict[str, Any]) -> pd.Series:
    """Per tree: a note when it stands in a row whose trunks were probably missed
    (``segment.trunk_feet``), else empty."""
    bad = set(feet.get("flagged_trees", []))
    ids = trees["tree_id"] if "tree_id" in trees else pd.Series("", index=trees.index)
    return pd.Series(np.where(ids.isin(bad), TRUNKS_MISSED_NOTE, ""), index=trees.index)


def with_trunk_flags(
    trees: pd.DataFrame, feet: dict[str, Any], tree_ids: pd.Series | None = None
) -> pd.DataFrame:
    """``trees`` with ``trunk_flags`` (:func:`trunk_flags`: the trees of the rows whose trunks
    were probably missed, ``feet`` as ``segment.trunk_feet`` gives them) and no volume interval
    for those trees (:func:`no_interval_where_trunks_missed`). ``tree_ids``: each row's id in
    the segmentation that measured the feet (default: the ``tree_id`` column)."""
    ids = trees["tree_id"] if tree_ids is None else tree_ids
    named = pd.DataFrame({"tree_id": np.asarray(ids)}, index=trees.index)
    return no_interval_where_trunks_missed(trees.assign(trunk_flags=trunk_flags(named, feet)))


NO_INTERVAL_NOTE = (
    "no interval: its row's trunks were probably missed, so the tree may hold a neighbour, "
    "beyond what an interval of the drive's losses covers"
)


def no_interval_where_trunks_missed(trees: pd.DataFrame) -> pd.DataFrame:
    """``trees`` with no volume interval (NaN bounds, :data:`NO_INTERVAL_NOTE` in
    ``volume_interval_flags``) where ``trunk_flags`` says the row's trunks were probably
    missed: a wall tree that took in a missed neighbour reads up to twice its cut (truth /
    estimate 0.53-1.03 on a Livox Mid-360 wall, seed 0), and an interval claiming to cover it
    would be false. Unchanged without those columns."""
    from canopy_kit.volume.uncertainty import appended_flags

    needed = ("trunk_flags", "volume_low_m3", "volume_high_m3", "volume_interval_flags")
    if any(c not in trees for c in needed):
        return trees
    missed = flagged(trees, "trunk_flags").to_numpy()
    if not missed.any():
        return trees
    out = trees.copy()
    out.loc[missed, ["volume_low_m3", "volume_high_m3"]] = np.nan
    before = list(out.loc[missed, "volume_interval_flags"].fillna("").astype(str))
    out.loc[missed, "volume_interval_flags"] = appended_flags(
        before, [NO_INTERVAL_NOTE] * len(before)
    )
    return out


AERIAL_COLUMNS = {  # ground_truth's per-tree columns -> the names of the per-tree table
    "aerial_diameter_max_m": "aerial_diameter_m",
    "aerial_diameter_mean_m": "aerial_diameter_mean_m",
    "aerial_diameter_across_row_m": "aerial_diameter_across_row_m",
    "aerial_diameter_along_row_m": "aerial_diameter_along_row_m",
    "aerial_sphere_volume_m3": "aerial_sphere_volume_m3",
    "aerial_ellipsoid_volume_m3": "aerial_ellipsoid_volume_m3",
    "aerial_chm_volume_m3": "aerial_chm_volume_m3",
    "aerial_envelope_volume_m3": "aerial_envelope_volume_m3",
    "aerial_hull_volume_m3": "aerial_hull_volume_m3",
    "aerial_height_m": "aerial_height_m",
    "aerial_distance_m": "aerial_match_distance_m",
    "aerial_crown_flag": "aerial_crown_flag",
}


def join_aerial(
    trees: pd.DataFrame, aerial: Any, settings: GroundTruthConfig | None = None
) -> pd.DataFrame:
    """Add the matched aerial crown diameter and sphere volume, and the LiDAR-vs-aerial errors.

    ``aerial_flag`` names an aerial crown that cannot be the same tree's crown (its diameter
    far from the LiDAR crown's: a fragment, or neighbours merged); such trees keep their
    aerial columns but get no error and stay out of the agreement statistics. So do trees
    whose crown the drone side flagged from the imagery alone (``aerial_crown_flag``,
    ``ground_truth.crown_flags``: probably two trees in one label, or a fragment).
    """
    st = settings or GroundTruthConfig()
    # A result made before a column existed (reused, read back from disk) lacks it.
    present = [c for c in AERIAL_COLUMNS if c in aerial.trees]
    matched = aerial.trees[["segment", *present]].rename(columns=AERIAL_COLUMNS)
    matched = matched[aerial.trees["matched"].to_numpy(bool)]
    out = trees.merge(matched, on="segment", how="left")
    ratio = out["aerial_diameter_m"] / out["crown_diameter_m"]
    out["aerial_flag"] = np.select(
        [ratio < st.min_diameter_ratio, ratio > st.max_diameter_ratio],
        [
            f"aerial crown a fragment (diameter below {st.min_diameter_ratio:g}x the LiDAR crown's)",
            f"aerial crown merged with neighbours (diameter above {st.max_diameter_ratio:g}x "
            "the LiDAR crown's)",
        ],
        default="",
    )
    if "aerial_crown_flag" in out:
        imagery = out["aerial_crown_flag"].fillna("").astype(str)
        out["aerial_flag"] = np.where(
            (out["aerial_flag"] == "") & (imagery != ""),
            "aerial crown flagged from the drone imagery (" + imagery + ")",
            out["aerial_flag"],
        )
    usable = comparable_aerial_sphere(out)
    for col in PAPER_VOLUME_COLUMNS:
        if col in out:
            name = col.replace("volume_", "").replace("_m3", "")
            out[f"error_{name}_vs_aerial_pct"] = 100.0 * (out[col] - usable) / usable
    return out


def comparable_aerial_sphere(trees: pd.DataFrame) -> pd.Series:
    """The aerial sphere volume of each tree whose aerial crown is not flagged (NaN otherwise)."""
    flag = trees["aerial_flag"].fillna("") if "aerial_flag" in trees else ""
    return trees["aerial_sphere_volume_m3"].where(flag == "")


def flagged(trees: pd.DataFrame, column: str) -> pd.Series:
    """Trees with a note in ``column`` (``volume_flags``, ``segment_flags``); none without it."""
    if column not in trees:
        return pd.Series(False, index=trees.index)
    return trees[column].fillna("").astype(str).str.len() > 0  # a missing note (NaN) is no note
