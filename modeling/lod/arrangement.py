"""Shape labelling on the segments' arrangement (the LOD paper, section 5.4, eq. 9-11):
the regularised segments slice the building into faces; an MRF on the faces' adjacency
graph gives each face a roof plane."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage as ndi

from workbench.graph_cuts import alpha_expansion


def arrangement_faces(mask: np.ndarray, segments: np.ndarray, extend: float) -> np.ndarray:
    """(h, w) int face ids 1.. of ``mask`` sliced by ``segments`` ((S, 4) in cells, each
    drawn extended by ``extend`` cells at both ends), 0 outside; the cells under a
    segment go to the nearest face.

    The arrangement is drawn on the grid the heights live on: a face is a 4-connected
    piece of the building between the segments' lines.
    """
    barrier = np.zeros(mask.shape, np.uint8)
    for x0, y0, x1, y1 in segments:
        d = np.array([x1 - x0, y1 - y0])
        n = np.hypot(*d)
        if n < 1e-9:
            continue
        e = d / n * extend
        p = (int(round(x0 - e[0])), int(round(y0 - e[1])))
        q = (int(round(x1 + e[0])), int(round(y1 + e[1])))
        cv2.line(barrier, p, q, 1, 1, lineType=cv2.LINE_4)
    open_cells = mask & (barrier == 0)
    faces, _ = ndi.label(open_cells)
    if faces.max() == 0:
        return mask.astype(np.int32)
    _, (r, c) = ndi.distance_transform_edt(faces == 0, return_indices=True)
    return np.where(mask, faces[r, c], 0).astype(np.int32)


def face_graph(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adjacent face pairs (E, 2) (ids from 0) and the cell edges they share (E,)."""
    pairs = []
    for a, b in ((faces[:, :-1], faces[:, 1:]), (faces[:-1], faces[1:])):
        sel = (a != b) & (a > 0) & (b > 0)
        pairs.append(np.sort(np.column_stack([a[sel], b[sel]]), axis=1))
    p = np.concatenate(pairs) - 1
    if not len(p):
        return np.zeros((0, 2), np.int64), np.zeros(0)
    uniq, counts = np.unique(p, axis=0, return_counts=True)
    return uniq.astype(np.int64), counts.astype(np.float64)


def planarity_weight(points_a: np.ndarray, points_b: np.ndarray) -> float:
    """1 - 3 lambda_0 / (lambda_0 + lambda_1 + lambda_2) of the two faces' points (eq.
    10): 1 when they lie in one plane, 0 when they are isotropic."""
    P = np.vstack([points_a, points_b])
    if len(P) < 4:
        return 0.0
    lam = np.linalg.eigvalsh(np.cov(P.T))
    return float(max(0.0, 1.0 - 3.0 * lam[0] / max(lam.sum(), 1e-12)))


def label_faces(
    faces: np.ndarray,
    points: np.ndarray,
    planes: np.ndarray,
    beta: float,
    gsd: float,
    levels: np.ndarray | None = None,
) -> np.ndarray:
    """Each face's plane by alpha-expansion on eq. 11: D_f(P) the sum over the face's
    cells of their distance to P (eq. 9), V the shared edge length times the pair's
    planarity (eq. 10).

    Parameters
    ----------
    faces : (h, w) int face ids 1..F, 0 outside
    points : (h, w, 3) each cell as a point (x, y, DSM height), NaN height unknown
    planes : (P, 4)
    levels : (h, w) bool, optional
        Cells whose height is a level no view saw (the lowest of the building's heights
        around them), not a point on a surface: their distance to P is the vertical one.
        Eq. 9's distance to a steep plane is its vertical one times the cosine of its
        tilt: a mansard's 70-degree lower face, carried over a hidden rim, stood within
        a third of its rise there and took it (seed 5: its rim rose to 22 m over a
        roof of 10).

    Returns
    -------
    (F,) plane index of each face (faces with no known height take their neighbours').
    """
    F = int(faces.max())
    ids = faces.ravel()
    X = points.reshape(-1, 3)
    known = (ids > 0) & np.isfinite(X[:, 2])
    dist = np.abs(X[known] @ planes[:, :3].T + planes[:, 3])  # (n, P)
    if levels is not None:
        level = levels.ravel()[known]
        dist[level] /= np.maximum(np.abs(planes[:, 2]), 1e-6)
    unary = np.zeros((F, len(planes)))
    np.add.at(unary, ids[known] - 1, dist)
    edges, shared = face_graph(faces)
    by_face = [X[known][ids[known] == f + 1] for f in range(F)]
    weights = np.array([shared[e] * gsd * planarity_weight(by_face[a], by_face[b])
                        for e, (a, b) in enumerate(edges)])  # fmt: skip
    return alpha_expansion(unary, edges, weights, beta)
