"""PLY meshes with per-face attributes (class, building id), readable by Open3D.

Binary little-endian PLY: vertex x y z (float64), optional red green blue (uchar);
face vertex_indices (uchar count, int32) and any extra per-face int32/uchar
properties. Open3D and other tools read the geometry and ignore the extras.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def write_ply(
    path: str | os.PathLike,
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    vertex_colors: np.ndarray | None = None,
    face_properties: dict[str, np.ndarray] | None = None,
    comments: list[str] | None = None,
) -> None:
    """Write a triangle mesh (binary PLY, float64 positions).

    Parameters
    ----------
    vertices : (V, 3) float
        Positions, metres.
    triangles : (T, 3) int
        Vertex indices, counter-clockwise seen from outside.
    vertex_colors : (V, 3) uint8, optional
    face_properties : dict of name -> (T,) uint8 or int32 array, optional
    comments : list of str, optional
        Header comment lines (one line each, such as ``crs EPSG:32631``).
    """
    face_properties = face_properties or {}
    V, T = len(vertices), len(triangles)
    vfields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if vertex_colors is not None:
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(V, dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    if vertex_colors is not None:
        vrec["red"], vrec["green"], vrec["blue"] = np.asarray(vertex_colors, np.uint8).T
    ffields = [("n", "u1"), ("v", "<i4", (3,))]
    ptypes = {}
    for name, arr in face_properties.items():
        kind = "u1" if arr.dtype == np.uint8 else "<i4"
        ffields.append((name, kind))
        ptypes[name] = "uchar" if kind == "u1" else "int"
    frec = np.empty(T, dtype=ffields)
    frec["n"] = 3
    frec["v"] = triangles
    for name, arr in face_properties.items():
        frec[name] = arr
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment city-workbench",
        *(f"comment {c}" for c in comments or []),
        f"element vertex {V}",
        "property double x",
        "property double y",
        "property double z",
    ]
    if vertex_colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"element face {T}", "property list uchar int vertex_indices"]
    header += [f"property {ptypes[n]} {n}" for n in face_properties]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vrec.tobytes())
        f.write(frec.tobytes())


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Read a mesh written by :func:`write_ply`.

    Returns
    -------
    vertices : (V, 3) float64
    triangles : (T, 3) int32
    face_properties : dict of name -> (T,) array
    """
    with open(path, "rb") as f:
        lines = []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: truncated PLY header")
            line = line.decode("ascii").strip()
            lines.append(line)
            if line == "end_header":
                break
        body = f.read()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    elements, cur = [], None
    for line in lines:
        parts = line.split()
        if parts[0] == "element":
            cur = (parts[1], int(parts[2]), [])
            elements.append(cur)
        elif parts[0] == "property" and cur is not None:
            if parts[1] == "list":
                cur[2].append(("n", types[parts[2]]))
                cur[2].append((parts[4], types[parts[3]], (3,)))
            else:
                cur[2].append((parts[2], types[parts[1]]))
    out, offset = {}, 0
    for name, count, fields in elements:
        dt = np.dtype(fields)
        out[name] = np.frombuffer(body, dtype=dt, count=count, offset=offset)
        offset += dt.itemsize * count
    v = out["vertex"]
    vertices = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    f = out["face"]
    props = {n: np.array(f[n]) for n in f.dtype.names if n not in ("n", "vertex_indices")}
    return vertices, np.array(f["vertex_indices"], dtype=np.int32), props


def write_obj(
    path: str | os.PathLike,
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    vertex_colors: np.ndarray | None = None,
    material: str | list[tuple[str, int]] | None = None,
    mtllib: str | None = None,
    uvs: np.ndarray | None = None,
) -> None:
    """Write a triangle mesh as Wavefront OBJ (world metres, millimetre precision).

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
        Counter-clockwise seen from outside.
    vertex_colors : (V, 3) uint8, optional
        Written as the widely read ``v x y z r g b`` extension (0-1).
    material : str or list of (str, int), optional
        ``usemtl`` name of all triangles, or of consecutive runs of that many triangles.
    mtllib : str, optional
        The ``.mtl`` file (relative to the OBJ) that defines the materials.
    uvs : (T, 3, 2) float, optional
        Texture coordinates (u right, v up, 0-1) of every triangle corner.
    """
    with open(path, "w") as f:
        for lines in _obj_chunks(vertices, triangles, vertex_colors, material, mtllib, uvs):
            if lines:
                f.write("\n".join(lines) + "\n")


# lines formatted at once by write_obj: a city's ground of 1.5 M vertices as one list of
# lines took some 500 MB
OBJ_CHUNK = 65536


def _obj_chunks(vertices, triangles, vertex_colors, material, mtllib, uvs):
    """:func:`write_obj`'s lines, at most ``OBJ_CHUNK`` rows of an array at a time."""
    yield ["# city-workbench"] + ([f"mtllib {mtllib}"] if mtllib else [])
    vertices = np.asarray(vertices)
    c = None if vertex_colors is None else np.asarray(vertex_colors, np.float64) / 255.0
    for i in range(0, len(vertices), OBJ_CHUNK):
        # rows as Python numbers: iterating an array's rows is several times slower
        v = vertices[i : i + OBJ_CHUNK].tolist()
        if c is None:
            yield [f"v {x:.3f} {y:.3f} {z:.3f}" for x, y, z in v]
        else:
            yield [
                f"v {x:.3f} {y:.3f} {z:.3f} {r:.3f} {g:.3f} {b:.3f}"
                for (x, y, z), (r, g, b) in zip(v, c[i : i + OBJ_CHUNK].tolist(), strict=True)
            ]
    if uvs is not None:
        uv = np.asarray(uvs).reshape(-1, 2)
        for i in range(0, len(uv), OBJ_CHUNK):
            yield [f"vt {u:.6f} {v:.6f}" for u, v in uv[i : i + OBJ_CHUNK].tolist()]
    triangles = np.asarray(triangles, np.int64)
    n = len(triangles)
    runs = [(material, n)] if isinstance(material, str) else material or [(None, n)]
    start = 0
    for name, count in runs:
        if name:
            yield [f"usemtl {name}"]
        for i in range(start, start + count, OBJ_CHUNK):
            stop = min(i + OBJ_CHUNK, start + count)
            corners = (triangles[i:stop] + 1).tolist()
            if uvs is None:
                yield [f"f {a} {b} {c}" for a, b, c in corners]
            else:
                yield [
                    f"f {a}/{3 * k + 1} {b}/{3 * k + 2} {c}/{3 * k + 3}"
                    for k, (a, b, c) in enumerate(corners, start=i)
                ]
        start += count


def write_mtl(
    path: str | os.PathLike,
    materials: dict[str, tuple[int, int, int]],
    textures: dict[str, str] | None = None,
) -> None:
    """Write an ``.mtl`` of plain diffuse colours ``{name: (r, g, b) 0-255}``; a name
    in ``textures`` also gets that image (path relative to the .mtl) as ``map_Kd``."""
    lines = ["# city-workbench"]
    for name, rgb in materials.items():
        r, g, b = (v / 255.0 for v in rgb)
        lines += [f"newmtl {name}", f"Kd {r:.3f} {g:.3f} {b:.3f}", "Ka 0 0 0", "Ks 0 0 0"]
        if textures and name in textures:
            lines.append(f"map_Kd {textures[name]}")
        lines.append("")
    with open(path, "w") as f:
        f.write("\n".join(lines))


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a Wavefront OBJ's faces as triangles (polygons as fans) in double precision,
    with their texture coordinates: Open3D's OBJ reader keeps single precision, half a
    metre at UTM northings.

    Returns
    -------
    vertices : (V, 3) float64
    triangles : (T, 3) int64
    uvs : (T, 3, 2) float64, or None unless every face has texture coordinates
    """
    v, vt, tris, uv_idx = [], [], [], []
    with_uv = True
    for line in Path(path).read_text().splitlines():
        head, _, rest = line.partition(" ")
        if head == "v":
            v.append([float(x) for x in rest.split()[:3]])
        elif head == "vt":
            vt.append([float(x) for x in rest.split()[:2]])
        elif head == "f":
            corners = [c.split("/") for c in rest.split()]
            with_uv = with_uv and all(len(c) >= 2 and c[1] for c in corners)
            for k in range(1, len(corners) - 1):
                tri = (corners[0], corners[k], corners[k + 1])
                tris.append([int(c[0]) - 1 for c in tri])
                if with_uv:
                    uv_idx.append([int(c[1]) - 1 for c in tri])
    uvs = np.asarray(vt, np.float64)[np.asarray(uv_idx, np.int64)] if with_uv and tris else None
    return np.asarray(v, np.float64).reshape(-1, 3), np.asarray(tris, np.int64).reshape(-1, 3), uvs


def texture_of(obj_path: str | os.PathLike) -> Path | None:
    """The image (``map_Kd``) of the ``.mtl`` beside an OBJ, None when there is none."""
    mtl = Path(obj_path).with_suffix(".mtl")
    if not mtl.exists():
        return None
    maps = [line.split(None, 1)[1].strip() for line in mtl.read_text().splitlines()
            if line.startswith("map_Kd ")]  # fmt: skip
    return mtl.parent / maps[0] if maps else None
