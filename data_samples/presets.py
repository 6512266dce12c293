"""Presets of the synthetic city: sizes, flight and sensor parameters.

The flight follows the camera rig of the voxel paper: a grid of viewpoints, each
with one nadir camera and four oblique cameras tilted about 45 degrees towards
north, east, south and west.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


@dataclass(frozen=True)
class Preset:
    """Parameters of one synthetic city.

    Lengths in metres, angles in degrees, image sizes in pixels.
    """

    name: str
    size: float  # side of the square area of interest
    block: tuple[float, float]  # range of road spacing (block size)
    max_height: float  # tallest building above ground
    tall_fraction: float  # share of buildings that are tall flat/stepped blocks
    ground_cell: float  # size of the ground material cells (and terrain mesh in the area)
    gsd: float  # reference ortho GSD of truth/ and training labels (~1.3x the image GSD)
    image_size: tuple[int, int]  # width, height
    flying_height: float  # above the mean terrain
    focal_px: float  # nadir focal length
    oblique_focal_scale: float  # oblique focal length = focal_px * this
    oblique_tilt: float  # degrees off nadir
    grid: tuple[int, int]  # viewpoints along x and y
    spacing: tuple[float, float]  # viewpoint spacing along x and y
    terrain_slope: float = 0.02  # largest terrain gradient (0 for flat ground)
    terrain_relief: float = 1.0  # amplitude of gentle undulations
    depth_sigma: float = 0.15  # depth noise at the flying height
    depth_outliers: float = 0.02  # fraction of outlier depths
    depth_matching: bool = True  # False: depth maps are the renderer's true depth (floors)
    depth_round_edges: bool = True  # False: matched depth with sharp edges (floors)
    calibration_error_px: float = 0.5  # RMS reprojection error of the written poses
    attitude_jitter: float = 1.5  # degrees of random roll/pitch/yaw of the rig
    trees_per_hectare: float = 45.0
    parcel: tuple[float, float] = (14.0, 30.0)  # range of parcel widths along a street
    parks: float = 0.12  # share of blocks that are parks
    lots: float = 0.08  # share of blocks that are parking lots or bare soil

    def with_overrides(self, **kw) -> Preset:
        return replace(self, **kw)

    def to_dict(self) -> dict:
        return asdict(self)


# the overrides that make a preset's depth maps the renderer's true depth (floors)
TRUE_DEPTH = {"depth_matching": False, "depth_sigma": 0.0, "depth_outliers": 0.0}

PRESETS = {
    "tiny": Preset(
        name="tiny",
        size=64.0,
        block=(62.0, 70.0),
        max_height=22.0,
        tall_fraction=0.15,
        ground_cell=0.5,
        gsd=0.25,
        image_size=(640, 480),
        flying_height=60.0,
        focal_px=500.0,
        oblique_focal_scale=1.0,
        oblique_tilt=40.0,
        grid=(2, 2),
        spacing=(24.0, 20.0),
        parcel=(11.0, 17.0),
        parks=0.0,
        lots=0.0,
    ),
    "small": Preset(
        name="small",
        size=200.0,
        block=(55.0, 75.0),
        max_height=60.0,
        tall_fraction=0.12,
        ground_cell=0.5,
        gsd=0.25,
        image_size=(1024, 768),
        flying_height=115.0,
        focal_px=575.0,
        oblique_focal_scale=1.0,
        oblique_tilt=45.0,
        grid=(3, 3),
        spacing=(75.0, 55.0),
    ),
    "city": Preset(
        name="city",
        size=1000.0,
        block=(60.0, 110.0),
        max_height=60.0,
        tall_fraction=0.12,
        ground_cell=1.0,
        gsd=0.4,
        image_size=(1024, 768),
        flying_height=180.0,
        focal_px=500.0,
        oblique_focal_scale=1.0,
        oblique_tilt=45.0,
        grid=(9, 11),
        spacing=(130.0, 100.0),
    ),
}
