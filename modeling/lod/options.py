"""The LOD path's options: the one place their defaults are declared."""

from __future__ import annotations

from dataclasses import dataclass

from workbench.options import (
    block_margin_option,
    block_side_option,
    comma_choices,
    documented,
    option,
    workers_option,
)

LODS = ("0", "1", "2")


@documented
@dataclass
class LodOptions:
    """Parameters of the LOD path (the LOD paper's values where it gives them: mu 1, three
    ground iterations, 200 boosting rounds, a collinear threshold of 0.5 m, beta 10; the
    departures, h_trunc among them, are listed in ``docs/lod.md``)."""

    lod: tuple[str, ...] = option(
        LODS, "levels of detail made: 0 the footprint, 1 each face at its plane's mean "
        "height, 2 each face on its roof plane; the highest is each building's mesh, the "
        "others go into model.city.json", parse=comma_choices(LODS), metavar="0,1,2",
    )  # fmt: skip
    h_trunc: float = option(
        2.5, "midpoint of the logistic normalised height (eq. 3), below a one-storey "
        "building (the paper's 3 m put a 3-3.5 m building at h_n 0.5-0.7)", unit="m",
    )  # fmt: skip
    mu: float = option(1.0, "weight of the labelling's smoothness (eq. 6)", kind="non_negative")
    colour_contrast: bool = option(
        True, "between two cells below --h-trunc, multiply the labelling's pairwise weight "
        "(eq. 5) by the ortho's colour contrast, so that ground and grass part at their "
        "colour edge (off: the paper's eq. 5)",
    )  # fmt: skip
    flat_colours: bool = option(
        True, "weigh ground against grass by each cell's ortho colour under Gaussian "
        "mixtures of the training strokes' colours, as the fusion does (with --labels)",
    )  # fmt: skip
    planar_objects: bool = option(
        True, "make building the objects labelled tree that a few roof planes explain, and "
        "roof faces joined to a crown, as the fusion does (a green roof's colour is a tree's)",
    )  # fmt: skip
    angle_threshold: float = option(
        10.0, "angle within which a normal counts for a facade or roof direction (eq. 7-8, "
        "ang_thre) and a segment is turned onto a facade direction", unit="deg",
    )  # fmt: skip
    beta: float = option(
        10.0, "weight of the face labelling's smoothness (eq. 11)", kind="non_negative"
    )  # fmt: skip
    collinear_m: float = option(
        0.5, "segments of one direction closer than this are merged into one line", unit="m"
    )  # fmt: skip
    ground_iterations: int = option(
        3, "MRF labellings, each re-estimating the ground height from the last's ground",
    )  # fmt: skip
    ground_block_m: float = option(
        50.0, "side of the blocks with one ground height each (the paper's block)", unit="m"
    )  # fmt: skip
    boost_rounds: int = option(200, "decision stumps of the tree classifier (eq. 1, T)")
    plane_inlier_m: float = option(
        0.3, "a cell belongs to a roof plane within this distance", unit="m"
    )  # fmt: skip
    min_plane_m2: float = option(4.0, "smallest roof plane detected", unit="m2")
    min_area_m2: float = option(20.0, "smallest building kept", unit="m2", flag="--min-area")
    outline_reach_m: float = option(
        1.0, "a building's outline may move this far from the labelling's edge to where its "
        "DSM's walls stand at half its eaves' height (0: the labelling's edge)", unit="m",
        kind="non_negative",
    )  # fmt: skip
    opening_m: float = option(
        1.0, "radius of the opening (then closing) of the building class", unit="m",
        kind="non_negative",
    )  # fmt: skip
    block_m: float | None = block_side_option()
    block_margin_m: float = block_margin_option()
    workers: int | None = workers_option()
    seed: int = option(0, "seed of the RANSACs and the classifier", kind="non_negative")
