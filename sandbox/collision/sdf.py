"""Signed distance to the objects of a scene, for particle collision.

Primitives (box, sphere, cylinder, capsule, torus) use their closed-form
signed distance. Every other shape uses a signed-distance grid sampled at
load with ``igl.signed_distance`` over the padded local bounding box and
interpolated trilinearly in Taichi; the normal is the normalised gradient of
the trilinear interpolant. Outside the grid the distance is the distance to
the grid box plus the value at the nearest grid point, and the normal points
from that grid point to the query, so far points still get a positive
distance and a normal pointing away.

A mesh made of several closed parts (basket = bowl + handle, jeep = boxes +
wheels) is the union of its parts: its signed distance is the minimum over
the parts of each part's exact signed distance (pseudonormal sign). This is
exact outside and where parts do not overlap, and keeps the right sign in
the overlaps. A mesh that is not a set of closed parts gets its sign from
the generalised winding number instead.

Objects may move kinematically: ``set_pose`` records the previous pose and
``velocity_at`` returns the velocity of the material point now at ``p``.
"""

import dataclasses

import igl
import numpy as np
import taichi as ti
import trimesh

from sandbox import runtime
from sandbox.objects.builders import resolve_params

BOX, SPHERE, CYLINDER, CAPSULE, TORUS, GRID = range(6)
KINDS = {"box": BOX, "sphere": SPHERE, "cylinder": CYLINDER, "capsule": CAPSULE, "torus": TORUS}
FAR = 1.0e10
"""Distance (m) returned when there is no object at all."""

_EPS = 1e-12


@dataclasses.dataclass
class ObjectInstance:
    """One object of a scene.

    Attributes:
        name: unique name in the level.
        shape: shape name (see ``sandbox.objects.builders.SHAPES``).
        params: shape parameters (defaults are filled in again here).
        mesh: the object's mesh in its local frame (``build_mesh``).
        position: (3,) world position of the local origin, m.
        rotation: (3, 3) rotation taking local to world coordinates.
        friction: Coulomb friction coefficient against particles.
    """

    name: str
    shape: str
    params: dict
    mesh: trimesh.Trimesh
    position: np.ndarray
    rotation: np.ndarray
    friction: float


# --- closed forms, local frame centred on the shape ----------------------------


@ti.func
def _safe_normalized(v, fallback):
    n = fallback
    norm = v.norm()
    if norm > 1e-12:
        n = v / norm
    return n


@ti.func
def sdf_sphere(q, r):
    """Sphere of radius r (m) at the origin: d = |q| - r, n = q / |q|."""
    return q.norm() - r, _safe_normalized(q, ti.math.vec3(0.0, 1.0, 0.0))


@ti.func
def sdf_box(q, b):
    """Box of half extents b (m) at the origin; n is the exact gradient."""
    a = ti.abs(q) - b
    s = ti.math.vec3(1.0 if q.x >= 0 else -1.0, 1.0 if q.y >= 0 else -1.0, 1.0 if q.z >= 0 else -1.0)
    outside = ti.max(a, 0.0)
    d = 0.0
    n = ti.math.vec3(0.0, 1.0, 0.0)
    if outside.norm() > 0.0:
        d = outside.norm()
        n = s * outside / d
    else:
        d = ti.max(a.x, a.y, a.z)
        if a.x >= a.y and a.x >= a.z:
            n = ti.math.vec3(s.x, 0.0, 0.0)
        elif a.y >= a.z:
            n = ti.math.vec3(0.0, s.y, 0.0)
        else:
            n = ti.math.vec3(0.0, 0.0, s.z)
    return d, n


@ti.func
def sdf_cylinder(q, r, hh):
    """Cylinder along y, radius r and half height hh (m), centred at the origin."""
    rho = ti.math.vec2(q.x, q.z).norm()
    u = ti.math.vec3(1.0, 0.0, 0.0)
    if rho > 1e-12:
        u = ti.math.vec3(q.x / rho, 0.0, q.z / rho)
    sy = 1.0 if q.y >= 0 else -1.0
    ax, ay = rho - r, ti.abs(q.y) - hh
    d = 0.0
    n = ti.math.vec3(0.0, sy, 0.0)
    if ax > 0.0 and ay > 0.0:
        d = ti.math.vec2(ax, ay).norm()
        n = (ax * u + ti.math.vec3(0.0, ay * sy, 0.0)) / d
    elif ax > 0.0 or (ay <= 0.0 and ax >= ay):
        d = ax
        n = u
    else:
        d = ay
    return d, n


@ti.func
def sdf_capsule(q, r, hl):
    """Capsule along y: segment y in [-hl, hl] (m) swept by radius r (m)."""
    c = ti.math.vec3(0.0, ti.math.clamp(q.y, -hl, hl), 0.0)
    v = q - c
    return v.norm() - r, _safe_normalized(v, ti.math.vec3(1.0, 0.0, 0.0))


@ti.func
def sdf_torus(q, big, small):
    """Torus about the y axis: ring radius big, tube radius small (m)."""
    rho = ti.math.vec2(q.x, q.z).norm()
    u = ti.math.vec3(1.0, 0.0, 0.0)
    if rho > 1e-12:
        u = ti.math.vec3(q.x / rho, 0.0, q.z / rho)
    v = q - big * u
    return v.norm() - small, _safe_normalized(v, ti.math.vec3(0.0, 1.0, 0.0))


# --- exact distance to meshes (NumPy / igl) ------------------------------------


def _closed_parts(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh] | None:
    """The mesh's connected parts if all are closed with positive volume, else None."""
    if not mesh.is_watertight:
        return None
    parts = mesh.split(only_watertight=False)
    if not all(p.is_watertight and p.volume > 0 for p in parts):
        return None
    return list(parts)


def mesh_signed_distance(mesh: trimesh.Trimesh, points: np.ndarray,
                         parts: list[trimesh.Trimesh] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact signed distance (m, negative inside) and closest points to a mesh.

    Args:
        mesh: the mesh (any frame; ``points`` in the same frame).
        points: (n, 3) query points, m.
        parts: the closed parts of ``mesh`` (``_closed_parts``); None: the
            whole mesh with the winding-number sign.

    Returns:
        (d (n,), closest points (n, 3)) in float64.
    """
    pts = np.ascontiguousarray(points, np.float64)
    if parts is None:
        s, _, c, _ = igl.signed_distance(
            pts, np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
            sign_type=igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)
        return np.asarray(s), np.asarray(c)
    best = np.full(len(pts), np.inf)
    closest = np.zeros((len(pts), 3))
    for part in parts:
        s, _, c, _ = igl.signed_distance(
            pts, np.asarray(part.vertices, np.float64), np.asarray(part.faces, np.int64),
            sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
        better = s < best
        best[better] = s[better]
        closest[better] = c[better]
    return best, closest


def _analytic_layout(shape: str, params: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(shape parameters, local centre, bounding radius) of a primitive, m."""
    p = resolve_params(shape, params)
    if shape == "box":
        half = np.asarray(p["size"], float) / 2.0
        return half, np.array([0.0, half[1], 0.0]), float(np.linalg.norm(half))
    if shape == "sphere":
        r = float(p["radius"])
        return np.array([r, 0.0, 0.0]), np.array([0.0, r, 0.0]), r
    if shape == "cylinder":
        r, hh = float(p["radius"]), float(p["height"]) / 2.0
        return np.array([r, hh, 0.0]), np.array([0.0, hh, 0.0]), float(np.hypot(r, hh))
    if shape == "capsule":
        r, h = float(p["radius"]), float(p["height"])
        return np.array([r, h / 2.0 - r, 0.0]), np.array([0.0, h / 2.0, 0.0]), h / 2.0
    big, small = float(p["major_radius"]), float(p["minor_radius"])
    return np.array([big, small, 0.0]), np.array([0.0, small, 0.0]), big + small


@ti.data_oriented
class ObjectSet:
    """All objects of a scene, queried by signed distance in Taichi funcs.

    Args:
        instances: the objects; their order gives the object index k.
        grid_resolution: samples along the longest side of a padded
            bounding box (cubic cells) for shapes without a closed form.
        band: padding (m) added on every side of a local bounding box before
            sampling; default 10 % of the box's largest extent.
    """

    def __init__(self, instances: list[ObjectInstance], *, grid_resolution: int = 64,
                 band: float | None = None) -> None:
        runtime.ensure_init()
        if grid_resolution < 4:
            raise ValueError(f"grid_resolution must be >= 4 (got {grid_resolution})")
        if band is not None and not band > 0:
            raise ValueError(f"band must be a positive length in m (got {band})")
        self.instances = list(instances)
        self.n = len(self.instances)
        self.names = [inst.name for inst in self.instances]
        nf = max(self.n, 1)
        self._kind = np.full(nf, -1, np.int32)
        par, center, g_org = np.zeros((nf, 3)), np.zeros((nf, 3)), np.zeros((nf, 3))
        bound_r, g_h, g_off = np.zeros(nf), np.ones(nf), np.zeros(nf, np.int32)
        g_res = np.full((nf, 3), 2, np.int32)
        values: list[np.ndarray] = []
        offset = 0
        self._parts: list[list[trimesh.Trimesh] | None] = []
        self.grid_cell = np.zeros(nf)
        """(n,) grid cell size per object, m (0 for primitives)."""
        for k, inst in enumerate(self.instances):
            lo, hi = np.asarray(inst.mesh.bounds, float)
            self._parts.append(_closed_parts(inst.mesh))
            if inst.shape in KINDS:
                self._kind[k] = KINDS[inst.shape]
                par[k], center[k], bound_r[k] = _analytic_layout(inst.shape, inst.params)
                continue
            self._kind[k] = GRID
            org, h, res, vals = self._sample_grid(inst.mesh, self._parts[k], grid_resolution, band)
            g_off[k], g_res[k], g_org[k], g_h[k] = offset, res, org, h
            self.grid_cell[k] = h
            values.append(vals)
            offset += vals.size
            center[k] = 0.5 * (lo + hi)
            bound_r[k] = 0.5 * float(np.linalg.norm(hi - lo))
        self.present = frozenset(int(x) for x in self._kind[: self.n])
        grid_values = np.concatenate(values) if values else np.zeros(1)

        # Static layout.
        self.kind = ti.field(ti.i32, shape=nf)
        """(n,) shape kind of each object (BOX ... GRID)."""
        self.shape_par = ti.Vector.field(3, ti.f32, shape=nf)
        """(n, 3) primitive parameters, m: box half extents; sphere (r); cylinder
        (r, half height); capsule (r, half segment); torus (ring r, tube r)."""
        self.center = ti.Vector.field(3, ti.f32, shape=nf)
        """(n, 3) local centre of the primitive (or of the mesh bounds), m."""
        self.bound_radius = ti.field(ti.f32, shape=nf)
        """(n,) radius of a sphere about ``center`` holding the object, m."""
        self.mu = ti.field(ti.f32, shape=nf)
        """(n,) friction coefficient, dimensionless."""
        self.grid_offset = ti.field(ti.i32, shape=nf)
        """(n,) index of the object's first sample in ``grid_values``."""
        self.grid_res = ti.Vector.field(3, ti.i32, shape=nf)
        """(n, 3) samples per axis (x, y, z) of the object's grid."""
        self.grid_origin = ti.Vector.field(3, ti.f32, shape=nf)
        """(n, 3) local position of sample (0, 0, 0), m."""
        self.grid_h = ti.field(ti.f32, shape=nf)
        """(n,) grid cell size, m."""
        self.grid_values = ti.field(ti.f32, shape=grid_values.size)
        """(total samples,) signed distances, m; sample (i, j, l) of object k is at
        grid_offset[k] + (i * res_y + j) * res_z + l."""
        # Pose and motion.
        self.pos = ti.Vector.field(3, ti.f32, shape=nf)
        """(n, 3) world position of each local origin, m."""
        self.rot = ti.Matrix.field(3, 3, ti.f32, shape=nf)
        """(n, 3, 3) rotation, local to world."""
        self.vel_lin = ti.Vector.field(3, ti.f32, shape=nf)
        """(n, 3) velocity of the local origin over the last pose change, m/s."""
        self.vel_mat = ti.Matrix.field(3, 3, ti.f32, shape=nf)
        """(n, 3, 3) (I - R_prev R^T) / dt, 1/s: the rotational part of the velocity."""

        mu = np.array([i.friction for i in self.instances] + [0.0] * (nf - self.n))
        f32 = [a.astype(np.float32) for a in (par, center, bound_r, mu, g_org, g_h, grid_values)]
        runtime.defer(self._load_static, self._kind, f32[0], f32[1], f32[2], f32[3], g_off, g_res, *f32[4:])

        self._pos, self._vel, self._omega = np.zeros((nf, 3)), np.zeros((nf, 3)), np.zeros((nf, 3))
        self._rot, self._vel_mat = np.tile(np.eye(3), (nf, 1, 1)), np.zeros((nf, 3, 3))
        for k, inst in enumerate(self.instances):
            self._pos[k], self._rot[k] = self._check_pose(inst.position, inst.rotation)
        runtime.defer(self._push_pose)

    # --- build ------------------------------------------------------------------

    @staticmethod
    def _sample_grid(mesh: trimesh.Trimesh, parts, resolution: int, band: float | None):
        """Samples the signed distance over the padded local bounds (float64)."""
        lo, hi = np.asarray(mesh.bounds, float)
        ext = hi - lo
        pad = band if band is not None else 0.1 * float(ext.max())
        h = (float(ext.max()) + 2 * pad) / (resolution - 1)
        res = np.maximum(np.ceil((ext + 2 * pad) / h - 1e-9).astype(int) + 1, 2)
        origin = 0.5 * (lo + hi) - 0.5 * (res - 1) * h
        axes = [origin[i] + h * np.arange(res[i]) for i in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        d, _ = mesh_signed_distance(mesh, pts, parts)
        return origin, h, res.astype(np.int32), d

    @staticmethod
    def _check_pose(position, rotation) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(position, float).reshape(3)
        r = np.asarray(rotation, float).reshape(3, 3)
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
            raise ValueError("rotation must be a proper 3x3 rotation matrix")
        return p, r

    def _push_pose(self) -> None:
        f32 = np.float32
        self._load_pose(self._pos.astype(f32), self._rot.astype(f32), self._vel.astype(f32),
                        self._vel_mat.astype(f32))

    # --- Taichi side ------------------------------------------------------------

    @ti.kernel
    def _load_static(self, kind: ti.types.ndarray(dtype=ti.i32, ndim=1),
                     par: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                     center: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                     bound_r: ti.types.ndarray(dtype=ti.f32, ndim=1),
                     mu: ti.types.ndarray(dtype=ti.f32, ndim=1),
                     g_off: ti.types.ndarray(dtype=ti.i32, ndim=1),
                     g_res: ti.types.ndarray(dtype=ti.math.ivec3, ndim=1),
                     g_org: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                     g_h: ti.types.ndarray(dtype=ti.f32, ndim=1),
                     values: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for k in range(kind.shape[0]):
            self.kind[k] = kind[k]
            self.shape_par[k] = par[k]
            self.center[k] = center[k]
            self.bound_radius[k] = bound_r[k]
            self.mu[k] = mu[k]
            self.grid_offset[k] = g_off[k]
            self.grid_res[k] = g_res[k]
            self.grid_origin[k] = g_org[k]
            self.grid_h[k] = g_h[k]
        for i in range(values.shape[0]):
            self.grid_values[i] = values[i]

    @ti.kernel
    def _load_pose(self, pos: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                   rot: ti.types.ndarray(dtype=ti.math.mat3, ndim=1),
                   vel: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                   vel_mat: ti.types.ndarray(dtype=ti.math.mat3, ndim=1)):
        for k in range(pos.shape[0]):
            self.pos[k] = pos[k]
            self.rot[k] = rot[k]
            self.vel_lin[k] = vel[k]
            self.vel_mat[k] = vel_mat[k]

    @ti.func
    def _grid_sdf(self, k, q):
        """Trilinear grid distance (m) and normal at local point q (m)."""
        o = self.grid_origin[k]
        h = self.grid_h[k]
        res = self.grid_res[k]
        off = self.grid_offset[k]
        qc = ti.math.clamp(q, o, o + (res - 1).cast(ti.f32) * h)
        g = (qc - o) / h
        i0 = ti.math.clamp(ti.floor(g).cast(ti.i32), 0, res - 2)
        t = ti.math.clamp(g - i0.cast(ti.f32), 0.0, 1.0)
        sy, sx = res.z, res.y * res.z
        base = off + i0.x * sx + i0.y * sy + i0.z
        c000 = self.grid_values[base]
        c001 = self.grid_values[base + 1]
        c010 = self.grid_values[base + sy]
        c011 = self.grid_values[base + sy + 1]
        c100 = self.grid_values[base + sx]
        c101 = self.grid_values[base + sx + 1]
        c110 = self.grid_values[base + sx + sy]
        c111 = self.grid_values[base + sx + sy + 1]
        # Interpolate along x, then y, then z; derivatives of the same steps.
        a00 = c000 + t.x * (c100 - c000)
        a10 = c010 + t.x * (c110 - c010)
        a01 = c001 + t.x * (c101 - c001)
        a11 = c011 + t.x * (c111 - c011)
        b0 = a00 + t.y * (a10 - a00)
        b1 = a01 + t.y * (a11 - a01)
        value = b0 + t.z * (b1 - b0)
        dx0 = (c100 - c000) + t.y * ((c110 - c010) - (c100 - c000))
        dx1 = (c101 - c001) + t.y * ((c111 - c011) - (c101 - c001))
        grad = ti.math.vec3(
            dx0 + t.z * (dx1 - dx0),
            (a10 - a00) + t.z * ((a11 - a01) - (a10 - a00)),
            b1 - b0,
        ) / h
        out = q - qc
        dist_out = out.norm()
        d, n = value, _safe_normalized(grad, ti.math.vec3(0.0, 1.0, 0.0))
        if dist_out > 0.0:
            d = value + dist_out
            n = out / dist_out
        return d, n

    @ti.func
    def _local_sdf(self, k, q):
        """Distance (m) and local normal of object k at local point q (m)."""
        kind = self.kind[k]
        par = self.shape_par[k]
        qc = q - self.center[k]
        d = FAR
        n = ti.math.vec3(0.0, 1.0, 0.0)
        if ti.static(BOX in self.present):
            if kind == BOX:
                d, n = sdf_box(qc, par)
        if ti.static(SPHERE in self.present):
            if kind == SPHERE:
                d, n = sdf_sphere(qc, par.x)
        if ti.static(CYLINDER in self.present):
            if kind == CYLINDER:
                d, n = sdf_cylinder(qc, par.x, par.y)
        if ti.static(CAPSULE in self.present):
            if kind == CAPSULE:
                d, n = sdf_capsule(qc, par.x, par.y)
        if ti.static(TORUS in self.present):
            if kind == TORUS:
                d, n = sdf_torus(qc, par.x, par.y)
        if ti.static(GRID in self.present):
            if kind == GRID:
                d, n = self._grid_sdf(k, q)
        return d, n

    @ti.func
    def query(self, p):
        """Signed distance to the nearest object at world point p (m).

        Returns:
            (d, n, k): distance in m (negative inside), outward unit normal in
            world coordinates, object index (-1 and FAR without objects).
        """
        best_d, best_n, best_k = FAR, ti.math.vec3(0.0, 1.0, 0.0), -1
        for k in range(self.n):
            R = self.rot[k]
            q = R.transpose() @ (p - self.pos[k])
            # A point farther than best_d from the bounding sphere cannot win.
            if (q - self.center[k]).norm() - self.bound_radius[k] < best_d:
                d, n = self._local_sdf(k, q)
                if d < best_d:
                    best_d, best_n, best_k = d, R @ n, k
        return best_d, best_n, best_k

    @ti.func
    def query_within(self, p, cutoff):
        """``query`` for contacts: objects whose bounding sphere is farther than
        ``cutoff`` (m) from p are skipped without evaluating their distance, and
        (FAR, up, -1) comes back when none is that close. Most particles of a
        large cloth are far from every object: they cost one sphere test each.
        """
        best_d, best_n, best_k = FAR, ti.math.vec3(0.0, 1.0, 0.0), -1
        for k in range(self.n):
            R = self.rot[k]
            q = R.transpose() @ (p - self.pos[k])
            if (q - self.center[k]).norm() - self.bound_radius[k] < ti.min(best_d, cutoff):
                d, n = self._local_sdf(k, q)
                if d < best_d:
                    best_d, best_n, best_k = d, R @ n, k
        return best_d, best_n, best_k

    @ti.func
    def velocity_at(self, k, p):
        """Velocity (m/s) of object k's material point now at world point p (m).

        It is the backward difference over the last ``set_pose``: zero for an
        object that was never moved.
        """
        return self.vel_lin[k] + self.vel_mat[k] @ (p - self.pos[k])

    @ti.func
    def friction(self, k):
        """Friction coefficient of object k (dimensionless)."""
        return self.mu[k]

    @ti.kernel
    def _query_kernel(self, pts: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                      d: ti.types.ndarray(dtype=ti.f32, ndim=1),
                      n: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                      k: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(pts.shape[0]):
            d[i], n[i], k[i] = self.query(pts[i])

    @ti.kernel
    def _velocity_kernel(self, k: ti.i32, pts: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                         v: ti.types.ndarray(dtype=ti.math.vec3, ndim=1)):
        for i in range(pts.shape[0]):
            v[i] = self.velocity_at(k, pts[i])

    # --- Python side ------------------------------------------------------------

    def __len__(self) -> int:
        return self.n

    def index(self, name: str) -> int:
        """Index of the object called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no object {name!r}; objects: {', '.join(self.names) or '(none)'}") from None

    def _check_k(self, k: int) -> int:
        if not 0 <= k < self.n:
            raise IndexError(f"object index {k} out of range (0..{self.n - 1})")
        return k

    def set_pose(self, k: int, position, rotation, dt: float) -> None:
        """Moves object k and records its velocity over the step.

        Args:
            k: object index.
            position: (3,) new world position of the local origin, m.
            rotation: (3, 3) new rotation, local to world.
            dt: time since the previous pose, s (> 0).
        """
        self._check_k(k)
        if not dt > 0:
            raise ValueError(f"dt must be positive (got {dt}); use place() to teleport")
        p, r = self._check_pose(position, rotation)
        self._vel[k] = (p - self._pos[k]) / dt
        self._vel_mat[k] = (np.eye(3) - self._rot[k] @ r.T) / dt
        rel = r @ self._rot[k].T
        angle = np.arccos(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0))
        axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
        s = np.linalg.norm(axis)
        self._omega[k] = axis / s * angle / dt if s > 1e-12 else np.zeros(3)
        self._pos[k], self._rot[k] = p, r
        self._push_pose()

    def place(self, k: int, position, rotation) -> None:
        """Sets the pose of object k without motion (velocity becomes zero)."""
        self._check_k(k)
        self._pos[k], self._rot[k] = self._check_pose(position, rotation)
        self._vel[k] = 0.0
        self._omega[k] = 0.0
        self._vel_mat[k] = 0.0
        self._push_pose()

    def pose(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) m, rotation (3, 3)) of object k."""
        self._check_k(k)
        return self._pos[k].copy(), self._rot[k].copy()

    def velocity(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(linear velocity of the origin m/s, angular velocity rad/s) of object k."""
        self._check_k(k)
        return self._vel[k].copy(), self._omega[k].copy()

    def world_mesh(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Object k's mesh at its pose: (vertices (n, 3) float32 m, faces (m, 3) int32)."""
        self._check_k(k)
        mesh = self.instances[k].mesh
        verts = np.asarray(mesh.vertices) @ self._rot[k].T + self._pos[k]
        return verts.astype(np.float32), np.asarray(mesh.faces, np.int32)

    def query_numpy(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Runs ``query`` on a batch of world points (m), (n, 3).

        Returns:
            (d (n,) float32 m, normals (n, 3) float32, k (n,) int32).
        """
        pts = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
        d = np.empty(len(pts), np.float32)
        n = np.empty((len(pts), 3), np.float32)
        k = np.empty(len(pts), np.int32)
        if len(pts):
            self._query_kernel(pts, d, n, k)
        return d, n, k

    def velocity_numpy(self, k: int, points) -> np.ndarray:
        """Runs ``velocity_at`` for object k on world points (n, 3) m; returns m/s."""
        self._check_k(k)
        pts = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
        v = np.empty((len(pts), 3), np.float32)
        if len(pts):
            self._velocity_kernel(k, pts, v)
        return v

    def reference_numpy(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact signed distance to the object meshes (igl), for tests.

        Primitives are measured against their triangle mesh, so they differ
        from ``query`` by the tessellation error.

        Returns:
            (d (n,) float64 m, normals (n, 3), k (n,)), as ``query_numpy``.
        """
        pts = np.asarray(points, float).reshape(-1, 3)
        best = np.full(len(pts), FAR)
        normal = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
        index = np.full(len(pts), -1, np.int32)
        for k, inst in enumerate(self.instances):
            local = (pts - self._pos[k]) @ self._rot[k]
            d, c = mesh_signed_distance(inst.mesh, local, self._parts[k])
            v = local - c
            norm = np.linalg.norm(v, axis=1, keepdims=True)
            nl = np.where(norm > _EPS, v / np.maximum(norm, _EPS), 0.0) * np.where(d < 0, -1.0, 1.0)[:, None]
            better = d < best
            best[better] = d[better]
            normal[better] = (nl @ self._rot[k].T)[better]
            index[better] = k
        return best, normal, index
