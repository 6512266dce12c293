"""The comparison report: one self-contained HTML page (images embedded), and the
terminal summary table."""

from __future__ import annotations

import base64
import html
from datetime import UTC, datetime

import cv2
import numpy as np

# (label, path in a run's metrics, format, better: +1 higher, -1 lower, 0 neither)
SUMMARY_ROWS = [
    ("classification: overall accuracy", "classification.overall_accuracy", "{:.3f}", 1),
    ("classification: mean class accuracy", "classification.mean_class_accuracy", "{:.3f}", 1),
    ("classification: building / other", "classification.building_accuracy", "{:.3f}", 1),
    ("footprint 2D: completeness", "footprint_2d.completeness", "{:.3f}", 1),
    ("footprint 2D: correctness", "footprint_2d.correctness", "{:.3f}", 1),
    ("footprint 2D: quality", "footprint_2d.quality", "{:.3f}", 1),
    ("buildings found / true", "footprint_2d.objects", "objects", 0),
    ("volume 3D: completeness", "volume_3d.completeness", "{:.3f}", 1),
    ("volume 3D: correctness", "volume_3d.correctness", "{:.3f}", 1),
    ("volume 3D: quality", "volume_3d.quality", "{:.3f}", 1),
    ("volume 3D within the tolerance: quality", "volume_3d_tolerant.quality", "{:.3f}", 1),
    ("height RMSE on buildings (m)", "height.rmse_m", "{:.2f}", -1),
    ("height RMSE on buildings, off walls (m)", "height.rmse_off_jumps_m", "{:.2f}", -1),
    ("... where both have a building (m)", "height.rmse_on_both_off_jumps_m", "{:.2f}", -1),
    ("... share of it on cells the run misses", "height.missed_share_off_jumps", "{:.2f}", -1),
    ("height MAE on buildings (m)", "height.mae_m", "{:.2f}", -1),
    ("building height error, median |%|", "buildings.height_error_pct_median", "{:.1f}", -1),
    ("building height error, mean |%|", "buildings.height_error_pct_mean", "{:.1f}", -1),
    ("roof type accuracy", "buildings.roof_type_accuracy", "{:.2f}", 1),
    ("roof plane angle, median (deg)", "roofs.plane_angle_median_deg", "{:.1f}", -1),
    ("outline edges within 2 deg of the facades", "regularity.edges_within_2deg", "{:.2f}", 1),
    ("roof-plane pairs within 2 deg of symmetric", "regularity.pairs_within_2deg", "{:.2f}", 1),
    ("mean surface distance (m)", "surface.mean_distance_m", "{:.2f}", -1),
    ("RMS surface distance (m)", "surface.rms_distance_m", "{:.2f}", -1),
    ("Hausdorff distance (m)", "surface.hausdorff_m", "{:.2f}", -1),
    ("faces, total", "complexity.faces_total", "{:d}", -1),
    ("faces per building, median", "complexity.faces_per_building_median", "{:.0f}", -1),
    ("watertight buildings", "complexity.watertight_fraction", "{:.0%}", 1),
    ("texture seam cost, graph cut", "texture.seam_cost", "{:.2f}", -1),
    ("texture seam cost, projective", "texture.seam_cost_projective", "{:.2f}", -1),
    ("texture seam cost, greedy cuts", "texture.seam_cost_greedy", "{:.2f}", -1),
    ("DSM RMSE, all cells (m)", "dsm.rmse_m", "{:.2f}", -1),
    ("DSM RMSE, off height jumps (m)", "dsm.rmse_off_jumps_m", "{:.2f}", -1),
    ("DSM median |error| (m)", "dsm.median_abs_m", "{:.3f}", -1),
    ("DSM valid cells", "dsm.valid_fraction", "{:.1%}", 1),
    ("ortho MAE (0-255)", "ortho.mae", "{:.1f}", -1),
    *[
        (f"LoD {lod}: RMS to the input mesh (m) / triangles", ("lods", lod), "lod", -1)
        for lod in ("0", "1.2", "1.3", "2.2")
    ],  # fmt: skip
    ("wall time (s)", "cost.wall_s", "{:.1f}", -1),
    ("peak memory (MiB)", "cost.peak_memory_mb", "{:.0f}", -1),
]

RUN_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2"]


def lookup(d: dict, path: str | tuple):
    """``d["a"]["b"]`` for ``path`` ``"a.b"`` (or ``("a", "b")``, for keys with a dot),
    None when absent."""
    for key in path.split(".") if isinstance(path, str) else path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def format_value(value, fmt: str) -> str:
    if value is None:
        return ""
    if fmt == "objects":
        return f"{value['found']} / {value['truth_buildings']}"
    if fmt == "lod":
        return f"{value['rms_to_mesh_m']:.2f} / {value['triangles']}"
    if fmt == "{:d}":
        return f"{int(value):d}"
    return fmt.format(value)


def summary_rows(runs: dict[str, dict]) -> list[tuple[str, list[str], set[int]]]:
    """Rows of the side-by-side table with at least one value: (label, cells, indices
    of the best runs, all of them when tied)."""
    out = []
    for label, path, fmt, better in SUMMARY_ROWS:
        values = [lookup(m, path) for m in runs.values()]
        if all(v is None for v in values):
            continue
        best: set[int] = set()
        nums = [(i, v) for i, v in enumerate(values) if isinstance(v, int | float)]
        if better and len(nums) > 1:
            top = (max if better > 0 else min)(v for _, v in nums)
            best = {i for i, v in nums if np.isclose(v, top, rtol=1e-9, atol=1e-12)}
        out.append((label, [format_value(v, fmt) for v in values], best))
    return out


def summary_text(runs: dict[str, dict]) -> str:
    """The side-by-side table as plain text for the terminal."""
    names = list(runs)
    rows = summary_rows(runs)
    width = max(len(r[0]) for r in rows) + 2 if rows else 10
    colw = max(12, *(len(n) + 2 for n in names))
    lines = [f"{'metric':<{width}}" + "".join(f"{n:>{colw}}" for n in names)]
    for label, cells, _ in rows:
        lines.append(f"{label:<{width}}" + "".join(f"{c or '-':>{colw}}" for c in cells))
    return "\n".join(lines)


def png_data_uri(rgb: np.ndarray) -> str:
    """An (H, W, 3) uint8 RGB image as a PNG data URI."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def bar_chart_svg(
    groups: list[str], series: dict[str, list[float | None]], unit: str, width: int = 900
) -> str:
    """Grouped bar chart as inline SVG: one group per label, one bar per series
    (signed values; None leaves a gap)."""
    vals = [abs(v) for s in series.values() for v in s if v is not None]
    if not groups or not vals:
        return ""
    top = max(vals) * 1.1 or 1.0
    h, pad_l, pad_b, pad_t = 260, 50, 40, 20
    mid = pad_t + (h - pad_t - pad_b) / 2
    scale = (h - pad_t - pad_b) / 2 / top
    gw = (width - pad_l - 10) / len(groups)
    bw = gw * 0.8 / max(len(series), 1)
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{h + 30}" '
        'font-family="sans-serif" font-size="11">',
        f'<line x1="{pad_l}" y1="{mid}" x2="{width - 10}" y2="{mid}" stroke="#444"/>',
    ]
    for tick in (-top / 1.1, 0.0, top / 1.1):
        y = mid - tick * scale
        parts.append(f'<text x="{pad_l - 4}" y="{y + 4:.1f}" text-anchor="end">{tick:.1f}</text>')
    parts.append(f'<text x="4" y="12">{html.escape(unit)}</text>')
    for gi, g in enumerate(groups):
        x0 = pad_l + gi * gw + gw * 0.1
        for si, (name, s) in enumerate(series.items()):
            v = s[gi]
            if v is None:
                continue
            y, bh = (mid - v * scale, v * scale) if v >= 0 else (mid, -v * scale)
            color = RUN_COLORS[si % len(RUN_COLORS)]
            parts.append(
                f'<rect x="{x0 + si * bw:.1f}" y="{y:.1f}" width="{bw * 0.9:.1f}" '
                f'height="{max(bh, 0.5):.1f}" fill="{color}"><title>{html.escape(name)} '
                f"{html.escape(g)}: {v:.2f}</title></rect>"
            )
        parts.append(
            f'<text x="{x0 + gw * 0.4:.1f}" y="{h - pad_b + 16}" text-anchor="middle">'
            f"{html.escape(g)}</text>"
        )
    for si, name in enumerate(series):
        x = pad_l + si * 160
        color = RUN_COLORS[si % len(RUN_COLORS)]
        parts.append(f'<rect x="{x}" y="{h + 8}" width="12" height="12" fill="{color}"/>')
        parts.append(f'<text x="{x + 16}" y="{h + 18}">{html.escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)


_CSS = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1500px}
h1{font-size:22px}h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:8px 0;font-size:13px}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
td.best{font-weight:bold;background:#e6f4e6}td.bad{background:#fbe3e3}
figure{display:inline-block;margin:4px;vertical-align:top}
figcaption{font-size:12px;color:#555;text-align:center}
img{border:1px solid #ddd}.note{color:#666;font-size:13px}
"""


def _table(header: list[str], rows: list[list[str]], classes: list[list[str]] | None = None) -> str:
    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for i, r in enumerate(rows):
        cells = []
        for j, c in enumerate(r):
            cls = classes[i][j] if classes else ""
            cells.append(
                f'<td class="{cls}">{html.escape(str(c))}</td>'
                if cls
                else f"<td>{html.escape(str(c))}</td>"
            )
        out.append("<tr>" + "".join(cells) + "</tr>")
    return "".join(out) + "</table>"


def _figures(items: list[tuple[np.ndarray, str]], width: int = 360) -> str:
    return "".join(
        f'<figure><img src="{png_data_uri(img)}" width="{width}" alt="{html.escape(cap)}">'
        f"<figcaption>{html.escape(cap)}</figcaption></figure>"
        for img, cap in items
    )


def report_html(
    *,
    runs: dict[str, dict],
    buildings: dict[str, list[dict]],
    truth_info: dict,
    truth_figures: list[tuple[np.ndarray, str]],
    run_figures: dict[str, list[tuple[np.ndarray, str]]],
    renders: list[tuple[np.ndarray, str]],
    max_error_m: float,
) -> str:
    """The whole report page.

    Parameters
    ----------
    runs : {run name: metrics}
    buildings : {run name: per-building rows}
    truth_info : what the truth is (shown as a list)
    truth_figures, renders : (RGB image, caption) pairs
    run_figures : {run name: (RGB image, caption) pairs}
    max_error_m : the red end of the error colour maps
    """
    names = list(runs)
    s = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>workbench compare</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>{len(names)} run{'s' if len(names) != 1 else ''} against the truth</h1>",
        f"<p class='note'>Made {datetime.now(UTC):%Y-%m-%d %H:%M} UTC by "
        "<code>workbench compare</code>. Every run is scored by the same functions on the "
        "truth's grid.</p><ul>",
    ]
    for k, v in truth_info.items():
        if isinstance(v, dict):
            v = ", ".join(
                f"{a} {b:g}" if isinstance(b, float) else f"{a} {b}" for a, b in v.items()
            )
        s.append(f"<li>{html.escape(k)}: {html.escape(str(v))}</li>")
    s.append("</ul>")

    s.append("<h2>Side by side</h2>")
    rows, classes = [], []
    for label, cells, best in summary_rows(runs):
        rows.append([label, *[c or "-" for c in cells]])
        classes.append(["", *["best" if i in best else "" for i in range(len(cells))]])
    s.append(_table(["metric", *names], rows, classes))
    s.append(
        "<p class='note'>Bold: the best run on that row. Height errors are over the true "
        "building cells; 3D measures use a vertical tolerance of "
        f"{_tolerance(runs)} m; a blank means the run or the truth has no data for it.</p>"
    )

    conf = [(n, m["classification"]) for n, m in runs.items() if "classification" in m]
    if conf:
        s.append("<h2>Classification (the super-pixel paper's Table 1)</h2>")
        classes_ = ["ground", "grass", "tree", "building"]
        for n, c in conf:
            mat = c.get("confusion")
            if not mat:
                continue
            s.append(f"<p><b>{html.escape(n)}</b>: rows truth, columns prediction (cells)</p>")
            s.append(
                _table(
                    ["truth \\ predicted", *classes_],
                    [[k, *row] for k, row in zip(classes_, mat, strict=True)],
                )
            )

    s.append("<h2>Pictures of the truth</h2>")
    s.append(_figures(truth_figures))
    s.append("<h2>Error maps</h2>")
    s.append(
        "<p class='note'>Footprints: green true positive, red false positive, blue false "
        f"negative. Height error: green 0 m, blue {max_error_m / 2:g} m, red {max_error_m:g} m "
        "or more (against the true buildings over the true ground).</p>"
    )
    for n in names:
        if run_figures.get(n):
            s.append(f"<h3>{html.escape(n)}</h3>" + _figures(run_figures[n]))

    if renders:
        s.append("<h2>Rendered models, same viewpoints</h2>")
        s.append(
            "<p class='note'>Ray-cast renders. Error-coloured renders show each face's "
            f"distance to the true buildings (green 0, blue {max_error_m / 2:g} m, red "
            f"{max_error_m:g} m or more).</p>"
        )
        s.append(_figures(renders, width=340))

    s.append(_buildings_section(buildings))
    s.append(_texture_section(runs, buildings))
    s.append(_cost_section(runs))
    s.append("</body></html>")
    return "\n".join(s)


def _tolerance(runs: dict[str, dict]) -> str:
    for m in runs.values():
        t = lookup(m, "volume_3d_tolerant.tolerance_m")
        if t is not None:
            return f"{t:g}"
    return "-"


def _buildings_section(buildings: dict[str, list[dict]]) -> str:
    names = [n for n, rows in buildings.items() if rows]
    if not names:
        return ""
    ids = sorted({r["id"] for n in names for r in buildings[n]})
    by = {n: {r["id"]: r for r in buildings[n]} for n in names}
    first = by[names[0]]
    s = ["<h2>Building by building</h2>"]
    series = {n: [by[n].get(i, {}).get("height_error_pct") for i in ids] for n in names}
    chart = bar_chart_svg([str(i) for i in ids], series, "height error, % of the true height")
    if chart:
        s.append(
            "<p>Per-building height error (the voxel paper's Fig. 13), signed: "
            "above the axis the model is too high.</p>" + chart
        )
    for n in names:
        header = ["id", "true roof", "true height (m)", "area (m²)", "covered"]
        header += ["model id", "roof", "height (m)", "height error %", "RMSE (m)"]
        header += ["plane angle (deg)", "faces"]
        rows, classes = [], []
        for i in ids:
            t, r = first.get(i, {}), by[n].get(i, {})
            roof, also = r.get("roof_type", ""), t.get("roof_type_true_also", [])
            true_roof = " or ".join([t["roof_type_true"], *also]) if "roof_type_true" in t else ""
            wrong = bool(roof and true_roof and roof not in (t["roof_type_true"], *also))
            rows.append(
                [
                    i,
                    true_roof,
                    _f(t.get("height_true_m"), "{:.2f}"),
                    _f(t.get("area_m2"), "{:.0f}"),
                    _f(r.get("covered_fraction"), "{:.0%}"),
                    r.get("model_id", ""),
                    roof,
                    _f(r.get("height_model_m"), "{:.2f}"),
                    _f(r.get("height_error_pct"), "{:+.1f}"),
                    _f(r.get("rmse_m"), "{:.2f}"),
                    _f(r.get("plane_angle_median_deg"), "{:.1f}"),
                    _f(r.get("faces"), "{:d}"),
                ]
            )
            big = abs(r.get("height_error_pct", 0.0)) > 5
            classes.append(
                ["", "", "", "", "", "", "bad" if wrong else "", "", "bad" if big else ""]
                + [""] * 3
            )
        s.append(f"<h3>{html.escape(n)}</h3>" + _table(header, rows, classes))
    s.append(
        "<p class='note'>Shaded: a roof type that differs from the truth, a height "
        "error above 5 %.</p>"
    )
    return "".join(s)


def _texture_section(runs: dict[str, dict], buildings: dict[str, list[dict]]) -> str:
    have = [n for n, m in runs.items() if "texture" in m]
    s = ["<h2>Texture seams</h2>"]
    if not have:
        s.append(
            "<p class='note'>No run reports seam costs (a textured model run writes "
            "<code>seam_cost</code> and <code>seam_cost_projective</code> in its "
            "model.json).</p>"
        )
        return "".join(s)
    rows = []
    for n in have:
        t = runs[n]["texture"]
        gc, pm = t.get("seam_cost"), t.get("seam_cost_projective")
        ratio = gc / pm if gc is not None and pm else None
        rows.append([n, _f(gc, "{:.2f}"), _f(pm, "{:.2f}"), _f(ratio, "{:.2f}")])
    s.append(
        "<p>Mean CIE Lab difference across surface-graph edges whose two sides take "
        "different images.</p>"
    )
    s.append(_table(["run", "graph cut", "projective mapping", "ratio"], rows))
    for n in have:
        ids = [str(r["id"]) for r in buildings.get(n, []) if "seam_cost" in r]
        series = {
            "graph cut": [r["seam_cost"] for r in buildings[n] if "seam_cost" in r],
            "projective": [r.get("seam_cost_projective") for r in buildings[n] if "seam_cost" in r],
        }
        chart = bar_chart_svg(ids, series, f"{n}: seam cost per building")
        if chart:
            s.append(chart)
    return "".join(s)


def _cost_section(runs: dict[str, dict]) -> str:
    have = {n: m["cost"] for n, m in runs.items() if "cost" in m}
    if not have:
        return ""
    rows = [
        [n, _f(c.get("wall_s"), "{:.1f}"), _f(c.get("peak_memory_mb"), "{:.0f}")]
        for n, c in have.items()
    ]
    return "<h2>Cost</h2>" + _table(["run", "wall time (s)", "peak memory (MiB)"], rows)


def _f(v, fmt: str) -> str:
    return "" if v is None else (f"{int(v):d}" if fmt == "{:d}" else fmt.format(v))
