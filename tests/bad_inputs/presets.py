"""Preset files a user might write: unknown keys, wrong types, values out of range."""

from __future__ import annotations

from pathlib import Path

GOOD = """name = "mine"
seed = 0
[mapping]
map_voxel_size = 0.05
[segment]
method = "dbscan"
params = { eps = 0.8, min_samples = 20 }
[volume]
methods = ["convex_hull", "alpha_shape"]
params = { alpha_shape = { alpha = 0.9 } }
"""

# id -> (replace this line of GOOD, with this text; "" appends)
EDITS: dict[str, tuple[str, str]] = {
    "unknown-key-top": ('name = "mine"', 'name = "mine"\ncolour = "red"'),
    "unknown-key-nested": ("map_voxel_size = 0.05", "voxel = 0.05"),
    "unknown-plugin": ('method = "dbscan"', 'method = "meanshift"'),
    "unknown-plugin-parameter": (
        "params = { eps = 0.8, min_samples = 20 }",
        "params = { epsilon = 0.8, min_samples = 20 }",
    ),
    "wrong-type-number": ("seed = 0", 'seed = "zero"'),
    "wrong-type-table": ('methods = ["convex_hull", "alpha_shape"]', 'methods = "alpha_shape"'),
    "negative-seed": ("seed = 0", "seed = -1"),
    "voxel-size-zero": ("", "[preprocess]\nvoxel_size = 0.0\n"),
    "stem-band-reversed": ("", "[preprocess]\nstem_band = [0.8, 0.3]\n"),
    "alpha-negative": (
        "params = { alpha_shape = { alpha = 0.9 } }",
        "params = { alpha_shape = { alpha = -0.9 } }",
    ),
    "range-limits-crossed": ("map_voxel_size = 0.05", "min_range = 70.0"),
    "not-toml": ('name = "mine"', "name = "),
}


def write_preset(folder: Path, case: str) -> Path:
    """The preset of ``case`` (a key of :data:`EDITS`) as a TOML file in ``folder``."""
    old, new = EDITS[case]
    text = GOOD + new if old == "" else GOOD.replace(old, new)
    assert text != GOOD
    path = folder / f"{case}.toml"
    path.write_text(text)
    return path
