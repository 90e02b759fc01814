"""What the rasterizer draws: mesh items, the scene, rope tubes and crease splitting.

Everything here is plain NumPy: a scene costs nothing until a ``Renderer`` draws it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass
class MeshItem:
    """One triangle mesh to draw.

    Attributes:
        verts: (n, 3) float32 world positions in m.
        faces: (m, 3) int32 vertex indices, counter-clockwise seen from the front.
        color: (3,) RGB colour in [0, 1] of the front side.
        back_color: (3,) RGB colour of the back side; None gives a darker tint of
            ``color``. Used only when ``two_sided``.
        two_sided: draw both sides (cloth); otherwise back faces are culled
            (closed objects, tubes).
        smooth: shade with interpolated vertex normals; False shades flat.
    """

    verts: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float] = (0.8, 0.8, 0.8)
    back_color: tuple[float, float, float] | None = None
    two_sided: bool = False
    smooth: bool = True

    def __post_init__(self) -> None:
        self.verts = np.ascontiguousarray(self.verts, dtype=np.float32).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32).reshape(-1, 3)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(self.verts)):
            raise ValueError("faces index vertices out of range")

    def back(self) -> tuple[float, float, float]:
        """The colour of the back side."""
        if self.back_color is not None:
            return tuple(float(c) for c in self.back_color)
        return tuple(0.6 * float(c) for c in self.color)


@dataclass
class RenderScene:
    """A list of meshes over an optional ground plane.

    Attributes:
        items: meshes to draw.
        ground_height: y of the ground plane in m; None draws no ground.
        ground_cell: checker cell size in m; None picks one from the scene size
            (``ground_cell_for``); fix it for a steady video.
    """

    items: list[MeshItem] = field(default_factory=list)
    ground_height: float | None = None
    ground_cell: float | None = None

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius in m of a sphere holding every vertex.

        The centre is the bounding-box centre; an empty scene gives the unit sphere.
        """
        pts = [it.verts for it in self.items if len(it.verts)]
        if not pts:
            return np.zeros(3), 1.0
        allv = np.concatenate(pts)
        lo = np.array([allv[:, k].min() for k in range(3)], dtype=np.float64)
        hi = np.array([allv[:, k].max() for k in range(3)], dtype=np.float64)
        centre = 0.5 * (lo + hi)
        d = allv - centre.astype(np.float32)
        radius = float(np.sqrt(np.einsum("ij,ij->i", d, d).max()))
        return centre, max(radius, 1e-6)


def ground_cell_for(radius: float) -> float:
    """A round checker size (1, 2 or 5 times a power of ten, m) about a quarter of a scene radius."""
    target = max(radius / 4.0, 1e-6)
    p = 10.0 ** np.floor(np.log10(target))
    for m in (1.0, 2.0, 5.0):
        if m * p >= target / 1.6:
            return float(m * p)
    return float(10.0 * p)


def _rotations_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotations (k, 3, 3) taking unit vectors a[i] onto b[i]."""
    v = np.cross(a, b)
    c = np.einsum("ij,ij->i", a, b)
    k = len(a)
    vx = np.zeros((k, 3, 3))
    vx[:, 0, 1], vx[:, 0, 2] = -v[:, 2], v[:, 1]
    vx[:, 1, 0], vx[:, 1, 2] = v[:, 2], -v[:, 0]
    vx[:, 2, 0], vx[:, 2, 1] = -v[:, 1], v[:, 0]
    flip = c < -1.0 + 1e-6
    scale = 1.0 / np.where(flip, 1.0, 1.0 + c)
    rot = np.eye(3)[None] + vx + (vx @ vx) * scale[:, None, None]
    if flip.any():  # half turn about any axis normal to a
        axis = np.cross(a[flip], [1.0, 0.0, 0.0])
        weak = np.linalg.norm(axis, axis=1) < 1e-3
        axis[weak] = np.cross(a[flip][weak], [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        rot[flip] = 2.0 * axis[:, :, None] * axis[:, None, :] - np.eye(3)[None]
    return rot


def rotation_minimising_frames(polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents, normals and binormals (each (n, 3)) along a polyline.

    Frames are parallel-transported by the minimal rotation between successive
    tangents; the running product of rotations is a Hillis-Steele prefix scan,
    so the whole rope is done in log2(n) vectorised steps.
    """
    p = np.asarray(polyline, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    seg = np.diff(p, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
    tan = np.empty((n, 3))
    tan[0], tan[-1] = seg[0], seg[-1]
    mid = seg[:-1] + seg[1:]
    norm = np.linalg.norm(mid, axis=1, keepdims=True)
    tan[1:-1] = np.where(norm > 1e-9, mid / np.maximum(norm, 1e-12), seg[1:])
    rot = np.concatenate([np.eye(3)[None], _rotations_between(tan[:-1], tan[1:])])
    step = 1
    while step < n:  # rot[i] <- rot[i] @ ... @ rot[1]
        rot[step:] = rot[step:] @ rot[:-step].copy()
        step *= 2
    seed = np.cross(tan[0], [0.0, 1.0, 0.0])
    if np.linalg.norm(seed) < 1e-3:
        seed = np.cross(tan[0], [1.0, 0.0, 0.0])
    seed /= np.linalg.norm(seed)
    nrm = rot @ seed
    nrm -= np.einsum("ij,ij->i", nrm, tan)[:, None] * tan  # re-orthogonalise
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return tan, nrm, np.cross(tan, nrm)


def tube_mesh(polyline: np.ndarray, radius: float, sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube of the given radius around a polyline (a rope).

    Args:
        polyline: (n, 3) points in m, n >= 2.
        radius: tube radius in m.
        sides: vertices per ring.

    Returns:
        verts (n * sides + 2 * (sides + 1), 3) float32 and faces int32, outward
        facing. Ring i (vertices ``i*sides .. i*sides+sides-1``) lies in the plane
        normal to the tangent at point i, at distance ``radius`` from it; the two
        end caps follow with their own vertices so they shade flat.
    """
    p = np.asarray(polyline, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        raise ValueError("a tube needs at least two polyline points")
    tan, nrm, bin_ = rotation_minimising_frames(p)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    offs = np.cos(ang)[None, :, None] * nrm[:, None] + np.sin(ang)[None, :, None] * bin_[:, None]
    rings = p[:, None] + radius * offs  # (n, sides, 3)
    n = len(p)
    i = np.arange(n - 1)[:, None] * sides
    j = np.arange(sides)[None, :]
    a, b = i + j, i + (j + 1) % sides
    c, d = a + sides, b + sides
    side_faces = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=1)
    verts = [rings.reshape(-1, 3)]
    faces = [side_faces.reshape(-1, 3)]
    base = n * sides
    for end, flip in ((0, True), (n - 1, False)):
        verts.append(np.concatenate([p[end][None], rings[end]]))
        fan = np.stack([np.zeros(sides, int), 1 + j[0], 1 + (j[0] + 1) % sides], -1) + base
        faces.append(fan[:, ::-1] if flip else fan)
        base += sides + 1
    return np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32)


def crease_split(verts: np.ndarray, faces: np.ndarray, angle_deg: float = 35.0) -> tuple[np.ndarray, np.ndarray]:
    """Unmerge vertices along sharp edges so smooth shading keeps creases crisp.

    Two faces sharing an edge are smoothed together when their normals differ
    by less than ``angle_deg``; a vertex gets one copy per smoothed fan.

    Returns:
        source (k,) int64: the original vertex of each new vertex, and new faces
        (m, 3) int32 into ``verts[source]``. Depends on topology and angles only,
        so it stays valid while the mesh moves rigidly.
    """
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    m = len(f)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    # undirected edges -> the faces that share them
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(m), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks, os_ = key[order], owner[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    f1, f2, edge = os_[:-1][same], os_[1:][same], ks[:-1][same]
    smooth = np.einsum("ij,ij->i", fn[f1], fn[f2]) > np.cos(np.radians(angle_deg))
    f1, f2, edge = f1[smooth], f2[smooth], edge[smooth]
    # corner (face, slot) ids: face * 3 + slot
    rows, cols = [], []
    for k in range(2):
        vk = edge[:, k]
        s1 = np.argmax(f[f1] == vk[:, None], axis=1)
        s2 = np.argmax(f[f2] == vk[:, None], axis=1)
        rows.append(f1 * 3 + s1)
        cols.append(f2 * 3 + s2)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * m, 3 * m))
    _, labels = connected_components(graph, directed=False)
    uniq, inverse = np.unique(labels, return_inverse=True)
    source = np.empty(len(uniq), dtype=np.int64)
    source[inverse] = f.reshape(-1)
    return source, inverse.reshape(m, 3).astype(np.int32)
