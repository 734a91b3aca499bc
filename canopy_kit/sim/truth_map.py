"""Moved to :mod:`canopy_kit.evaluate.truth_map` (a reference map built from a session's data, not
from the simulator); these names stay here for code that imported them from the simulator."""

from canopy_kit.evaluate.truth import true_pose_interpolator
from canopy_kit.evaluate.truth_map import TruthMapping, truth_map, truth_mapping

__all__ = ["TruthMapping", "true_pose_interpolator", "truth_map", "truth_mapping"]
