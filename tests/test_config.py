"""Typed config: presets load with the paper's values, unknown keys and wrong types are
errors naming the key, and the config written next to a result reads back identically."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from canopy_kit.config import (
    MappingConfig,
    PipelineConfig,
    from_dict,
    load_preset,
    preset_names,
    write_config,
)
from canopy_kit.errors import ConfigError, InputError


def test_shipped_presets() -> None:
    assert {"pistachio", "almond"} <= set(preset_names())


@pytest.mark.parametrize("name", preset_names())
def test_every_preset_loads(name: str) -> None:
    config = load_preset(name)
    assert isinstance(config, PipelineConfig)
    assert config.name == name


def test_presets_follow_the_paper() -> None:
    pistachio, almond = load_preset("pistachio"), load_preset("almond")
    # §II.C: DBSCAN eps 0.8 m, N_min 1300; spectral split above 45,000 points, k = 10; alpha 0.9 m
    assert pistachio.segment.method == "dbscan"
    assert pistachio.segment.params == {"eps": 0.8, "min_samples": 1300}
    assert almond.segment.method == "dbscan_spectral"
    assert almond.segment.params["max_cluster_size"] == 45_000
    assert almond.segment.params["n_neighbors"] == 10
    for config in (pistachio, almond):
        assert config.volume.params["alpha_shape"]["alpha"] == 0.9
        assert config.preprocess.voxel_size == 0.1
        assert config.preprocess.voxelize in ("before_clustering", "after_clustering")


def test_defaults_fill_what_a_preset_leaves_out() -> None:
    config = load_preset("pistachio")
    assert config.mapping.max_range == MappingConfig().max_range
    assert isinstance(config.preprocess.voxel_size, float)


@pytest.mark.parametrize(
    ("data", "where", "key"),
    [
        ({"sede": 1}, "config", "sede"),
        ({"mapping": {"voxel": 0.1}}, "config.mapping", "voxel"),
        ({"preprocess": {"voxel_size": 0.1, "ransac": 1}}, "config.preprocess", "ransac"),
    ],
)
def test_unknown_key_is_named(data: dict, where: str, key: str) -> None:
    with pytest.raises(ConfigError) as err:
        from_dict(PipelineConfig, data)
    message = str(err.value)
    assert message.startswith(f"{where}: unknown key {key!r}")
    assert "known keys:" in message


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({"seed": "zero"}, "config.seed: expected an integer, got 'zero'"),
        ({"seed": True}, "config.seed: expected an integer, got True"),
        ({"seed": 1.5}, "config.seed: expected an integer, got 1.5"),
        ({"preprocess": {"voxel_size": "0.1"}}, "config.preprocess.voxel_size: expected a number"),
        ({"mapping": {"deskew": 1}}, "config.mapping.deskew: expected true or false, got 1"),
        (
            {"preprocess": {"voxelize": "never"}},
            "config.preprocess.voxelize: 'never' is not one of",
        ),
        ({"volume": {"methods": "alpha_shape"}}, "config.volume.methods: expected a list"),
        (
            {"volume": {"methods": ["alpha_shape", 3]}},
            "config.volume.methods[1]: expected a string",
        ),
        ({"mapping": 5}, "config.mapping: expected a table"),
    ],
)
def test_wrong_type_is_named(data: dict, fragment: str) -> None:
    with pytest.raises(ConfigError) as err:
        from_dict(PipelineConfig, data)
    assert fragment in str(err.value)


def test_integer_is_accepted_for_a_float() -> None:
    config = from_dict(PipelineConfig, {"preprocess": {"voxel_size": 1}})
    assert config.preprocess.voxel_size == 1.0 and isinstance(config.preprocess.voxel_size, float)


def test_overrides_merge_into_a_preset() -> None:
    config = load_preset("almond", overrides={"segment": {"params": {"eps": 0.6}}, "seed": 3})
    assert config.seed == 3
    assert config.segment.params["eps"] == 0.6
    assert config.segment.params["min_samples"] == 1300  # untouched neighbours survive
    with pytest.raises(ConfigError, match="preset 'almond'.*unknown key 'colour'"):
        load_preset("almond", overrides={"colour": "red"})


def test_another_method_starts_from_its_own_defaults() -> None:
    """The preset's segment.params belong to its method: overriding the method (``segment
    --method``) drops them in the loader; params given with it are that method's."""
    other = load_preset("almond", overrides={"segment": {"method": "adaptive"}})
    assert other.segment.method == "adaptive" and other.segment.params == {}
    same = load_preset("almond", overrides={"segment": {"method": "dbscan_spectral"}})
    assert same.segment.params == load_preset("almond").segment.params
    given = load_preset(
        "almond", overrides={"segment": {"method": "dbscan", "params": {"eps": 0.5}}}
    )
    assert given.segment.params == {"eps": 0.5}


def test_segment_cli_builds_its_config_through_the_loader() -> None:
    """``canopy-kit segment`` edits no config after loading it."""
    import inspect
    import re

    from canopy_kit.cli import segment

    assert not re.search(r"\bconfig(\.\w+)+\s*=[^=]", inspect.getsource(segment))


@pytest.mark.parametrize("name", ["pistachio", "almond"])
def test_write_config_round_trip(tmp_path: Path, name: str) -> None:
    config = load_preset(name, overrides={"mapping": {"pointcloud_topic": "/ouster/points"}})
    path = write_config(config, tmp_path / "results" / "config.toml")
    assert path.exists()
    assert tomllib.loads(path.read_text())["mapping"]["pointcloud_topic"] == "/ouster/points"
    assert load_preset(path) == config
    assert [p.name for p in path.parent.iterdir()] == ["config.toml"]  # no temporary left


def test_preset_file_errors_name_the_file(tmp_path: Path) -> None:
    bad_key = tmp_path / "mine.toml"
    bad_key.write_text('name = "mine"\n[segment]\nmethod = "dbscan"\nepsilon = 0.8\n')
    with pytest.raises(ConfigError) as err:
        load_preset(bad_key)
    assert str(bad_key) in str(err.value) and "unknown key 'epsilon'" in str(err.value)
    broken = tmp_path / "broken.toml"
    broken.write_text("name = \n")
    with pytest.raises(ConfigError, match="broken.toml: not valid TOML"):
        load_preset(broken)


def test_unknown_preset_lists_the_shipped_ones() -> None:
    with pytest.raises(ConfigError) as err:
        load_preset("walnut")
    assert (
        "'walnut'" in str(err.value)
        and "almond" in str(err.value)
        and "pistachio" in str(err.value)
    )
    assert isinstance(err.value, InputError)  # the CLI maps it to exit code 2


def test_one_settings_parser_for_cli_and_manifests():
    """--set items and a manifest's "a=1; b=2" text go through the same parser."""
    from canopy_kit.config import nested_settings, parse_settings

    parsed = parse_settings(["volume.voxel_size=0.05", "segment.method = dbscan", " a.b.c=[1, 2]"])
    assert parsed == {
        "volume": {"voxel_size": 0.05},
        "segment": {"method": "dbscan"},  # not TOML: kept as text
        "a": {"b": {"c": [1, 2]}},
    }
    assert parse_settings("x.y=1; ; x.z=true".split(";")) == {"x": {"y": 1, "z": True}}
    assert nested_settings({"m.t": 1, "n": {"o.p": 2}}) == {"m": {"t": 1}, "n": {"o": {"p": 2}}}
    with pytest.raises(ConfigError, match=r"row 3: set 'novalue': expected section.key=value"):
        parse_settings(["novalue"], "row 3: set")
