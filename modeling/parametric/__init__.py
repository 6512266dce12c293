"""The parametric path (Karantzas & Paragios): a level set over colour and height, footprint
priors in competition, the five-parameter roof fitted to the DSM.

``run_parametric`` (in :mod:`.path`) is the path; this module only registers it, and
imports nothing heavy so that the command line starts fast.
"""

from modeling.registry import Input, PathSpec

from .options import ParametricOptions

SPEC = PathSpec(
    name="parametric",
    help="level-set segmentation, footprint priors in competition, five-parameter roofs",
    description="The variational path (Karantzas & Paragios 2009) on the rasters of "
    "`workbench fusion`: a level set over the ortho's colour and the DSM's height (eq. 1), "
    "footprint priors (rectangle, L, T, U, courtyard) registered to each segment and "
    "competing with an unknown-object label (eq. 2-4), and per wing the main height and "
    "the four angles of its roof planes fitted to the DSM (eq. 5-6, 11-12). Writes the run "
    "folder of every path (buildings/, scene.ply|.obj, ground, dtm.tif, model.json, "
    "preview.png) and segments.tif.",
    options=ParametricOptions,
    inputs=(
        Input("fusion_dir", "output of workbench fusion", "FUSION_DIR"),
        Input(
            "footprints",
            "building outlines that initialise the level set instead of the fusion's "
            "building probability (GeoJSON, GeoPackage, Shapefile, ...)",
            "FILE",
            flag="--footprints",
        ),
    ),  # fmt: skip
    run="modeling.parametric.path:run_parametric",
    summary="modeling.parametric.path:summary_lines",
    tasks=True,
    check="modeling.parametric.path:check_inputs",
)

__all__ = ["SPEC", "ParametricOptions"]
