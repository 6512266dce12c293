"""The block path (Lafarge et al., the DEM-blocks paper): buildings as assemblies of
parametric 3D blocks on 2D supports, sampled by RJMCMC under simulated annealing.

``run_blocks`` (in :mod:`.path`) is the path; this module only registers it, and imports
nothing heavy so that the command line starts fast.
"""

from modeling.registry import Input, PathSpec

from .options import BlocksOptions

SPEC = PathSpec(
    name="blocks",
    help="2D supports, a library of parametric 3D blocks, RJMCMC with simulated annealing",
    description="The DEM-blocks path (Lafarge, Descombes, Zerubia & Pierrot-Deseilligny "
    "2008) on the DSM of `workbench fusion` (from images or from `--points`): per building "
    "2D supports (connected rectangles from the footprint priors of its height regions, "
    "or quadrilaterals from --supports), a block of the library on each (flat, shed, "
    "gable, hipped, half-hipped, pyramid, mansard, gambrel, semi-elliptic), chosen by "
    "RJMCMC with uniform, data-driven and regularisation jumps under simulated annealing "
    "of the L-alpha likelihood and the joinable prior (eq. 1-6). Writes the run folder of "
    "every path (buildings/, scene.ply|.obj, ground, dtm.tif, model.json, preview.png).",
    options=BlocksOptions,
    inputs=(
        Input("fusion_dir", "output of workbench fusion", "FUSION_DIR"),
        Input(
            "supports",
            "2D supports: convex quadrilaterals or triangles (GeoJSON, GeoPackage, "
            "Shapefile, ...), touching ones one building; default: extracted from the DSM",
            "FILE",
            flag="--supports",
        ),
    ),  # fmt: skip
    run="modeling.blocks.path:run_blocks",
    summary="modeling.blocks.path:summary_lines",
    tasks=True,
    check="modeling.blocks.path:check_inputs",
)

__all__ = ["SPEC", "BlocksOptions"]
