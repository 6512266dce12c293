"""PLY meshes with per-face attributes (class, building id), readable by Open3D.

Binary little-endian PLY: vertex x y z (float64), optional red green blue (uchar);
face vertex_indices (uchar count, int32) and any extra per-face int32/uchar
properties. Open3D and other tools read the geometry and ignore the extras.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterable
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
    with open(path, "wb") as f:
        f.write(_ply_header(len(vertices), len(triangles), vertex_colors is not None,
                            face_properties, comments))  # fmt: skip
        f.write(_vertex_records(vertices, vertex_colors).tobytes())
        f.write(_face_records(triangles, face_properties).tobytes())


def write_ply_pieces(
    path: str | os.PathLike,
    pieces: Callable[[], Iterable[MeshPiece]],
    n_vertices: int,
    n_triangles: int,
    *,
    colours: bool,
) -> None:
    """Write the pieces of a mesh as one binary PLY (what :func:`write_ply` writes of
    them put together), one piece in memory at a time.

    Parameters
    ----------
    pieces : callable
        Gives the pieces, (vertices, triangles, vertex colours or None) each, its
        triangles indexing its own vertices; called twice (vertices, then faces).
    n_vertices, n_triangles : int
        Their totals.
    colours : bool
        Whether the pieces have vertex colours.
    """
    with open(path, "wb") as f:
        f.write(_ply_header(n_vertices, n_triangles, colours, {}, None))
        for v, _, c in pieces():
            f.write(_vertex_records(v, c if colours else None).tobytes())
        offset = 0
        for v, t, _ in pieces():
            f.write(_face_records(np.asarray(t, np.int64) + offset, {}).tobytes())
            offset += len(v)


MeshPiece = tuple  # (vertices (V, 3), triangles (T, 3), vertex colours (V, 3) uint8 or None)


class PlyWriter:
    """A binary PLY (what :func:`write_ply` writes) written a piece at a time, for a mesh
    larger than memory: the vertices and faces go to two scratch files beside ``path``
    as they come, and :meth:`close` writes the header with their counts and copies them
    after it. The file appears whole or not at all: it is written beside ``path`` and
    moved into place; leaving the ``with`` block on an error removes the scratch files.

    Parameters
    ----------
    path : path-like
        The PLY to write.
    colours : bool
        Whether the vertices carry colours.
    comments : list of str, optional
        Header comment lines.
    """

    def __init__(self, path: str | os.PathLike, *, colours: bool,
                 comments: list[str] | None = None):  # fmt: skip
        self.path = Path(path)
        self.colours, self.comments = colours, comments
        self.n_vertices = self.n_triangles = 0
        self._scratch = [self.path.with_name(f".{self.path.name}.{part}.partial")
                         for part in ("vertices", "faces", "whole")]  # fmt: skip
        self._vertices = open(self._scratch[0], "wb")
        self._faces = open(self._scratch[1], "wb")

    def add_vertices(self, vertices: np.ndarray, colours: np.ndarray | None = None) -> int:
        """Append (V, 3) float positions (and (V, 3) uint8 colours); returns the index
        the first of them takes."""
        first = self.n_vertices
        self._vertices.write(_vertex_records(vertices, colours if self.colours else None)
                             .tobytes())  # fmt: skip
        self.n_vertices += len(vertices)
        return first

    def add_triangles(self, triangles: np.ndarray) -> None:
        """Append (T, 3) triangles on the indices of every vertex added so far."""
        self._faces.write(_face_records(np.asarray(triangles, np.int64), {}).tobytes())
        self.n_triangles += len(triangles)

    def close(self) -> None:
        """Write the PLY and remove the scratch files."""
        self._vertices.close()
        self._faces.close()
        whole = self._scratch[2]
        with open(whole, "wb") as out:
            out.write(_ply_header(self.n_vertices, self.n_triangles, self.colours, {},
                                  self.comments))  # fmt: skip
            for part in self._scratch[:2]:
                with open(part, "rb") as f:
                    shutil.copyfileobj(f, out, 16 << 20)
                part.unlink()
        whole.replace(self.path)

    def discard(self) -> None:
        """Close and remove the scratch files; ``path`` is left as it was."""
        self._vertices.close()
        self._faces.close()
        for part in self._scratch:
            part.unlink(missing_ok=True)

    def __enter__(self) -> PlyWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()


def _ply_header(n_vertices: int, n_triangles: int, colours: bool, face_properties: dict,
                comments: list[str] | None) -> bytes:  # fmt: skip
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment city-workbench",
        *(f"comment {c}" for c in comments or []),
        f"element vertex {n_vertices}",
        "property double x",
        "property double y",
        "property double z",
    ]
    if colours:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"element face {n_triangles}", "property list uchar int vertex_indices"]
    header += [f"property {_ply_type(a)[1]} {n}" for n, a in face_properties.items()]
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii")


def _ply_type(arr: np.ndarray) -> tuple[str, str]:
    return ("u1", "uchar") if arr.dtype == np.uint8 else ("<i4", "int")


def _vertex_records(vertices: np.ndarray, vertex_colors: np.ndarray | None) -> np.ndarray:
    vfields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if vertex_colors is not None:
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(len(vertices), dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = np.asarray(vertices).T
    if vertex_colors is not None:
        vrec["red"], vrec["green"], vrec["blue"] = np.asarray(vertex_colors, np.uint8).T
    return vrec


def _face_records(triangles: np.ndarray, face_properties: dict) -> np.ndarray:
    ffields = [("n", "u1"), ("v", "<i4", (3,))]
    ffields += [(name, _ply_type(arr)[0]) for name, arr in face_properties.items()]
    frec = np.empty(len(triangles), dtype=ffields)
    frec["n"] = 3
    frec["v"] = triangles
    for name, arr in face_properties.items():
        frec[name] = arr
    return frec


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
    write_obj_pieces(path, lambda: [(vertices, triangles, vertex_colors)], len(triangles),
                     material=material, mtllib=mtllib, uvs=uvs)  # fmt: skip


def write_obj_pieces(
    path: str | os.PathLike,
    pieces: Callable[[], Iterable[MeshPiece]],
    n_triangles: int,
    *,
    material: str | list[tuple[str, int]] | None = None,
    mtllib: str | None = None,
    uvs: np.ndarray | Callable[[], Iterable[np.ndarray]] | None = None,
) -> None:
    """Write the pieces of a mesh as one OBJ (what :func:`write_obj` writes of them put
    together), one piece and at most ``OBJ_CHUNK`` of its rows formatted at a time.
    ``pieces`` is as for :func:`write_ply_pieces`; the vertices are coloured when the
    pieces' colours are not None. ``uvs``: every triangle's corners' texture coordinates
    (T, 3, 2), or a function that yields them piece by piece (a city's scene would hold
    48 bytes a triangle otherwise)."""
    with open(path, "w") as f:
        for text in _obj_chunks(pieces, n_triangles, material, mtllib, uvs):
            f.write(text)


# rows of an array formatted at once by write_obj: a city's ground of 1.5 M vertices as
# one list of lines took some 500 MB
OBJ_CHUNK = 65536


def _rows(pattern: str, values: np.ndarray) -> str:
    """``pattern`` (one row, its newline included) formatted with each row of ``values``
    (N, k), as one string: one ``%`` over the chunk's numbers, 2-3 times faster than a
    formatted string a row (the city's ground and scene OBJ: 3.5 s)."""
    return (pattern * len(values)) % tuple(values.ravel().tolist())


def _obj_chunks(pieces, n_triangles, material, mtllib, uvs):
    """:func:`write_obj_pieces`'s text, at most ``OBJ_CHUNK`` rows at a time."""
    yield "# city-workbench\n" + (f"mtllib {mtllib}\n" if mtllib else "")
    for vertices, _, colours in pieces():
        vertices = np.asarray(vertices, np.float64)
        c = None if colours is None else np.asarray(colours, np.float64) / 255.0
        for i in range(0, len(vertices), OBJ_CHUNK):
            v = vertices[i : i + OBJ_CHUNK]
            if c is None:
                yield _rows("v %.3f %.3f %.3f\n", v)
            else:
                yield _rows("v %.3f %.3f %.3f %.3f %.3f %.3f\n",
                            np.hstack([v, c[i : i + OBJ_CHUNK]]))  # fmt: skip
    if uvs is not None:
        for part in uvs() if callable(uvs) else [uvs]:
            uv = np.asarray(part, np.float64).reshape(-1, 2)
            for i in range(0, len(uv), OBJ_CHUNK):
                yield _rows("vt %.6f %.6f\n", uv[i : i + OBJ_CHUNK])
    runs = [(material, n_triangles)] if isinstance(material, str) else material
    rows = _TriangleRows(pieces)
    for name, count in runs or [(None, n_triangles)]:
        if name:
            yield f"usemtl {name}\n"
        for first, corners in rows.take(count):
            if uvs is None:
                yield _rows("f %d %d %d\n", corners)
            else:  # each corner with its own texture coordinate, 3 k + 1.. of triangle k
                k = 3 * np.arange(first, first + len(corners), dtype=np.int64)[:, None]
                both = np.stack([corners, k + np.arange(1, 4)], axis=2).reshape(-1, 6)
                yield _rows("f %d/%d %d/%d %d/%d\n", both)


class _TriangleRows:
    """The pieces' triangles as one run of OBJ corners (1-based, offset by the vertices
    of the pieces before), taken in consecutive runs of at most ``OBJ_CHUNK`` rows."""

    def __init__(self, pieces):
        self._chunks = self._stream(pieces)
        self._left = np.zeros((0, 3), np.int64)
        self.first = 0  # the global index of the next triangle

    @staticmethod
    def _stream(pieces):
        offset = 1
        for v, t, _ in pieces():
            t = np.asarray(t, np.int64)
            for i in range(0, len(t), OBJ_CHUNK):
                yield t[i : i + OBJ_CHUNK] + offset
            offset += len(v)

    def take(self, n: int):
        """Yields (index of the first triangle, its corners (m, 3)) up to ``n`` rows."""
        while n > 0:
            if not len(self._left):
                self._left = next(self._chunks, None)
                if self._left is None:  # fewer triangles than asked for
                    self._left = np.zeros((0, 3), np.int64)
                    return
            rows, self._left = self._left[:n], self._left[n:]
            yield self.first, rows
            self.first += len(rows)
            n -= len(rows)


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
