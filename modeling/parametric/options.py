"""The parametric path's options: the one place their defaults are declared."""

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

FAMILIES = ("rect", "L", "T", "U", "courtyard")


@documented
@dataclass
class ParametricOptions:
    """Parameters of the parametric path (the variational paper's values where it gives
    them: rho 1, lambda 0.95, mu 1, the height term's weight 0.85; the departures are
    listed in ``docs/parametric.md``)."""

    families: tuple[str, ...] = option(
        FAMILIES, "footprint priors in competition (comma-separated)",
        parse=comma_choices(FAMILIES), metavar="rect,L,T,U,courtyard",
    )  # fmt: skip
    mu: float = option(1.0, "weight of the shape-prior terms E_2D and E_3D (eq. 7)")
    rho: float = option(
        1.0, "weight of the labelling's boundary length (eq. 4): a prior with a longer "
        "outline must explain that many more cells", flag="--rho",
    )  # fmt: skip
    lambda_: float = option(
        0.95, "cost of the unknown-object label per cell (eq. 4): a segment that no prior "
        "explains better is left to the data term and not modelled (one the fusion classes "
        "building is always modelled)", flag="--lambda",
    )  # fmt: skip
    height_weight: float = option(
        0.85, "weight of the height's region term against the colour's (eq. 1's varrho)",
        kind="non_negative",
    )  # fmt: skip
    unseen_rim_m: float = option(
        0.25, "the height term reads the unknown cells this close to a known one at its "
        "height (a fusion of depth maps keeps no roof up to its wall: each view drops "
        "the pixels of a depth jump's ramp; 0: the known cells only)", unit="m",
        kind="non_negative",
    )  # fmt: skip
    outline_reach_m: float = option(
        1.0, "a segment that no prior explains is tried again on its outline where its "
        "DSM's walls stand at half its eaves' height, within this reach (the block "
        "path's; 0: not tried)", unit="m", kind="non_negative",
    )  # fmt: skip
    probability_weight: float = option(
        1.0, "weight of a third region term on the fusion's building probability, beside "
        "colour and height (0: the paper's two sources)", kind="non_negative",
    )  # fmt: skip
    length_weight: float = option(
        0.5, "weight of the level set's boundary length (eq. 1's first term)", unit="m",
        kind="non_negative", cli=False,
    )  # fmt: skip
    level_set_iterations: int = option(
        120, "gradient steps of the level set per round", cli=False,
    )  # fmt: skip
    rounds: int = option(
        2, "rounds of segmentation and prior registration (eq. 8 pulls the second round's "
        "level set towards the registered priors)",
    )  # fmt: skip
    min_area_m2: float = option(20.0, "smallest building kept", unit="m2", flag="--min-area")
    min_part_m: float = option(
        3.0, "narrowest wing of a footprint prior (a U's notch and a courtyard's hole may be "
        "narrower), and of a part decomposed from a complex outline", unit="m",
    )  # fmt: skip
    opening_m: float = option(
        1.0, "radius of the opening that splits weakly touching segments", unit="m",
        kind="non_negative", cli=False,
    )  # fmt: skip
    tier_step_m: float = option(
        1.5, "a part of the roof standing this far above the fitted roof, over at least the "
        "smallest part's area, is a part of its own (a multi-level building's upper tier)",
        unit="m",
    )  # fmt: skip
    planar_m: float = option(
        0.1, "a segment the fusion classes mostly tree is a building all the same when its "
        "fitted roof leaves a median residual under this on its cells: a planar roof is a "
        "roof whatever its colour (crowns leave 0.12 m and more, roofs 0.05 m)", unit="m",
        kind="non_negative",
    )  # fmt: skip
    robust_m: float = option(
        0.3, "scale of the robust loss of the roof fit (eq. 6): residuals beyond it, walls' "
        "cells and chimneys, weigh less", unit="m", cli=False,
    )  # fmt: skip
    all_building: bool = option(
        False, "every cell with a height is building, with no level set (clouds of single "
        "buildings, such as City3D's building instances, have no ground to segment against)",
    )  # fmt: skip
    block_m: float | None = block_side_option()
    block_margin_m: float = block_margin_option()
    workers: int | None = workers_option()
