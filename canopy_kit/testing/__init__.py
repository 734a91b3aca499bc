"""Conformance suite for every plugin kind, shipped with the library.

Modelled on scikit-learn's ``utils.estimator_checks``: every rule of a plugin contract is a
named check. ``check_reader``, ``check_segmenter``, ``check_volume_estimator``,
``check_world`` (with a session folder its generator wrote) and ``check_command`` run all of
a kind's rules on a plugin (a class, built with its defaults, or a configured instance) and
raise one AssertionError naming each broken rule; :func:`parametrize_with_checks` makes one
pytest test per (plugin, rule), choosing the rules by the plugin's kind::

    from canopy_kit.testing import parametrize_with_checks

    @parametrize_with_checks([MyReader, MySegmenter, MyVolume(margin=0.1)])
    def test_my_plugins(estimator, check):
        check(estimator)
"""

from canopy_kit.testing.commands import check_command, command_checks
from canopy_kit.testing.estimators import (
    Check,
    blobs,
    check_segmenter,
    check_volume_estimator,
    checks_for,
    coplanar,
    crown,
    parametrize_with_checks,
    segmenter_checks,
    unit_cube,
    volume_checks,
)
from canopy_kit.testing.readers import check_reader, reader_checks
from canopy_kit.testing.worlds import check_world, world_checks

__all__ = [
    "Check",
    "blobs",
    "check_command",
    "check_reader",
    "check_segmenter",
    "check_volume_estimator",
    "check_world",
    "checks_for",
    "command_checks",
    "coplanar",
    "crown",
    "parametrize_with_checks",
    "reader_checks",
    "segmenter_checks",
    "unit_cube",
    "volume_checks",
    "world_checks",
]
