"""Fusion of calibrated views or LiDAR into ortho colour, height and class rasters.

The steps of Kluckner & Bischof (2010), sections 3 and 4, each in its module:
:mod:`~fusion.sigma_points` (features), :mod:`~fusion.classifier` (random forest),
:mod:`~fusion.observations` (lifting depth maps, visibility), :mod:`workbench.robust`
(median and vector median per cell), :mod:`~fusion.crowns` (the crowns' top surface,
not in the paper), :mod:`~fusion.ground` (DTM), and the drivers
:mod:`~fusion.scene_fusion` (views) and :mod:`~fusion.points` (LiDAR);
:mod:`~fusion.run` runs either and writes the run folder. The options are in
:mod:`~fusion.options`, which imports nothing heavy (the command line reads it).
"""

from .options import FusionOptions

__all__ = ["FusionOptions", "FusionResult", "fuse_points", "fuse_views"]


def __getattr__(name: str):  # the drivers import Open3D and OpenCV: only when asked for
    if name in ("FusionResult", "fuse_views"):
        from . import scene_fusion

        return getattr(scene_fusion, name)
    if name == "fuse_points":
        from .points import fuse_points

        return fuse_points
    raise AttributeError(f"module 'fusion' has no attribute {name!r}")
