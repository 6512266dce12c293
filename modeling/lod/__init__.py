"""The LOD path (the LOD paper, "LOD modeling of urban scenes from MVS meshes"): the
orthographic products of a mesh (or any fusion) labelled by an MRF, roof planes detected
with regularity, segments arranging each building into faces, and LOD0/1/2 models.

``run_lod`` (in :mod:`.path`) is the path; this module only registers it, and imports
nothing heavy so that the command line starts fast.
"""

from modeling.registry import Input, PathSpec

from .options import LodOptions

SPEC = PathSpec(
    name="lod",
    help="MRF labelling, regular roof planes, segment arrangements, LOD0/1/2 (LOD paper)",
    description="The LOD path (LOD modeling of urban scenes from MVS meshes) on the "
    "rasters of `workbench fusion` (best from a mesh: `fusion --mesh`, whose normal.tif it "
    "uses): a boosted tree probability (section 4.1), an MRF labelling into ground, grass, "
    "tree and building with the ground height re-estimated (eq. 3-6), facade directions "
    "by RANSAC (eq. 7), line segments from the ortho, the height map and the normal map "
    "regularised to them (section 5.2), roof planes detected along symmetric roof "
    "directions (eq. 8), an MRF assigning each face of the segments' arrangement a plane "
    "(eq. 9-11), and LOD0, LOD1 and LOD2 models. Writes the run folder of every path.",
    options=LodOptions,
    inputs=(
        Input("fusion_dir", "output of workbench fusion (--mesh for normal.tif)", "FUSION_DIR"),
        Input(
            "labels",
            "training strokes (class codes 1-4, 0 unlabelled; a scene's "
            "training/labels.tif) for the tree classifier; default: the fusion's tree "
            "probability",
            "LABELS.tif",
            flag="--labels",
        ),
    ),  # fmt: skip
    run="modeling.lod.path:run_lod",
    summary="modeling.lod.path:summary_lines",
    tasks=True,
    check="modeling.lod.path:check_inputs",
)

__all__ = ["SPEC", "LodOptions"]
