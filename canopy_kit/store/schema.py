"""Tables of the orchard store (DuckDB). Positions are metres in the orchard's own frame:
UTM (``epsg``) minus the orchard's origin, fixed by its first session."""

from __future__ import annotations

SCHEMA_VERSION = "2"

TABLES = {
    "meta": "key VARCHAR PRIMARY KEY, value VARCHAR",
    "orchards": "orchard VARCHAR PRIMARY KEY, epsg INTEGER, origin_easting DOUBLE, "
    "origin_northing DOUBLE, created_at TIMESTAMP",
    "sessions": "session_id VARCHAR PRIMARY KEY, orchard VARCHAR NOT NULL, date DATE NOT NULL, "
    "bag VARCHAR, preset VARCHAR, run_dir VARCHAR, n_trees INTEGER, n_matched INTEGER, "
    "n_new INTEGER, n_missing INTEGER, n_replanted INTEGER, align_method VARCHAR, "
    "align_dx DOUBLE, align_dy DOUBLE, align_rotation_deg DOUBLE, align_rms_m DOUBLE, "
    "ingested_at TIMESTAMP, metrics JSON",
    # One row per tree the orchard ever had; status: present, missing (not seen where the
    # last session looked), removed (replaced by a replanted tree).
    "trees": "tree_id BIGINT PRIMARY KEY, orchard VARCHAR NOT NULL, x DOUBLE, y DOUBLE, "
    "lat DOUBLE, lon DOUBLE, row INTEGER, label VARCHAR, first_session VARCHAR, "
    "last_seen VARCHAR, status VARCHAR, replaces BIGINT",
    # One row per tree seen in a session; kind: matched, new, replanted, found_again.
    "observations": "session_id VARCHAR, tree_id BIGINT, kind VARCHAR, segment INTEGER, "
    "label VARCHAR, row INTEGER, x DOUBLE, y DOUBLE, x_session DOUBLE, "
    "y_session DOUBLE, lat DOUBLE, lon DOUBLE, match_distance_m DOUBLE, "
    "n_points INTEGER, height_m DOUBLE, crown_diameter_m DOUBLE, flags VARCHAR, "
    "crown_contact DOUBLE, trunk_flags VARCHAR, "
    "PRIMARY KEY (session_id, tree_id)",
    # low_m3 / high_m3: the volume interval, on the row of the method it bounds (the run's
    # recommended estimator, trees.csv volume_method); NULL on the other methods' rows.
    "volumes": "session_id VARCHAR, tree_id BIGINT, method VARCHAR, volume_m3 DOUBLE, "
    "low_m3 DOUBLE, high_m3 DOUBLE, interval_flags VARCHAR",
    "aerial": "session_id VARCHAR, tree_id BIGINT, diameter_m DOUBLE, sphere_volume_m3 DOUBLE, "
    "height_m DOUBLE, match_distance_m DOUBLE, crown_flag VARCHAR",
    # kind: new, missing, replanted (tree_id is the new tree, detail names the old one),
    # found_again (seen again after being missing).
    "events": "session_id VARCHAR, tree_id BIGINT, kind VARCHAR, detail VARCHAR",
}

# The per-tree table's aerial columns (canopy_kit.pipeline) and their names in the store.
AERIAL_COLUMNS = {
    "aerial_diameter_m": "diameter_m",
    "aerial_sphere_volume_m3": "sphere_volume_m3",
    "aerial_height_m": "height_m",
    "aerial_match_distance_m": "match_distance_m",
}
# The per-tree table's text columns of the aerial check (``ground_truth.crown_flags``).
AERIAL_TEXT_COLUMNS = {"aerial_crown_flag": "crown_flag"}

# Version 1 stored the interval's bounds and the void-free volume of the per-tree table as if
# they were volume methods ("low", "high", "without_voids"): they are not (volume_methods).
V1_PSEUDO_METHODS = ("low", "high", "without_voids")

# Each version's step to the next: (next version, statements); store.upgrade chains them.
UPGRADES: dict[str, tuple[str, list[str]]] = {
    "1": (
        "2",
        [
            "ALTER TABLE observations ADD COLUMN crown_contact DOUBLE",
            "ALTER TABLE observations ADD COLUMN trunk_flags VARCHAR",
            "ALTER TABLE volumes ADD COLUMN low_m3 DOUBLE",
            "ALTER TABLE volumes ADD COLUMN high_m3 DOUBLE",
            "ALTER TABLE volumes ADD COLUMN interval_flags VARCHAR",
            "ALTER TABLE aerial ADD COLUMN crown_flag VARCHAR",
            "DELETE FROM volumes WHERE method IN ("
            + ", ".join(f"'{m}'" for m in V1_PSEUDO_METHODS)
            + ")",
        ],
    )
}
