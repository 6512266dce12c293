"""The fusion's options: the one place their defaults are declared."""

from __future__ import annotations

import os
from dataclasses import dataclass

from workbench.options import documented, option


@documented
@dataclass
class FusionOptions:
    """Parameters of :func:`~fusion.scene_fusion.fuse_views` and
    :func:`~fusion.points.fuse_points` (the paper's values where it gives them; the
    departures are listed in ``docs/fusion.md``)."""

    gsd: float | None = option(
        None, "cell size in the CRS's units", unit="m",
        auto="the scene's gsd, else the nadir view's; for clouds, the cell that holds one "
        "return on average at the cloud's density over the ground it covers",
    )  # fmt: skip
    fill_radius: float | None = option(
        None, "clouds: empty cells in gaps up to twice this wide inside the coverage (between "
        "scan lines) take the height, colour and class of the surface around them; larger "
        "voids (water, occlusions) and the outside stay empty",
        unit="m", kind="non_negative", auto="two cells",
    )  # fmt: skip
    bounds: tuple[float, float, float, float] | None = option(
        None, "area to fuse, world units (XMIN YMIN XMAX YMAX)", kind="any", nargs=4,
        auto="the scene's bounds",
    )  # fmt: skip
    tile: int = option(512, "cells per tile side", cli=False)
    block: float | None = option(
        None, "fuse blocks of this side one after another, each with a margin of the "
        "ground filter's largest window (80 m), and write their insides into windows of the "
        "rasters: the command's memory follows the block, not the area",
        unit="m", auto="the whole grid at once up to 4096 x 4096 cells (clouds: and 3 "
        "million returns), else blocks of 4096 cells (clouds: of about 3 million returns "
        "with their margins) less their margins",
    )  # fmt: skip
    tolerance: float = option(
        1.0, "visibility band behind the nearest surface of a cell", unit="m", cli=False
    )
    patch: int = option(11, "side of the feature patch around a pixel", unit="px", cli=False)
    n_trees: int = option(8, "trees of the per-view random forest", cli=False)
    max_depth: int = option(14, "depth of its trees", cli=False)
    samples_per_class: int = option(20000, "training samples per class", cli=False)
    label_split: float = option(
        1.0, "training pixels labelled tree or building must stand at least this high above "
        "the DTM, ground or grass below it; others are dropped", unit="m", kind="non_negative",
    )  # fmt: skip
    training_views: int = option(
        16, "views the training samples are drawn from (spread evenly)", cli=False
    )
    projections: int = option(8, "random directions of the vector median", cli=False)
    seed: int = option(0, "random seed", kind="non_negative")
    classifier: str | os.PathLike | None = option(
        None,
        "reuse a saved forest instead of training one",
        auto="train one",
        parse=str,
        metavar="FILE",
    )
    geometry_cues: bool = option(
        True, "give the per-view forest the fused surface's planarity and the spread of the "
        "heights the views see in each cell, beside colour and elevation (off: the "
        "paper's features)",
    )  # fmt: skip
    flat_colours: bool = option(
        True, "views with training strokes: weigh each cell's ground and grass "
        "probabilities by its ortho colour's likelihood under colour models of the ortho "
        "under the ground and the grass strokes (off: the forest's patches alone, the "
        "paper's)",
    )  # fmt: skip
    class_crf: float = option(
        8.0, "views: weight omega of the contrast-sensitive Potts model that makes "
        "class.tif's classes stop at the ortho's colour edges and the DSM's height jumps (0: "
        "the most probable class of each cell, the paper's, as for clouds and meshes); "
        "class_prob.tif keeps the confidences",
        kind="non_negative", metavar="OMEGA",
    )  # fmt: skip
    planar_objects: bool = option(
        True, "views and meshes: an object classed tree, a storey or more above the DTM, becomes "
        "building where a few planes explain most of its cells (a green roof), and so does a "
        "planar part of one that continues a building's roof (a shaded face beside a crown); "
        "off: the classes as the forest and the class CRF leave them",
    )  # fmt: skip
    free_space: bool = option(
        True, "views with depth maps: a cell not classed tree whose column a view sees past "
        "more than the tolerance below its height takes the height of its observations "
        "below that (the points of a wall seen edge-on), and an object the views see "
        "through at most of its cells becomes tree (a crown); off: the heights as fused",
    )  # fmt: skip
    raster_prior: bool = option(
        False, "multiply the views' class probabilities by those of a forest on the fused "
        "rasters (nDSM, slope, roughness, colour), trained on the synthetic city; not in the "
        "paper",
    )  # fmt: skip
    max_memory_fraction: float = option(
        0.5, "largest share of the machine's memory the fusion plans to use", cli=False
    )
    workers: int | None = option(
        None, "views and tiles processed at once: worker processes of a local Dask cluster "
        "(1: in this process; the products do not depend on it)",
        auto="every core",
    )  # fmt: skip
