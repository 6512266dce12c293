"""The super-pixel path's options: the one place their defaults are declared."""

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
class SuperpixelOptions:
    """Parameters of the super-pixel path (the paper's values where it gives them; the
    departures are listed in ``docs/superpixel.md``)."""

    sigma: float = option(2.0, "Quickshift kernel width", unit="px", flag="--quickshift-sigma")
    tau: float = option(8.0, "Quickshift largest link distance", unit="px",
                        flag="--quickshift-tau")  # fmt: skip
    ratio: float = option(1.0, "Quickshift's weight of colour against position", cli=False)
    segment_on: str | None = option(
        None, "what Quickshift segments: the ortho (the paper) or the DSM's surface normals",
        choices=("ortho", "relief"),
        auto="the relief for point-cloud fusions, whose ortho is one grey level per cell; "
        "the ortho otherwise",
    )  # fmt: skip
    height_weight: float = option(
        10.0, "Lab units per metre of the DSM's height segmented beside the ortho's colour, "
        "so that super-pixels do not straddle walls (0: the colour alone, as the paper; not "
        "used on the relief)", unit="Lab/m", kind="non_negative",
    )  # fmt: skip
    geometry_unary: bool = option(
        False, "weigh each super-pixel's plane-fit residual into the class CRF's unary, as "
        "tree and building residuals learned on the training strokes (default off, the "
        "paper's class likelihoods alone: no gain on the sample, whose crowns are smooth)",
    )  # fmt: skip
    omega_class: float | None = option(
        3.0, "weight of the class CRF's pairwise term (eq. 2), or auto: the best of 0.25-12 "
        "on the scene's training strokes", auto="auto",
    )  # fmt: skip
    omega_roof: float = option(5.0, "weight of the prototype CRF's pairwise term")
    opening_m: float = option(
        1.0, "radius of the opening that splits weakly touching buildings", unit="m",
        kind="non_negative", cli=False,
    )  # fmt: skip
    min_area_m2: float = option(20.0, "smallest building kept", unit="m2", flag="--min-area")
    ransac_threshold_m: float = option(0.15, "RANSAC inlier distance", unit="m", cli=False)
    ransac_iterations: int = option(200, "RANSAC iterations", cli=False)
    min_plane_points: int = option(
        6, "a super-pixel with fewer heights borrows its neighbours' for its hypothesis",
        cli=False,
    )  # fmt: skip
    prototype_tolerance_m: float = option(
        0.25, "affinity propagation's preference is minus this: a hypothesis joins another's "
        "prototype when that explains its points to about this distance", unit="m", cli=False,
    )  # fmt: skip
    prototype_reach: int = option(
        3, "rings of adjacent super-pixels around a prototype's exemplar that the prototype "
        "CRF offers it to: its cluster lies within one ring, the others let it grow",
        cli=False,
    )  # fmt: skip
    truncation_m: float = option(
        2.0, "point-to-plane distances are truncated here in the prototype unary, so that a "
        "tree over a roof does not decide its plane", unit="m", cli=False,
    )  # fmt: skip
    simplify_m: float | None = option(
        None, "tolerance of the roof polygon simplification", unit="m", flag="--simplify",
        auto="2.25 cells, which removes the cell staircase and little more",
    )  # fmt: skip
    regularise_deg: float = option(
        0.0, "put outline sides this close to the building's dominant directions on them, "
        "and square their corners (0: the outline as simplified)", unit="deg",
        kind="non_negative", flag="--regularise",
    )  # fmt: skip
    edge_reach_m: float | None = option(
        None, "unseen cells of a building this close to its seen cells stay in it",
        unit="m", kind="non_negative", flag="--edge-reach",
        auto="1 m for fused views, whose occlusions leave building edges unseen; 0 for clouds",
    )  # fmt: skip
    all_building: bool = option(
        False, "every cell with a height is building (clouds of single buildings, such as "
        "City3D's building instances, have no ground to classify against)",
    )  # fmt: skip
    seed: int = option(0, "seed of RANSAC and affinity propagation", kind="non_negative")
    block_m: float | None = block_side_option()
    block_margin_m: float = block_margin_option()
    workers: int | None = workers_option(", and Quickshift tiles segmented at once in threads")
