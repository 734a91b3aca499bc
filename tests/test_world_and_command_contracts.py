"""The contract of the two remaining plugin kinds (issue 49): every registered world model
and command passes the shipped conformance rules of ``canopy_kit.testing``, a world or a
command that breaks a rule fails with that rule's name, and both kinds are built by
``plugins.create`` like every other kind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import typer

from canopy_kit import plugins
from canopy_kit.evaluate.truth import WORLD_GROUP, load_world
from canopy_kit.sim.world import SimulatedWorld
from canopy_kit.testing.commands import check_command
from canopy_kit.testing.worlds import check_world


@pytest.mark.parametrize("name", plugins.names("commands"))
def test_every_registered_command_keeps_the_contract(name: str) -> None:
    check_command(plugins.create("commands", name))


def test_a_command_without_help_breaks_the_rules_it_breaks() -> None:
    def undocumented(count: int = typer.Option(1, "--count")) -> None:
        pass

    with pytest.raises(AssertionError) as err:
        check_command(undocumented)
    text = str(err.value)
    assert "says_what_it_does" in text and "every_parameter_documented" in text
    assert "'count'" in text and "help_runs" not in text


def test_a_documented_command_and_group_pass() -> None:
    def hello(name: str = typer.Argument(..., help="Whom to greet")) -> None:
        """Greet someone."""

    group = typer.Typer(help="Greetings.")
    group.command()(hello)
    check_command(hello)
    check_command(group)


def test_a_command_that_is_not_callable_is_named() -> None:
    with pytest.raises(AssertionError, match="is_a_command"):
        check_command("not a command")


def test_the_simulators_world_keeps_the_contract(tiny_pistachio) -> None:
    check_world(SimulatedWorld, tiny_pistachio.root)


def test_the_world_of_a_session_is_built_by_plugins_create(tiny_pistachio, monkeypatch) -> None:
    built = []
    create = plugins.create

    def counting(kind, name, params=None, **kw):
        built.append((kind, name, dict(params or {})))
        return create(kind, name, params, **kw)

    monkeypatch.setattr(plugins, "create", counting)
    world = load_world(tiny_pistachio.root)
    assert isinstance(world, SimulatedWorld)
    assert built == [(WORLD_GROUP, "sim_config.toml", {"session_dir": Path(tiny_pistachio.root)})]


class _ShiftedWorld(SimulatedWorld):
    """Foliage 5 m off its trees: what a generator with a frame bug would rebuild."""

    def complete_foliage(self, density: float = 50.0) -> dict[int, np.ndarray]:
        return {k: v + [5.0, 0.0, 0.0] for k, v in super().complete_foliage(density).items()}


class _ForgetfulWorld(SimulatedWorld):
    """An orchard missing its first tree."""

    def orchard(self):
        orchard = super().orchard()
        orchard.trees = orchard.trees[1:]
        return orchard


@pytest.mark.parametrize(
    ("world", "rule"),
    [(_ShiftedWorld, "foliage_lies_around_each_trunk"), (_ForgetfulWorld, "orchard_has_the_truth")],
)
def test_a_world_that_misplaces_its_trees_breaks_the_rule(tiny_pistachio, world, rule) -> None:
    with pytest.raises(AssertionError) as err:
        check_world(world, tiny_pistachio.root)
    assert rule in str(err.value)
    assert "scene_is_a_labelled_mesh" not in str(err.value)


def test_a_world_built_without_its_folder_is_a_config_error(tiny_pistachio) -> None:
    from canopy_kit.errors import ConfigError

    with pytest.raises(ConfigError, match="session_dir|world model"):
        plugins.create(WORLD_GROUP, "sim_config.toml", {"folder": tiny_pistachio.root})
