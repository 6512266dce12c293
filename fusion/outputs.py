"""Writing a fusion run: GeoTIFFs, fusion.json and preview.png."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from workbench.imageio import write_rgb
from workbench.pictures import colorize_classes, colorize_height, contact_sheet
from workbench.raster import write_raster

from .classifier import CLASS_NAMES


def write_fusion(out: Path, result, crs, record: dict) -> None:
    """Write every product of a :class:`~fusion.scene_fusion.FusionResult` into ``out``."""
    g = result.grid
    write_raster(out / "ortho.tif", np.moveaxis(result.ortho, -1, 0), g, crs, nodata=None)
    write_raster(out / "dsm.tif", result.dsm, g, crs)
    write_raster(out / "dtm.tif", result.dtm, g, crs)
    write_raster(out / "ndsm.tif", result.ndsm, g, crs)
    write_raster(
        out / "class_prob.tif",
        result.class_prob.astype(np.float32),
        g,
        crs,
        descriptions=list(CLASS_NAMES),
    )
    write_raster(out / "class.tif", result.classes, g, crs, nodata=0)
    write_raster(
        out / "count.tif",
        result.count,
        g,
        crs,
        nodata=None,
        descriptions=["observations per cell (-1: interpolated small hole)"],
    )
    if result.normal is not None:
        write_raster(out / "normal.tif", result.normal, g, crs, descriptions=["nx", "ny", "nz"])
    (out / "fusion.json").write_text(json.dumps(record, indent=1, default=_jsonable) + "\n")
    write_rgb(
        out / "preview.png",
        contact_sheet(
            [
                [
                    (result.ortho, "fused ortho"),
                    (colorize_height(result.ndsm), "nDSM"),
                    (colorize_classes(result.classes), "classes"),
                ]
            ],
            height=360,
        ),
    )


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))
