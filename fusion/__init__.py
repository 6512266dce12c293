"""Fusion of calibrated views or LiDAR into ortho colour, height and class rasters.

The steps of Kluckner & Bischof (2010), sections 3 and 4, each in its module:
:mod:`~fusion.sigma_points` (features), :mod:`~fusion.classifier` (random forest),
:mod:`~fusion.observations` (lifting depth maps, visibility), :mod:`~fusion.robust`
(median and vector median per cell), :mod:`~fusion.crowns` (the crowns' top surface,
not in the paper), :mod:`~fusion.ground` (DTM), and the drivers
:mod:`~fusion.scene_fusion` (views) and :mod:`~fusion.points` (LiDAR).
"""

from .robust import group_median, vector_median
from .scene_fusion import FusionOptions, FusionResult, fuse_views
from .sigma_points import feature_cues, sigma_points

__all__ = [
    "FusionOptions",
    "FusionResult",
    "feature_cues",
    "fuse_views",
    "group_median",
    "sigma_points",
    "vector_median",
]
