"""The voxel path (Garcia-Dorado, Demir & Aliaga 2013): photo-consistency proxies from
GIS footprints, textured by surface graph cuts.

``run_voxel`` (in :mod:`.path`) is the path; this module only registers it, and imports
nothing heavy so that the command line starts fast.
"""

from modeling.registry import Input, PathSpec

from .options import VoxelOptions

SPEC = PathSpec(
    name="voxel",
    help="photo-consistency voxel proxies from GIS footprints, graph-cut texture atlases",
    description="The voxel path (Garcia-Dorado, Demir & Aliaga 2013) on a scene's images: "
    "each footprint's over-estimated extrusion is voxelised, carved to the heights its views "
    "agree on, clustered into roof levels and meshed; surface graph cuts stitch the views "
    "into one texture atlas per building, and a ground cut with the proxies masked out "
    "textures the ground. Writes the run folder of every path (buildings/<id>.ply|.obj|.png, "
    "scene.ply|.obj, ground.obj|.png, dtm.tif, model.json, preview.png).",
    options=VoxelOptions,
    inputs=(
        Input("scene_dir", "scene folder (scene.json)", "SCENE"),
        Input(
            "footprints",
            "GeoJSON footprints with a height property (default: the scene's footprints)",
            "FILE",
            flag="--footprints",
        ),
        Input(
            "fusion_dir",
            "a fusion run: its DTM is the ground, its nDSM marks ground "
            "columns and places and grows flat roofs, its building mask stands in for "
            "missing footprints (default: a flat ground plane)",
            "FUSION_DIR",
            flag="--fusion",
        ),
    ),  # fmt: skip
    run="modeling.voxel.path:run_voxel",
    summary="modeling.voxel.path:summary_lines",
    tasks=True,
    check="modeling.voxel.inputs:check_inputs",
)

__all__ = ["SPEC", "VoxelOptions"]
