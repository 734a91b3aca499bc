"""Tables of the orchard store (DuckDB). Positions are metres in the orchard's own frame:
UTM (``epsg``) minus the orchard's origin, fixed by its first session."""

from __future__ import annotations

SCHEMA_VERSION = "1"

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
    "PRIMARY KEY (session_id, tree_id)",
    "volumes": "session_id VARCHAR, tree_id BIGINT, method VARCHAR, volume_m3 DOUBLE",
    "aerial": "session_id VARCHAR, tree_id BIGINT, diameter_m DOUBLE, sphere_volume_m3 DOUBLE, "
    "height_m DOUBLE, match_distance_m DOUBLE",
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
