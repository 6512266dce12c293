"""A binary PLY surface mesh read a slice or a selection of its records at a time.

A city's mesh does not fit in memory beside what is made of it (the 1 km² sample's: 38 M
triangles, 1.3 GB on disk; Open3D's arrays and ours took 5.4 GiB). A binary PLY whose
faces are all triangles has records of one size, so its vertices and faces are two
arrays on disk: each read maps the file (``np.memmap``), copies the records it asks for
and lets the mapping go, so that the process holds only what it copied.

Any other mesh (OBJ with its textures, ASCII PLY, polygons) is read whole by Open3D
(:func:`fusion.mesh_sampling.read_surface_mesh`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workbench.errors import InputError

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4",
    "uint32": "<u4", "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip
CHUNK = 1 << 20  # records read at once in a pass over the file


@dataclass
class PlySurface:
    """A binary little-endian PLY of triangles, read a part at a time.

    Attributes
    ----------
    path : Path
    n_vertices, n_triangles : int
    vertex_dtype, face_dtype : numpy dtype
        One record of each element (the face's list of three indices as a field of
        shape (3,)).
    vertex_offset, face_offset : int
        Bytes from the start of the file to each element.
    crs : rasterio CRS or None
        Set by the reader.
    lo, hi : (3,) float64
        The vertices' bounding box, world metres (set by :meth:`check_vertices`).
    """

    path: Path
    n_vertices: int
    n_triangles: int
    vertex_dtype: np.dtype
    face_dtype: np.dtype
    vertex_offset: int
    face_offset: int
    index_field: str
    crs: object = None
    lo: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hi: np.ndarray = field(default_factory=lambda: np.zeros(3))
    uvs = None  # textures come only with a mesh read whole
    textures: tuple = ()
    material = None

    @property
    def has_colours(self) -> bool:
        return {"red", "green", "blue"} <= set(self.vertex_dtype.names)

    def _records(self, offset: int, dtype: np.dtype, count: int, sel) -> np.ndarray:
        mapped = np.memmap(self.path, dtype=dtype, mode="r", offset=offset, shape=(count,))
        out = mapped[sel]  # indices give a copy, a slice a view: copied
        out = np.array(out) if isinstance(sel, slice) else np.asarray(out)
        del mapped  # the mapping goes: only the copy stays in memory
        return out

    def positions(self, sel) -> np.ndarray:
        """(N, 3) float64 world positions of the vertices ``sel`` (a slice or indices)."""
        return _xyz(self._records(self.vertex_offset, self.vertex_dtype, self.n_vertices, sel))

    def vertex_data(self, sel) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 3) float64 positions and (N, 3) uint8 colours (None without colours) of the
        vertices ``sel``, their records read once."""
        r = self._records(self.vertex_offset, self.vertex_dtype, self.n_vertices, sel)
        colours = (_uint8(np.column_stack([r["red"], r["green"], r["blue"]]))
                   if self.has_colours else None)  # fmt: skip
        return _xyz(r), colours

    def faces(self, sel) -> np.ndarray:
        """(N, 3) int64 vertex indices of the triangles ``sel`` (a slice or indices)."""
        r = self._records(self.face_offset, self.face_dtype, self.n_triangles, sel)
        if (r["n"] != 3).any():
            raise InputError(self.path, "faces", "a face of more or fewer than three "
                             "vertices: only triangle meshes are read")  # fmt: skip
        return r[self.index_field].astype(np.int64)

    def check_vertices(self) -> None:
        """Read the vertices once: their bounding box, and no NaN or infinite one.

        Raises
        ------
        InputError
            A vertex is not finite.
        """
        lo, hi, bad = np.full(3, np.inf), np.full(3, -np.inf), 0
        for s in range(0, self.n_vertices, CHUNK):
            p = self.positions(slice(s, s + CHUNK))
            ok = np.isfinite(p).all(axis=1)
            bad += int((~ok).sum())
            if ok.any():
                lo, hi = np.minimum(lo, p[ok].min(axis=0)), np.maximum(hi, p[ok].max(axis=0))
        if bad:
            raise InputError(self.path, "vertices", f"{bad} vertices are not finite (NaN)")
        self.lo, self.hi = lo, hi


def open_ply_surface(path: Path) -> PlySurface | None:
    """The PLY at ``path`` as a :class:`PlySurface`, or None when it is not one that can
    be read a part at a time (ASCII or big-endian, a list of vertex indices with a
    count other than uchar, elements other than vertex and face, a size that is not
    that of triangles only): Open3D reads those whole.

    Raises
    ------
    InputError
        A header that is not PLY's.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        return None
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, None, "not a PLY file (no 'ply' on its first line)")
        lines = []
        while True:
            line = f.readline()
            if not line:
                raise InputError(path, None, "truncated PLY header (no end_header)")
            text = line.decode("ascii", "replace").strip()
            if text == "end_header":
                break
            lines.append(text.split())
        start = f.tell()
    if ["format", "binary_little_endian", "1.0"] not in lines:
        return None
    elements: list[list] = []
    for parts in lines:
        if parts[0] == "element" and len(parts) == 3:
            elements.append([parts[1], int(parts[2]), [], None])
        elif parts[0] == "property" and elements:
            fields, name = elements[-1][2], parts[-1]
            if parts[1] == "list":
                if PLY_TYPES.get(parts[2]) != "u1" or parts[3] not in PLY_TYPES:
                    return None
                fields += [("n", "u1"), (name, PLY_TYPES[parts[3]], (3,))]
                elements[-1][3] = name
            elif parts[1] in PLY_TYPES:
                fields.append((name, PLY_TYPES[parts[1]]))
            else:
                return None
    if [e[0] for e in elements] != ["vertex", "face"] or elements[1][3] is None:
        return None
    (_, nv, vfields, _), (_, nt, ffields, index_field) = elements
    vdt, fdt = np.dtype(vfields), np.dtype(ffields)
    if not {"x", "y", "z"} <= set(vdt.names):
        raise InputError(path, "vertex", "no x, y and z properties")
    size, need = os.path.getsize(path), start + nv * vdt.itemsize + nt * fdt.itemsize
    if size < need:  # every face has three vertices or more: the file was cut short
        raise InputError(path, None, f"truncated: its header's {nv} vertices and {nt} "
                         f"faces need {need:,} bytes or more, the file has {size:,}")  # fmt: skip
    if size != need:
        return None  # polygons (faces of other sizes), or more than vertices and faces
    return PlySurface(path, nv, nt, vdt, fdt, start, start + nv * vdt.itemsize, index_field)


def _xyz(records: np.ndarray) -> np.ndarray:
    """(N, 3) float64 x, y, z of vertex records."""
    out = np.empty((len(records), 3))
    out[:, 0], out[:, 1], out[:, 2] = records["x"], records["y"], records["z"]
    return out


def _uint8(c: np.ndarray) -> np.ndarray:
    """Colours as uint8: floats are 0-1 (Open3D's, MeshLab's), integers 0-255."""
    if c.dtype == np.uint8:
        return c
    if c.dtype.kind == "f":
        return np.clip(c * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.clip(c, 0, 255).astype(np.uint8)
