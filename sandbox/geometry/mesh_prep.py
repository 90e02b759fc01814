"""Surface-mesh preparation for mesh geodesics: clean-up, refinement, point insertion.

Geodesic solvers work on a manifold triangle mesh whose vertices are dense
enough to route paths through (a 12-triangle box has no interior vertices).
``prepare_mesh`` cleans the mesh and refines it conformingly (no T-junctions)
until no edge exceeds a target length; ``insert_point`` makes a surface point a
vertex by splitting its face (or edge) so that solvers can start or end there;
``surface_graph`` is the vertex graph used to route initial paths.
All lengths are in the mesh's units (m, world space).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import csr_matrix


def prepare_mesh(
    mesh: trimesh.Trimesh, *, hull: bool = False, target_edge: float | None = None
) -> trimesh.Trimesh:
    """Clean, optionally convexify, and refine a mesh for geodesic queries.

    Args:
        mesh: Triangle mesh in world space (m).
        hull: Replace the mesh by its convex hull first.
        target_edge: Longest allowed edge after refinement (m); None means
            1/40 of the bounding-box diagonal, ``inf`` disables refinement.

    Returns:
        A new manifold, consistently oriented mesh (``process=False``).

    Raises:
        ValueError: The mesh is empty or has edges shared by more than two faces.
    """
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces")
    m = mesh.convex_hull if hull else mesh.copy()
    m.merge_vertices()
    keep = m.nondegenerate_faces() & m.unique_faces()
    m.update_faces(keep)
    m.remove_unreferenced_vertices()
    if not m.is_winding_consistent:
        trimesh.repair.fix_winding(m)
    if target_edge is None:
        target_edge = float(np.linalg.norm(m.extents)) / 40.0
    if not target_edge > 0.0:
        raise ValueError(f"target_edge must be > 0, got {target_edge}")
    vertices = np.asarray(m.vertices, dtype=np.float64)
    faces = np.asarray(m.faces, dtype=np.int64)
    if np.isfinite(target_edge):
        vertices, faces = refine_to_edge(vertices, faces, target_edge)
    check_manifold_edges(faces)
    return trimesh.Trimesh(vertices, faces, process=False)


def check_manifold_edges(faces: np.ndarray) -> None:
    """Raise ValueError when an edge is shared by more than two faces."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    bad = int((counts > 2).sum())
    if bad:
        raise ValueError(f"mesh is not manifold: {bad} edges are shared by more than two faces")


def refine_to_edge(
    vertices: np.ndarray, faces: np.ndarray, max_edge: float, *, max_rounds: int = 40
) -> tuple[np.ndarray, np.ndarray]:
    """Split edges longer than ``max_edge`` at their midpoints, conformingly.

    Each round marks every edge longer than ``max_edge`` and splits every face
    by its number of marked edges (red-green refinement: 1 -> 2, 2 -> 3 using
    the shorter diagonal, 3 -> 4), so neighbouring faces share the new
    midpoints and no T-junction appears. Flat regions stay exactly flat.

    Args:
        vertices: (n, 3) float positions (m).
        faces: (f, 3) int vertex indices, counter-clockwise.
        max_edge: Longest allowed edge (m).
        max_rounds: Safety cap on the number of rounds.

    Returns:
        (vertices, faces) of the refined mesh; original vertices keep their indices.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    for _ in range(max_rounds):
        corner_edges = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, inverse = np.unique(corner_edges, axis=0, return_inverse=True)
        lengths = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
        marked = lengths > max_edge
        if not marked.any():
            break
        mid = np.full(len(edges), -1, dtype=np.int64)
        mid[marked] = len(V) + np.arange(int(marked.sum()))
        V = np.vstack([V, 0.5 * (V[edges[marked, 0]] + V[edges[marked, 1]])])
        M = mid[inverse.reshape(-1, 3)]  # M[:, k]: midpoint of edge (v_k, v_k+1)
        n_marked = (M >= 0).sum(axis=1)
        F = np.vstack(
            [F[n_marked == 0], _split_one(F, M, n_marked == 1)]
            + [_split_two(V, F, M, n_marked == 2), _split_three(F, M, n_marked == 3)]
        )
    return V, F


def _rolled(F: np.ndarray, M: np.ndarray, sel: np.ndarray, k: np.ndarray):
    """Faces and midpoints of ``sel`` rotated so that local index 0 is ``k``."""
    idx = (k[:, None] + np.arange(3)) % 3
    return np.take_along_axis(F[sel], idx, 1), np.take_along_axis(M[sel], idx, 1)


def _split_one(F: np.ndarray, M: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Bisect faces with one marked edge (rotated to edge 0: a-b)."""
    f, m = _rolled(F, M, sel, np.argmax(M[sel] >= 0, axis=1))
    a, b, c, mab = f[:, 0], f[:, 1], f[:, 2], m[:, 0]
    return np.vstack([np.stack([a, mab, c], 1), np.stack([mab, b, c], 1)])


def _split_two(V: np.ndarray, F: np.ndarray, M: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Split faces with two marked edges (unmarked edge rotated to a-b) into three."""
    f, m = _rolled(F, M, sel, np.argmin(M[sel] >= 0, axis=1))
    a, b, c, mbc, mca = f[:, 0], f[:, 1], f[:, 2], m[:, 1], m[:, 2]
    corner = np.stack([mbc, c, mca], 1)
    diag_a = np.linalg.norm(V[a] - V[mbc], axis=1) <= np.linalg.norm(V[b] - V[mca], axis=1)
    q1 = np.where(diag_a[:, None], np.stack([a, b, mbc], 1), np.stack([a, b, mca], 1))
    q2 = np.where(diag_a[:, None], np.stack([a, mbc, mca], 1), np.stack([b, mbc, mca], 1))
    return np.vstack([corner, q1, q2])


def _split_three(F: np.ndarray, M: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Split faces with three marked edges 1-to-4."""
    f, m = F[sel], M[sel]
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    mab, mbc, mca = m[:, 0], m[:, 1], m[:, 2]
    return np.vstack(
        [
            np.stack([a, mab, mca], 1),
            np.stack([mab, b, mbc], 1),
            np.stack([mca, mbc, c], 1),
            np.stack([mab, mbc, mca], 1),
        ]
    )


def barycentric(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points in triangles.

    Args:
        points: (n, 3) positions (m).
        tri: (n, 3, 3) triangle corners (m).

    Returns:
        (n, 3) coordinates summing to 1 (of the projection onto each triangle's plane).
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 0.0, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=1)


def locate(V: np.ndarray, F: np.ndarray, candidates, x: np.ndarray) -> tuple[int, np.ndarray]:
    """The candidate face that best contains surface point ``x``, and its barycentrics."""
    cand = np.asarray(list(candidates), dtype=np.int64)
    bary = barycentric(np.repeat(x[None], len(cand), 0), V[F[cand]])
    best = int(np.argmax(bary.min(axis=1)))
    return int(cand[best]), np.clip(bary[best], 0.0, 1.0) / np.clip(bary[best], 0.0, 1.0).sum()


def insert_point(
    V: np.ndarray, F: np.ndarray, face: int, bary: np.ndarray, snap: float
) -> tuple[np.ndarray, np.ndarray, int, list[int]]:
    """Make a surface point a mesh vertex.

    The point ``bary`` in ``face`` becomes an existing vertex when within
    ``snap`` of one, otherwise a new vertex that splits its edge (when within
    ``snap`` of an edge: both adjacent faces are bisected, no sliver appears)
    or its face (1-to-3). New vertices and faces are appended, so existing
    vertex indices stay valid.

    Args:
        V: (n, 3) vertex positions (m); not modified.
        F: (f, 3) faces; not modified.
        face: Face containing the point.
        bary: (3,) barycentric coordinates in ``face``.
        snap: Distance (m) under which the point snaps to a vertex or an edge.

    Returns:
        (V, F, vertex index of the point, indices of faces that changed or were added).
    """
    tri = F[face]
    corners = V[tri]
    x = np.asarray(bary, dtype=np.float64) @ corners
    d_vert = np.linalg.norm(corners - x, axis=1)
    if d_vert.min() <= snap:
        return V, F, int(tri[np.argmin(d_vert)]), []
    seg = np.roll(corners, -1, axis=0) - corners  # edge k: corner k -> k+1
    t = np.clip(np.einsum("ij,ij->i", x - corners, seg) / np.einsum("ij,ij->i", seg, seg), 0, 1)
    foot = corners + t[:, None] * seg
    d_edge = np.linalg.norm(foot - x, axis=1)
    k = int(np.argmin(d_edge))
    vid = len(V)
    F = F.copy()
    if d_edge[k] <= snap:
        V = np.vstack([V, foot[k]])
        a, b = int(tri[k]), int(tri[(k + 1) % 3])
        sharing = np.flatnonzero((F == a).any(axis=1) & (F == b).any(axis=1))
        added = []
        for h in sharing:
            j = next(i for i in range(3) if {int(F[h, i]), int(F[h, (i + 1) % 3])} == {a, b})
            u, w, c = F[h, j], F[h, (j + 1) % 3], F[h, (j + 2) % 3]
            F[h] = (u, vid, c)
            added.append((vid, w, c))
        F = np.vstack([F, np.asarray(added, dtype=np.int64)])
        touched = list(map(int, sharing)) + list(range(len(F) - len(added), len(F)))
        return V, F, vid, touched
    V = np.vstack([V, x])
    a, b, c = (int(i) for i in tri)
    F[face] = (a, b, vid)
    F = np.vstack([F, np.array([[b, c, vid], [c, a, vid]], dtype=np.int64)])
    return V, F, vid, [int(face), len(F) - 2, len(F) - 1]


def surface_graph(V: np.ndarray, F: np.ndarray) -> csr_matrix:
    """Vertex graph for routing: mesh edges plus the flipped diagonal of each edge.

    A diagonal joins the two vertices opposite an interior edge, weighted by
    its length in the unfolded pair of faces, and is kept only where the pair
    is convex (the segment stays on the surface). With both diagonals of every
    quad the graph distance exceeds the surface distance by at most ~8% on
    regular grids, against up to 41% for mesh edges alone (right-triangle
    grids), so Dijkstra picks the right side of sharp corners far more often.

    Args:
        V: (n, 3) vertex positions (m).
        F: (f, 3) faces.

    Returns:
        (n, n) symmetric sparse matrix of edge lengths (m).
    """
    n = len(V)
    half = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    opposite = F[:, [2, 0, 1]].reshape(-1)
    rows, cols = [half[:, 0]], [half[:, 1]]
    weights = [np.linalg.norm(V[half[:, 0]] - V[half[:, 1]], axis=1)]
    key = np.minimum(half[:, 0], half[:, 1]) * n + np.maximum(half[:, 0], half[:, 1])
    order = np.argsort(key, kind="stable")
    pair = np.flatnonzero(key[order][1:] == key[order][:-1])
    h1, h2 = order[pair], order[pair + 1]
    a, b = V[half[h1, 0]], V[half[h1, 1]]
    c, d = V[opposite[h1]], V[opposite[h2]]
    length = np.linalg.norm(b - a, axis=1)
    u = (b - a) / length[:, None]
    xc = np.einsum("ij,ij->i", c - a, u)
    xd = np.einsum("ij,ij->i", d - a, u)
    yc = np.linalg.norm(c - a - xc[:, None] * u, axis=1)
    yd = np.linalg.norm(d - a - xd[:, None] * u, axis=1)
    cross = xc + yc / np.maximum(yc + yd, 1e-300) * (xd - xc)  # where c-d meets the edge
    convex = (cross > 0.0) & (cross < length)
    rows.append(opposite[h1][convex])
    cols.append(opposite[h2][convex])
    weights.append(np.hypot(xc - xd, yc + yd)[convex])
    r, c_, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    r, c_, w = np.r_[r, c_], np.r_[c_, r], np.r_[w, w]
    keys = r * n + c_
    order = np.lexsort((w, keys))
    first = np.r_[True, keys[order][1:] != keys[order][:-1]]  # keep the shortest duplicate
    o = order[first]
    return csr_matrix((w[o], (r[o], c_[o])), shape=(n, n))
