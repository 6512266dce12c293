"""Surface graph cuts (the voxel paper, section 5.1-5.2).

The visible surface of a proxy is covered with texels of size r / S (the S x S sub-faces
of every voxel face); each texel is a vertex of the surface graph, joined to the texels
next to it on its face and across face borders. Every vertex takes the view that faces
it best; runs of vertices with the same view are patches; patches are stitched into the
largest one by minimum cuts of the seam cost of eq. 5 (PyMaxflow), one patch at a time;
then expansion moves over the whole graph move the seams the greedy order left where two
views disagree (:func:`refine_seams`, ours).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from workbench.graph_cuts import pairwise_cut
from workbench.texture_seams import ViewSamples, framed, hidden_from, seam_costs, seam_terms

_INF = 1e9


@dataclass
class Chart:
    """A planar, connected set of proxy triangles and its texel grid.

    Attributes
    ----------
    triangles : (T,) int
        Indices into the mesh's triangles.
    origin : (3,) float
        World point of texel corner (0, 0), metres.
    u, v, normal : (3,) float
        Unit axes of texel columns and rows, and the outward normal.
    shape : (rows, cols)
    visible : bool
        False for floors (faces looking down), which get no texels in the graph.
    """

    triangles: np.ndarray
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    shape: tuple[int, int]
    visible: bool


@dataclass
class SurfaceGraph:
    """Vertices (texels) and edges of a surface graph.

    Attributes
    ----------
    positions, normals : (V, 3) float
        Texel centres (world metres) and their faces' outward unit normals.
    chart, row, col : (V,) int
        Chart of each texel and its place in the chart's grid.
    edges : (E, 2) int
        Adjacent texel pairs (within 1.5 texels: a face's 8-neighbours and the texels
        across a fold).
    charts : list of Chart
    texel_m : float
    """

    positions: np.ndarray
    normals: np.ndarray
    chart: np.ndarray
    row: np.ndarray
    col: np.ndarray
    edges: np.ndarray
    charts: list[Chart]
    texel_m: float


def mesh_charts(
    vertices: np.ndarray, triangles: np.ndarray, texel_m: float, u_hint: np.ndarray | None = None
) -> list[Chart]:
    """Group a proxy's triangles into planar connected charts with texel grids.

    Parameters
    ----------
    vertices : (V, 3), triangles : (T, 3)
    texel_m : float
        Texel size, metres.
    u_hint : (3,), optional
        Horizontal direction of texel columns on roofs (the voxel grid's x axis).
    """
    # a local origin (a texel corner): at UTM magnitudes, n . p carries the normal's
    # rounding (1e-9) as millimetres, which split coplanar triangles into charts (a tiny
    # city at UTM: 66 charts where the same city near the origin has 51)
    ref = np.floor(vertices.min(axis=0) / texel_m) * texel_m
    p = vertices[triangles] - ref
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    offset = np.einsum("ij,ij->i", n, p[:, 0])
    key = np.column_stack([np.round(n, 3), np.round(offset, 3)])
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    # triangles sharing an edge and a plane are one chart
    t = len(triangles)
    e = np.sort(
        np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1
    )
    tri_of = np.tile(np.arange(t), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, tri_of = e[order], tri_of[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    a, b = tri_of[:-1][same], tri_of[1:][same]
    keep = group[a] == group[b]
    adj = sparse.coo_matrix((np.ones(keep.sum()), (a[keep], b[keep])), shape=(t, t))
    _, comp = csgraph.connected_components(adj, directed=False)
    up = np.array([0.0, 0.0, 1.0])
    hint = np.array([1.0, 0.0, 0.0]) if u_hint is None else np.asarray(u_hint, float)
    charts = []
    for c in np.unique(comp):
        tris = np.flatnonzero(comp == c)
        normal = n[tris[0]]
        if normal @ normal < 0.5:  # zero-area triangles (collinear corners): no texels
            continue
        if abs(normal[2]) > 0.9:
            u = hint - normal * (hint @ normal)
        else:
            u = np.cross(up, normal)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        pts = p[tris].reshape(-1, 3)
        a_, b_ = pts @ u, pts @ v
        a0 = np.floor(a_.min() / texel_m) * texel_m
        b0 = np.floor(b_.min() / texel_m) * texel_m
        cols = max(1, int(np.ceil((a_.max() - a0) / texel_m - 1e-9)))
        rows = max(1, int(np.ceil((b_.max() - b0) / texel_m - 1e-9)))
        origin = ref + (a0 * u + b0 * v + normal * offset[tris[0]])
        charts.append(Chart(tris, origin, u, v, normal, (rows, cols), normal[2] > -0.9))
    return charts


def chart_mask(
    chart: Chart, vertices: np.ndarray, triangles: np.ndarray, texel_m: float
) -> np.ndarray:
    """(rows, cols) bool: texels whose centre lies in the chart's triangles (at least one)."""
    rows, cols = chart.shape
    mask = np.zeros((rows, cols), np.uint8)
    q = vertices[triangles[chart.triangles]] - chart.origin
    x = q @ chart.u / texel_m - 0.5
    y = q @ chart.v / texel_m - 0.5
    pts = np.round(np.stack([x, y], axis=-1) * 16).astype(np.int32)
    cv2.fillPoly(mask, list(pts), 1, lineType=cv2.LINE_8, shift=4)
    if not mask.any():
        centre = np.clip(np.round([y.mean(), x.mean()]).astype(int), 0, [rows - 1, cols - 1])
        mask[centre[0], centre[1]] = 1
    return mask.astype(bool)


def surface_graph(
    vertices: np.ndarray, triangles: np.ndarray, texel_m: float, u_hint: np.ndarray | None = None
) -> SurfaceGraph:
    """The surface graph of a proxy mesh (section 5.1) on texels of ``texel_m`` metres."""
    charts = mesh_charts(vertices, triangles, texel_m, u_hint)
    pos, nrm, ch, rr, cc = [], [], [], [], []
    for i, chart in enumerate(charts):
        if not chart.visible:
            continue
        r, c = np.nonzero(chart_mask(chart, vertices, triangles, texel_m))
        pos.append(
            chart.origin
            + np.outer((c + 0.5) * texel_m, chart.u)
            + np.outer((r + 0.5) * texel_m, chart.v)
        )
        nrm.append(np.broadcast_to(chart.normal, (len(r), 3)))
        ch.append(np.full(len(r), i))
        rr.append(r)
        cc.append(c)
    if not pos:
        z = np.zeros(0, np.int64)
        return SurfaceGraph(
            np.zeros((0, 3)), np.zeros((0, 3)), z, z, z, np.zeros((0, 2), np.int64), charts, texel_m
        )
    positions = np.concatenate(pos)
    edges = cKDTree(positions).query_pairs(1.5 * texel_m, output_type="ndarray").astype(np.int64)
    return SurfaceGraph(
        positions, np.concatenate(nrm), np.concatenate(ch), np.concatenate(rr),
        np.concatenate(cc), edges.reshape(-1, 2), charts, texel_m,
    )  # fmt: skip


def texel_colours(labels: np.ndarray, samples: ViewSamples, fill: int = 128) -> np.ndarray:
    """(V, 3) uint8 colour of every vertex in its view (``labels``), ``fill`` grey where
    it has none."""
    out = np.full((len(labels), 3), fill, np.uint8)
    seen = labels >= 0
    out[seen] = samples.rgb[np.flatnonzero(seen), labels[seen]]
    return out


def best_views(
    positions: np.ndarray, normals: np.ndarray, centres: np.ndarray, samples: ViewSamples
) -> np.ndarray:
    """k_a: among the views that see each vertex, the one maximising (g_k - q_a) . n_a
    with g_k - q_a normalised (section 5.2). -1 where no view sees the vertex.

    Normalised, because our cameras fly at one height: the plain dot product would tie
    every view for every roof texel.

    ``centres`` (K, 3) are the projection centres of the views of ``samples``' columns.
    """
    centres = np.asarray(centres)
    best = np.full(len(positions), -1)
    # a few thousand vertices at a time: the (V, K, 3) directions of a whole building
    # are hundreds of megabytes, written and read three times
    for lo in range(0, len(positions), 2048):
        hi = lo + 2048
        visible = samples.visible[lo:hi]
        score = np.where(visible, facing_scores(positions[lo:hi], normals[lo:hi], centres),
                         -np.inf)  # fmt: skip
        best[lo:hi] = np.where(visible.any(axis=1), np.argmax(score, axis=1), -1)
    return best


def select_views(
    positions: np.ndarray,
    normals: np.ndarray,
    rank_normals: np.ndarray,
    cameras: list,
    views: list[int],
    occluders=None,
    tolerance: float = 0.01,
    sample: int = 2000,
) -> list[int]:
    """The fewest of ``views`` that texture a surface almost as squarely as all of them.

    On a city a building is framed by about 150 views and a texel's best view changes
    every few metres among near-equal ones: the cuts of section 5.2 then stitch over a
    hundred patches and the refinement tries every view. The views are chosen greedily,
    each the one that most raises the sum over a sample of the vertices of their best
    :func:`best_views` score (facility location), until the sample's mean best score is
    within ``tolerance`` of what every view gives. The refinement prices a worse-facing
    view at ``facing_weight`` Lab units per unit cosine, so a tolerance of 0.01 costs 0.1
    Lab unit a texel on average at the default weight, far below a visible difference.

    Parameters
    ----------
    positions, normals : (V, 3)
        Vertices and the normals visibility is judged by
        (:func:`~workbench.texture_seams.framed`, occlusion by ``occluders``).
    rank_normals : (V, 3)
        The normals :func:`best_views` rates the views by.
    cameras : list of Camera
    views : list of int
        The candidates (indices into ``cameras``).
    occluders : workbench.raycast.RayScene, optional
    tolerance : float
        Mean cosine the chosen views may give up; 0 keeps every view.
    sample : int
        At most this many vertices, evenly spaced in the graph's order, are scored.

    Returns
    -------
    The chosen views, in the order of ``views`` (all of them when no sampled vertex is
    seen, or with a tolerance of 0).
    """
    views = list(views)
    if tolerance <= 0 or not views or not len(positions):
        return views
    at = np.arange(0, len(positions), max(1, len(positions) // sample))
    P, N = positions[at], normals[at]
    centres = np.array([cameras[k].center for k in views]).reshape(-1, 3)
    seen = np.zeros((len(at), len(views)), bool)
    for j, k in enumerate(views):
        sel = framed(P, N, cameras[k])[0]
        if occluders is not None and len(sel):
            sel = sel[~hidden_from(occluders, P[sel], N[sel], cameras[k].center)]
        seen[sel, j] = True
    if not seen.any():
        return views
    score = np.where(seen, np.maximum(facing_scores(P, rank_normals[at], centres), 0.0), 0.0)
    target = score.max(axis=1).mean() - tolerance
    chosen = np.zeros(len(views), bool)
    best = np.zeros(len(at))
    while best.mean() < target:
        gain = np.maximum(score - best[:, None], 0.0).sum(axis=0)
        gain[chosen] = -1.0
        j = int(np.argmax(gain))
        chosen[j] = True
        best = np.maximum(best, score[:, j])
    return [k for k, c in zip(views, chosen, strict=True) if c]


def facing_scores(positions: np.ndarray, normals: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(V, K) float64 (g_k - q_a) . n_a of :func:`best_views`, g_k - q_a normalised, for
    vertices ``positions`` (V, 3) with ``normals`` (V, 3) and views at ``centres`` (K, 3)."""
    d = centres[None, :, :] - positions[:, None, :]
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    return np.einsum("vkc,vc->vk", d, normals)


def patches(edges: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(V,) patch id of every vertex: connected runs of one view (-1 where unlabelled)."""
    v = len(labels)
    same = (labels[edges[:, 0]] == labels[edges[:, 1]]) & (labels[edges[:, 0]] >= 0)
    e = edges[same]
    adj = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(v, v))
    _, comp = csgraph.connected_components(adj, directed=False)
    comp[labels < 0] = -1
    return comp


def view_facing(labels: np.ndarray, samples: ViewSamples) -> float:
    """Mean cosine between each seen vertex's normal and the direction to its view
    (``labels``): 1 when every texel is textured from straight in front. NaN when no
    vertex has a view."""
    seen = np.flatnonzero(labels >= 0)
    if not len(seen):
        return float("nan")
    return float(samples.facing[seen, labels[seen]].mean())


@dataclass
class Stitching:
    """Result of :func:`stitch_patches`.

    Attributes
    ----------
    labels : (V,) int
        View of every vertex after the cuts (-1 unseen).
    patches_before, patches_after : int
    cuts : int
        Minimum cuts run.
    """

    labels: np.ndarray
    patches_before: int
    patches_after: int
    cuts: int


def stitch_patches(
    graph_edges: np.ndarray,
    positions: np.ndarray,
    labels: np.ndarray,
    samples: ViewSamples,
    overlap_m: float,
    min_patch: int = 16,
) -> Stitching:
    """Greedy surface graph cuts (section 5.2).

    Starting from the largest patch, the largest patch next to the stitched vertices is
    added, one at a time: stitched vertices within ``overlap_m`` of it that its view also
    sees form the band where the seam may go; the other stitched vertices are tied to
    the source, the new patch's to the sink, edges weigh C(s, t) of eq. 5 between each
    vertex's current view and the new one, and a minimum cut decides which band vertices
    change view.

    Parameters
    ----------
    graph_edges : (E, 2) int
    positions : (V, 3) float
    labels : (V,) int
        Initial view per vertex (-1 unseen).
    samples : ViewSamples
    overlap_m : float
        Band width, metres.
    min_patch : int
        A patch smaller than this (vertices) takes the view most of its stitched
        neighbours have, without a cut, when that view sees all of it.
    """
    initial, labels = labels, labels.copy()
    patch = patches(graph_edges, labels)
    _, patch = np.unique(patch, return_inverse=True)  # -1 first, then 0..n-1
    patch = patch.ravel() - (1 if (labels < 0).any() else 0)
    n_patch = int(patch.max()) + 1 if len(patch) else 0
    sizes = np.bincount(patch[patch >= 0], minlength=n_patch)
    done = np.zeros(len(labels), bool)
    remaining = sizes > 0
    cuts = 0
    incident = _incidence(graph_edges, len(labels))
    order = np.argsort(positions[:, 0], kind="stable")
    by_x = (order, positions[order, 0])
    # patches with a vertex next to a stitched one; a remaining patch's vertices are
    # never stitched nor relabelled by a cut, so marking the neighbours of each newly
    # stitched patch keeps this exact
    touching = np.zeros(n_patch, bool)

    def stitched(members: np.ndarray) -> None:
        done[members] = True
        near = patch[incident[np.flatnonzero(members)].indices]
        touching[near[near >= 0]] = True

    while remaining.any():
        candidates = remaining & touching
        if not candidates.any():  # a new part of the surface: start from its largest patch
            p = int(np.argmax(np.where(remaining, sizes, -1)))
            stitched(patch == p)
            remaining[p] = False
            continue
        p = int(np.argmax(np.where(candidates, sizes, -1)))
        remaining[p] = False
        members = patch == p
        if sizes[p] < min_patch and _absorb(incident, labels, done, members, samples):
            stitched(members)
            continue
        k = int(labels[members][0])
        keep, free = _frontier(positions, by_x, labels, done, members, samples, k, overlap_m)
        labels, changed = _cut(graph_edges, incident, keep, done, members, free, k, samples)
        cuts += 1
        stitched(members)
        patch[changed] = p
    return Stitching(
        labels, count_patches(graph_edges, initial), count_patches(graph_edges, labels), cuts
    )


def refine_seams(
    graph_edges: np.ndarray,
    labels: np.ndarray,
    samples: ViewSamples,
    facing_weight: float = 10.0,
    sweeps: int = 2,
) -> np.ndarray:
    """Expansion moves over the whole surface graph after the greedy stitching.

    The greedy cuts of section 5.2 fix each seam once, inside one band, in the order the
    patches come; a seam they leave where two views disagree stays there. This pass
    lowers, over every vertex at once,

        E = sum_v w (1 - cos_v(view_v)) + sum_(s,t) C_(view_s, view_t)(s, t)

    with C of eq. 5 (0 between equal views) and ``w`` = ``facing_weight`` Lab units per
    unit of the cosine between a vertex's normal and the direction to its view, so that
    a seam moves only where it pays for the views it gives up. One alpha-expansion move
    per view already used (a single exact cut each,
    :func:`~workbench.graph_cuts.pairwise_cut`: C is a sum of distances between
    views, a metric), kept when it lowers E; vertices
    take only views that see them, unseen ones stay unseen.

    Parameters
    ----------
    graph_edges : (E, 2) int
    labels : (V,) int
        View per vertex after the stitching (-1 unseen).
    samples : ViewSamples
    facing_weight : float
        w, Lab units per unit cosine.
    sweeps : int
        Passes over the views (fewer when one changes nothing).

    Returns
    -------
    (V,) int views.
    """
    labels = labels.copy()
    seen = labels >= 0
    rows = np.arange(len(labels))

    def data(at: np.ndarray, view) -> np.ndarray:
        return facing_weight * (1.0 - samples.facing[at, view])

    d_now = data(rows, np.maximum(labels, 0))
    index = np.full(len(labels), -1)
    to_alpha = np.zeros(len(labels))
    for _ in range(sweeps):
        improved = False
        for alpha in np.unique(labels[seen]):
            movable = seen & samples.visible[:, alpha] & (labels != alpha)
            if not movable.any():
                continue
            # edges with no end that may move keep their cost and play no part; nor do
            # the vertices that cannot move and touch none of them (a cut leaves them)
            edges = graph_edges[movable[graph_edges[:, 0]] | movable[graph_edges[:, 1]]]
            touched = movable.copy()
            touched[edges.ravel()] = True
            nodes = np.flatnonzero(touched)
            index[nodes] = np.arange(len(nodes))
            unary = np.column_stack(
                [d_now[nodes], np.where(movable[nodes], data(nodes, alpha), _INF)]
            )
            # each vertex's term of C between its view and alpha, shared by its edges
            to_alpha[nodes] = seam_terms(nodes, np.maximum(labels[nodes], 0), alpha, samples)
            pair = _move_costs(edges, labels, alpha, samples, to_alpha)
            x = pairwise_cut(unary, index[edges], pair)
            taken = pair[np.arange(len(edges)), 2 * x[index[edges[:, 0]]] + x[index[edges[:, 1]]]]
            gain = np.sum((unary[:, 1] - d_now[nodes])[x == 1]) + np.sum(taken - pair[:, 0])
            if gain < -1e-9:
                moved = nodes[x == 1]
                labels[moved] = alpha
                d_now[moved] = unary[x == 1, 1]
                improved = True
        if not improved:
            break
    return labels


def _move_costs(
    edges: np.ndarray, labels: np.ndarray, k: int, samples, to_k: np.ndarray | None = None
) -> np.ndarray:
    """(E, 4) C of eq. 5 of each edge for an expansion move to view ``k``: both ends keep
    their views (E00), the second end takes ``k`` (E01), the first does (E10), both do
    (E11, no seam). Equal views and unseen ends (-1) cost nothing.

    ``to_k`` (V,), when given, is every vertex's term of C between its own view and
    ``k`` (:func:`~workbench.texture_seams.seam_terms`): an edge inside a patch, most of
    them, then costs two look-ups; only the edges across a seam are computed here.
    """
    s, t = edges[:, 0], edges[:, 1]
    ls, lt = labels[s], labels[t]
    out = np.zeros((len(edges), 4))
    differ = (ls != lt) & (ls >= 0) & (lt >= 0)
    out[differ, 0] = seam_costs(edges[differ], ls[differ], lt[differ], samples)
    if to_k is None:  # at the edges' ends only: a stitching cut's band is small
        to_k = np.zeros(len(labels))
        ends = np.zeros(len(labels), bool)
        ends[edges.ravel()] = True
        ends = np.flatnonzero(ends)
        to_k[ends] = seam_terms(ends, np.maximum(labels[ends], 0), k, samples)
    across = ls != lt
    at_s, at_t = to_k[s], to_k[t]
    # E01: s keeps ls, t takes k; t's term is its own when it has ls too
    differ = (ls != k) & (ls >= 0)
    far = np.where(across, 0.0, at_t)
    one = differ & across
    far[one] = seam_terms(t[one], ls[one], k, samples)
    out[differ, 1] = at_s[differ] + far[differ]
    # E10: s takes k, t keeps lt
    differ = (lt != k) & (lt >= 0)
    near = np.where(across, 0.0, at_s)
    one = differ & across
    near[one] = seam_terms(s[one], k, lt[one], samples)
    out[differ, 2] = near[differ] + at_t[differ]
    return out


def count_patches(graph_edges: np.ndarray, labels: np.ndarray) -> int:
    """Number of patches (connected runs of one view; unseen vertices are none)."""
    patch = patches(graph_edges, labels)
    return int(len(np.unique(patch[patch >= 0])))


def _incidence(edges: np.ndarray, v: int) -> sparse.csr_matrix:
    """(V, V) sparse: row s holds, at column t, 1 + the index of edge (s, t) or (t, s)."""
    ids = np.arange(1, len(edges) + 1)
    return sparse.csr_matrix(
        (np.concatenate([ids, ids]), (edges.T.ravel(), edges[:, ::-1].T.ravel())), shape=(v, v)
    )


def _absorb(incident, labels, done, members, samples) -> bool:
    """Give a small patch its stitched neighbours' most common view, if it sees the patch."""
    near = incident[np.flatnonzero(members)].indices
    outer = labels[near[done[near]]]
    if not len(outer):
        return False
    k = int(np.bincount(outer).argmax())
    if not samples.visible[members, k].all():
        return False
    labels[members] = k
    return True


def _frontier(positions, by_x, labels, done, members, samples, k, overlap_m):
    """The overlap band of a new patch (view ``k``) with the stitched vertices.

    On the stitched side, the vertices within ``overlap_m`` of the patch that view ``k``
    sees; on the patch's side, its vertices within ``overlap_m`` of a stitched vertex
    whose view sees them too. Returns the view each vertex keeps if the cut leaves it
    on the source side ((V,) int: its own, or for the patch's band vertices their nearest
    stitched vertex's) and the band ((V,) bool). ``by_x`` is the vertices in order of x
    and their x, two (V,) arrays.
    """
    lo = positions[members].min(axis=0) - overlap_m
    hi = positions[members].max(axis=0) + overlap_m
    # the stitched vertices in the patch's box, in index order; x first, by bisection
    order, x = by_x
    close = order[np.searchsorted(x, lo[0], "left") : np.searchsorted(x, hi[0], "right")]
    p = positions[close]
    close = np.sort(close[done[close] & np.all((p >= lo) & (p <= hi), axis=1)])
    free = np.zeros(len(labels), bool)
    keep = labels.copy()
    if not len(close):
        return keep, free
    near = cKDTree(positions[members]).query(positions[close], distance_upper_bound=overlap_m)[0]
    free[close[np.isfinite(near)]] = True
    free &= samples.visible[:, k]
    inside = np.flatnonzero(members)
    d, nearest = cKDTree(positions[close]).query(positions[inside], distance_upper_bound=overlap_m)
    inside, nearest = inside[np.isfinite(d)], nearest[np.isfinite(d)]
    other = labels[close[nearest]]
    sees = samples.visible[inside, other]
    keep[inside[sees]] = other[sees]
    free[inside[sees]] = True
    return keep, free


def _cut(edges, incident, keep, done, members, free, k, samples):
    """One min cut: band vertices (``free``) keep their view ``keep`` (source side) or
    take view ``k`` (sink side); other stitched vertices keep theirs, the new patch's
    take ``k``. Each edge pays C of eq. 5 between the views its two ends end up with.

    ``incident`` is :func:`_incidence` of ``edges``: the cut reads the band's edges only.
    """
    rows = incident[np.flatnonzero(free)]
    # vertices next to the band keep the seam honest at its edge
    rim = np.zeros(len(keep), bool)
    rim[rows.indices] = True
    in_graph = free | (rim & (done | members))
    ids = np.sort(rows.data)  # the band's edges, once each, in the graph's order
    first = np.ones(len(ids), bool)
    first[1:] = ids[1:] != ids[:-1]
    e = edges[ids[first] - 1]
    e = e[in_graph[e[:, 0]] & in_graph[e[:, 1]]]
    # a patch vertex off the band has no edge here and takes k whatever the cut
    nodes = np.flatnonzero(in_graph)
    index = np.full(len(keep), -1)
    index[nodes] = np.arange(len(nodes))
    pair = _move_costs(e, keep, k, samples)
    unary = np.zeros((len(nodes), 2))
    unary[:, 1] = np.where(done[nodes] & ~free[nodes], _INF, 0.0)  # tied to the source
    unary[:, 0] = np.where(members[nodes] & ~free[nodes], _INF, 0.0)  # tied to the sink
    to_k = nodes[pairwise_cut(unary, index[e], pair) == 1]
    labels = keep.copy()
    labels[members & ~in_graph] = k
    labels[to_k] = k
    return labels, to_k[~members[to_k]]
