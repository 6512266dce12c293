"""The super-pixel path (Kluckner & Bischof 2010): Quickshift super-pixels on the fused
ortho, a class CRF, RANSAC roof-plane prototypes, a prototype CRF, LOD2 meshes.

``run_superpixel`` (in :mod:`.path`) is the path; this module only registers it, and
imports nothing heavy so that the command line starts fast.
"""

from modeling.registry import Input, PathSpec

from .options import SuperpixelOptions

SPEC = PathSpec(
    name="superpixel",
    help="Quickshift super-pixels, class CRF, RANSAC roof prototypes, LOD2 meshes",
    description="The super-pixel path (Kluckner & Bischof 2010) on the rasters of "
    "`workbench fusion`: Quickshift super-pixels on the ortho, a class CRF on them, RANSAC "
    "plane hypotheses clustered into roof prototypes by affinity propagation, a prototype "
    "CRF, and roof polygons lifted to their planes with walls to the DTM. Writes the run "
    "folder of every path (buildings/, scene.ply|.obj, ground, dtm.tif, model.json, "
    "preview.png) and class.tif, superpixels.tif.",
    options=SuperpixelOptions,
    inputs=(
        Input("fusion_dir", "output of workbench fusion", "FUSION_DIR"),
        Input(
            "truth",
            "record the paper's Table 1 rows (pixel, super-pixel, CRF) against "
            "SCENE/truth in model.json",
            "SCENE",
            flag="--truth",
        ),
    ),  # fmt: skip
    run="modeling.superpixel.path:run_superpixel",
    summary="modeling.superpixel.path:summary_lines",
    tasks=True,
    check="modeling.superpixel.path:check_inputs",
)

__all__ = ["SPEC", "SuperpixelOptions"]
