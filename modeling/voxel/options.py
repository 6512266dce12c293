"""The voxel path's options: the one place their defaults are declared."""

from __future__ import annotations

from dataclasses import dataclass

from workbench.options import documented, option, workers_option


@documented
@dataclass
class VoxelOptions:
    """Parameters of the voxel path (defaults from the paper where it gives them; the
    departures are listed in ``docs/voxel.md``)."""

    voxel_m: float = option(1.0, "voxel size r", unit="m", flag="--voxel")
    subdivisions: int = option(4, "texels per voxel side on the surface graph (S)")
    cluster_error: float = option(
        0.3, "c_e: k-means stops when one more cluster lowers the error by less than this"
    )
    overlap_m: float = option(
        4.0, "width of the band where a graph cut may move a seam", unit="m", flag="--overlap"
    )
    refine_sweeps: int = option(
        2, "passes of expansion moves over the whole surface after the greedy cuts (0: the "
        "paper's greedy cuts alone)", kind="non_negative",
    )  # fmt: skip
    facing_weight: float = option(
        10.0, "what the refinement charges for a worse-facing view, per unit cosine",
        unit="Lab", kind="non_negative",
    )  # fmt: skip
    view_tolerance: float = option(
        0.01, "a building's texture takes the fewest views that face a sample of its texels "
        "within this mean cosine of what every view gives (0: every view, as in the paper)",
        kind="non_negative",
    )  # fmt: skip
    ring_m: float = option(4.0, "width of the building-ground ring cut", unit="m", flag="--ring")
    grow_m: float = option(
        1.5, "grow the GIS footprints by this much before voxelising", unit="m",
        kind="non_negative", flag="--grow",
    )  # fmt: skip
    height_weight: float = option(
        0.0, "how much eq. 3 favours higher voxels (0: not at all)", kind="non_negative",
        cli=False,
    )  # fmt: skip
    outlier_sigma: float = option(
        2.0, "columns whose minimum variance lies this many standard deviations above the "
        "mean are discarded", cli=False,
    )  # fmt: skip
    min_height_m: float = option(
        2.0, "roof levels lower than this above the ground are ground", unit="m", cli=False
    )
    normal_sigma: float = option(1.0, "sigma_n of eq. 4", unit="voxels", cli=False)
    simplify_m: float | None = option(
        None, "outline simplification of the proxy mesh", unit="m", cli=False,
        auto="a quarter voxel; 2.25 fine cells on pitched roofs",
    )  # fmt: skip
    footprint_scale: float = option(
        1.0, "scales the eq. 2 window (1: half the voxel's projected size)", cli=False
    )
    tie_tolerance: float = option(
        0.05, "how far above a column's minimum a higher voxel still ties with it, as a "
        "fraction of the spread up to the column's median", kind="non_negative", cli=False,
    )  # fmt: skip
    band_tolerance: float = option(
        0.1, "how far above a column's minimum a voxel still counts as consistent, as a "
        "fraction of the spread up to the column's median", kind="non_negative", cli=False,
    )  # fmt: skip
    consistency: str = option(
        "lab", "colour of the photo-consistency: CIE Lab (measured better on the sample "
        "city) or the paper's HSL hue and saturation", choices=("lab", "hs"),
    )  # fmt: skip
    keep_views: float = option(
        0.75, "fraction of a voxel's samples its variance keeps (those nearest its median)",
        cli=False,
    )  # fmt: skip
    min_view_fraction: float = option(
        0.3, "voxels seen by fewer views than this fraction of the building's median (and "
        "than 3) are unknown", cli=False,
    )  # fmt: skip
    fusion_ground: bool = option(
        True, "with --fusion, columns its nDSM puts on the ground are ground (off: "
        "photo-consistency alone decides the proxies' extent, as in the paper)",
    )  # fmt: skip
    pitched_roofs: bool = option(
        True, "with --fusion, fit roof planes to its heights where the flat levels leave a "
        "high height error (off: the paper's flat levels only)",
    )  # fmt: skip
    plane_tolerance_m: float = option(
        0.3, "RANSAC inlier distance of the pitched roofs' planes", unit="m", cli=False
    )
    plane_gain: float = option(
        0.5, "planes replace the flat levels when they bring the median absolute height "
        "error down to this fraction of the levels'", cli=False,
    )  # fmt: skip
    min_plane_m2: float = option(6.0, "smallest roof plane of a pitched roof", unit="m2", cli=False)
    fusion_flat_roofs: bool = option(
        True, "with --fusion, flat roof levels stand at its nDSM's height and grow over the "
        "empty columns beside them at that height (off: the photo-consistent height and "
        "extent, as in the paper)",
    )  # fmt: skip
    ground_gsd_m: float = option(0.5, "texel size of the ground texture", unit="m", cli=False)
    default_height_m: float = option(
        35.0, "height of footprints without one (the paper's zonal default)", unit="m",
        flag="--default-height",
    )  # fmt: skip
    ground_z: float | None = option(
        None, "height of the flat ground plane without --fusion or a scene DTM", unit="m",
        kind="any", auto="from the depth maps of the most downward-looking views",
    )  # fmt: skip
    seed: int = option(0, "random seed", kind="non_negative")
    workers: int | None = workers_option()
