"""The block path's options: the one place their defaults are declared."""

from __future__ import annotations

from dataclasses import dataclass

from workbench.options import (
    block_margin_option,
    block_side_option,
    documented,
    option,
    workers_option,
)


@documented
@dataclass
class BlocksOptions:
    """Parameters of the block path (the DEM-blocks paper's values where it gives them:
    alpha 3/2, the kernels' probabilities, the data-driven spread of 1 m, the stage
    switch at 5 % acceptance over 1,000 iterations; the departures are listed in
    ``docs/blocks.md``)."""

    alpha: float = option(
        1.5, "exponent of the likelihood's L-alpha distance between a block and the DSM "
        "(eq. 3): 2 is least squares, smaller is more robust to the DSM's outliers",
    )  # fmt: skip
    beta: float = option(
        5.0, "weight of the prior (eq. 4): what a pair of neighbouring joinable blocks with "
        "equal parameters earns against the likelihood", kind="non_negative",
    )  # fmt: skip
    form_cost: float = option(
        0.05, "share by which each parameter of a block's form beyond the first raises its "
        "likelihood energy (a prior on the model index; 0: the paper's energy): a form "
        "that nests a simpler one, as a mansard nests a hipped roof, must fit the DSM that "
        "much better", kind="non_negative",
    )  # fmt: skip
    iterations: int = option(
        2000, "RJMCMC iterations per support (a building of three supports runs three "
        "times as many); the temperature falls geometrically to 1e-4 of White's initial "
        "temperature over them",
    )  # fmt: skip
    seed: int = option(
        0, "seed of the sampler (each building draws from the seed and its id, so a model "
        "does not depend on the workers)", kind="non_negative",
    )  # fmt: skip
    step_m: float = option(
        1.5, "a height step of more than this between cells 0.5 m apart is a wall: the "
        "building's supports do not cross it (a multi-level building's tiers)", unit="m",
    )  # fmt: skip
    outline_reach_m: float = option(
        1.0, "a building's outline may move this far from the building class's edge to "
        "where its DSM's walls stand at half its eaves' height (0: the class's edge)",
        unit="m", kind="non_negative",
    )  # fmt: skip
    unseen_rim_m: float = option(
        0.25, "the outline may take in the unknown cells this close to a roof's known ones "
        "(a fusion of depth maps keeps no roof up to its wall: each view drops the "
        "pixels of a depth jump's ramp; 0: the known cells only)", unit="m",
        kind="non_negative",
    )  # fmt: skip
    wall_blur_m: float = option(
        0.25, "cells this close to the building's outline or on a step between its parts "
        "are left out of the likelihood: a DSM's walls are blurred over them (0 keeps "
        "every cell)", unit="m", kind="non_negative",
    )  # fmt: skip
    min_area_m2: float = option(20.0, "smallest building kept", unit="m2", flag="--min-area")
    min_part_m: float = option(
        3.0, "narrowest arm of a support's footprint prior, and of a part decomposed from "
        "a complex outline", unit="m",
    )  # fmt: skip
    opening_m: float = option(
        1.0, "radius of the opening that splits weakly touching buildings", unit="m",
        kind="non_negative", cli=False,
    )  # fmt: skip
    all_building: bool = option(
        False, "every cell with a height is building (clouds of single buildings, such as "
        "City3D's building instances, have no ground to segment against)",
    )  # fmt: skip
    block_m: float | None = block_side_option()
    block_margin_m: float = block_margin_option()
    workers: int | None = workers_option()
