"""The software renderer: one vertex, visibility and shading pass per frame."""

from __future__ import annotations

import time

import numpy as np
import taichi as ti

from sandbox.runtime import ensure_init
from shaders import raster, shading
from shaders.camera import Camera, auto_camera, light_frame
from shaders.scene import RenderScene, ground_cell_for

#: Triangles with a bigger pixel bounding box are rasterised row-parallel.
MAX_BOX = 1024
#: Shadow-map half-width over the scene radius: leaves an empty border of texels.
SHADOW_MARGIN = 1.08


def _linear(rgb) -> np.ndarray:
    """Display colour in [0, 1] to linear RGB (gamma 2, matching the output)."""
    return np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0) ** 2


def bounds(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding-box min and max (3,) float64 of (n, 3) points (per column: numpy's axis-0 reduction is slow)."""
    lo = np.array([verts[:, k].min() for k in range(3)], dtype=np.float64)
    hi = np.array([verts[:, k].max() for k in range(3)], dtype=np.float64)
    return lo, hi


@ti.data_oriented
class Renderer:
    """Draws a ``RenderScene`` into an RGB image, on whatever backend Taichi runs.

    Buffers are allocated here, once per image size, and the per-frame mesh
    buffers once per vertex/face count; every pass is one kernel launch over
    all meshes together. Mesh buffers (``_buf``), n vertices and m faces of all
    items concatenated: ``pos`` (n,) vec3 m; ``nrm`` (n,) unit normals; ``scr``
    (n,) pixel x, pixel y, 1/z (1/m); ``lsc`` (n,) shadow-map texel x, y and
    light depth (m); ``tri`` (m,) ivec3 vertex ids; ``fnrm`` (m,) area-weighted
    face normals (m^2); ``face_item`` (m,) item index; ``adj_face`` (3m,) and
    ``adj_off`` (n+1,) faces around each vertex; ``large`` (m,) and ``n_large``
    (1,) rasteriser scratch; ``front``, ``back`` (items,) linear colours and
    ``flags`` (items,) ``raster.FLAG_*``.

    Args:
        width, height: image size in pixels.
        shadows: draw the key light's soft shadow.
        shadow_size: shadow-map resolution in pixels (square).
        light_dir: direction towards the key light; None follows the camera.
    """

    def __init__(
        self,
        width: int = 640,
        height: int = 480,
        *,
        shadows: bool = True,
        shadow_size: int = 384,
        light_dir: tuple[float, float, float] | None = None,
    ) -> None:
        ensure_init()
        self.width, self.height = int(width), int(height)
        self.shadows = bool(shadows)
        self.shadow_size = int(shadow_size)
        self.light_dir = light_dir
        self.camera: Camera | None = None
        self.stage_ms: dict[str, float] = {}
        #: (H * W,) int64 camera visibility buffer, row-major: view depth (m,
        #: float32 bits) << 32 | triangle id.
        self.vis = ti.ndarray(ti.i64, self.height * self.width)
        #: (S * S,) int32 shadow map, row-major: depth from the light plane (m, float32 bits).
        self.smap = ti.ndarray(ti.i32, self.shadow_size**2 if shadows else 1)
        #: (LUT_SIZE,) uint8 tone curve and gamma, linear intensity -> display byte.
        self.lut = ti.ndarray(ti.u8, shading.LUT_SIZE)
        self.lut.from_numpy(shading.tone_lut())
        n = self.height * self.width
        #: (H * W,) vec3 f32 background per pixel: linear colour without the key light,
        #: the key light's contribution, and (ground x m, ground z m, view depth m or
        #: 3e38 for the sky); kept while camera, light and ground stay the same.
        self.bg_a = ti.Vector.ndarray(3, ti.f32, shape=n)
        self.bg_b = ti.Vector.ndarray(3, ti.f32, shape=n)
        self.bg_g = ti.Vector.ndarray(3, ti.f32, shape=n)
        self._bg_key: tuple | None = None
        self._last_view: tuple | None = None
        self._buf: dict[str, ti.Ndarray] = {}
        self._topology: tuple | None = None
        self._faces = np.zeros((0, 3), np.int32)
        self._materials: list | None = None

    # ------------------------------------------------------------------ buffers
    def _ndarray(self, name: str, n: int, kind: str) -> ti.Ndarray:
        """The named per-frame buffer with n entries, reallocated when n changes."""
        arr = self._buf.get(name)
        if arr is None or arr.shape[0] != n:
            if kind == "v3":
                arr = ti.Vector.ndarray(3, ti.f32, shape=n)
            elif kind == "i3":
                arr = ti.Vector.ndarray(3, ti.i32, shape=n)
            else:
                arr = ti.ndarray(ti.i32, shape=n)
            self._buf[name] = arr
        return arr

    def _upload(self, scene: RenderScene) -> tuple[np.ndarray, np.ndarray]:
        """Copy the frame's meshes into the buffers; returns the bbox min and max (m).

        Positions are copied every frame; faces, vertex-face adjacency and
        materials only when they change.
        """
        items = [it for it in scene.items if len(it.faces)]
        if items:
            verts = np.concatenate([it.verts for it in items]) if len(items) > 1 else items[0].verts
            offsets = np.cumsum([0] + [len(it.verts) for it in items[:-1]])
            faces = np.concatenate([it.faces + np.int32(off) for it, off in zip(items, offsets)])
            counts = [len(it.faces) for it in items]
        else:  # one degenerate triangle keeps every buffer non-empty
            verts, faces, counts = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.int32), [1]
        nv, nf = len(verts), len(faces)
        pos = self._ndarray("pos", nv, "v3")
        for name in ("nrm", "scr", "lsc"):
            self._ndarray(name, nv, "v3")
        self._ndarray("fnrm", nf, "v3")
        self._ndarray("large", nf, "i1")
        self._ndarray("n_large", 1, "i1")
        pos.from_numpy(verts)
        topology = (nv, tuple(counts))
        if self._topology != topology or not np.array_equal(self._faces, faces):
            self._ndarray("tri", nf, "i3").from_numpy(faces)
            self._ndarray("face_item", nf, "i1").from_numpy(np.repeat(np.arange(len(counts), dtype=np.int32), counts))
            corner_v = faces.reshape(-1)
            order = np.argsort(corner_v, kind="stable")
            self._ndarray("adj_face", 3 * nf, "i1").from_numpy((order // 3).astype(np.int32))
            off = np.searchsorted(corner_v[order], np.arange(nv + 1)).astype(np.int32)
            self._ndarray("adj_off", nv + 1, "i1").from_numpy(off)
            self._topology, self._faces = topology, faces
        materials = [(tuple(it.color), it.back(), it.two_sided, it.smooth) for it in items]
        materials = materials or [((0, 0, 0), (0, 0, 0), False, False)]
        if materials != self._materials:
            n = len(materials)
            self._ndarray("front", n, "v3").from_numpy(np.stack([_linear(m[0]) for m in materials]))
            self._ndarray("back", n, "v3").from_numpy(np.stack([_linear(m[1]) for m in materials]))
            flags = [raster.FLAG_TWO_SIDED * bool(m[2]) + raster.FLAG_SMOOTH * bool(m[3]) for m in materials]
            self._ndarray("flags", n, "i1").from_numpy(np.array(flags, np.int32))
            self._materials = materials
        return bounds(verts)

    # ------------------------------------------------------------------ passes
    def _mark(self, name: str, t0: float, profile: bool) -> float:
        if not profile:
            return t0
        ti.sync()
        t1 = time.perf_counter()
        self.stage_ms[name] = (t1 - t0) * 1e3
        return t1

    def render(self, scene: RenderScene, camera: Camera | None = None, *, profile: bool = False) -> np.ndarray:
        """Render the scene.

        Args:
            scene: meshes and ground.
            camera: the view; None frames the scene automatically.
            profile: record per-stage milliseconds in ``stage_ms`` (adds syncs).

        Returns:
            (height, width, 3) uint8 RGB image, row 0 at the top.
        """
        cam = camera if camera is not None else auto_camera(scene, self.width / self.height)
        self.camera = cam
        t0 = time.perf_counter()
        lo, hi = self._upload(scene)
        t0 = self._mark("upload", t0, profile)
        b, prm = self._buf, self._params(scene, cam, lo, hi)
        raster.face_normals(b["pos"], b["tri"], b["fnrm"])
        raster.transform(b["pos"], b["fnrm"], b["adj_face"], b["adj_off"], b["nrm"], b["scr"], b["lsc"], prm)
        t0 = self._mark("vertex", t0, profile)
        self._rasterize(b["scr"], self.vis, self.width, self.height, camera=True)
        t0 = self._mark("raster", t0, profile)
        if self.shadows:
            self._rasterize(b["lsc"], self.smap, self.shadow_size, self.shadow_size, camera=False)
            t0 = self._mark("shadow", t0, profile)
        cached = self._background(prm)
        t0 = self._mark("background", t0, profile)
        out = np.empty(self.height * self.width * 3, np.uint8)  # the kernel writes it in place on the CPU
        shading.shade(
            self.vis, self.smap, self.bg_a, self.bg_b, self.bg_g, b["pos"], b["nrm"], b["scr"], b["tri"],
            b["face_item"], b["flags"], b["front"], b["back"], b["fnrm"], self.lut, out, prm, cached,
        )  # fmt: skip
        self._mark("shade", t0, profile)
        return out.reshape(self.height, self.width, 3)

    def _params(self, scene: RenderScene, cam: Camera, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The frame's parameter block (``raster.P_*`` layout), float32."""
        prm = np.zeros(raster.P_SIZE, np.float32)
        eye, right, up, fwd = cam.basis()
        for k, v in ((raster.P_EYE, eye), (raster.P_RIGHT, right), (raster.P_UP, up), (raster.P_FWD, fwd)):
            prm[k : k + 3] = v
        prm[raster.P_CAM : raster.P_CAM + 3] = (cam.focal(self.height), 0.5 * self.width, 0.5 * self.height)
        self._light(prm, cam, fwd, right, lo, hi)
        if scene.ground_height is not None:
            radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
            cell = scene.ground_cell or ground_cell_for(radius)
            prm[raster.P_GROUND : raster.P_GROUND + 3] = (1.0, scene.ground_height, cell)
        else:
            prm[raster.P_GROUND : raster.P_GROUND + 3] = (0.0, 0.0, 1.0)
        prm[raster.P_SHADOWS] = float(self.shadows)
        return prm

    def _background(self, prm: np.ndarray) -> bool:
        """Whether the cached sky and ground hold for this frame, filling the cache if due.

        The first view, and any view seen in two frames running, is cached; a
        camera that moves every frame is shaded inline instead (writing the
        cache would cost more).
        """
        key = (prm[: raster.P_CAM + 3].tobytes(), prm[raster.P_LDIR : raster.P_LDIR + 3].tobytes(),
               prm[raster.P_GROUND : raster.P_GROUND + 3].tobytes())  # fmt: skip
        if key == self._bg_key:
            return True
        if self._bg_key is None or key == self._last_view:
            shading.background(self.bg_a, self.bg_b, self.bg_g, self.width, prm)
            self._bg_key = key
            return True
        self._last_view = key
        return False

    def _light(
        self, prm: np.ndarray, cam: Camera, fwd: np.ndarray, right: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> None:
        """Fill the key-light part of the parameter block.

        The orthographic shadow map covers the scene's bounding sphere with a
        margin; ``P_LBOX`` receives the texels the bounding box can cover.
        """
        centre = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        ldir = light_frame(fwd, right, self.light_dir)
        lright = np.cross(-ldir, [0.0, 1.0, 0.0] if abs(ldir[1]) < 0.99 else [1.0, 0.0, 0.0])
        lright /= np.linalg.norm(lright)
        lup = np.cross(lright, -ldir)
        # steady shadows while the scene moves: the map's size takes 2^(k/4) steps
        # and its centre snaps to whole texels (the margin absorbs the shift)
        half = SHADOW_MARGIN * 2.0 ** (np.ceil(4.0 * np.log2(radius)) / 4.0)
        texel = 2.0 * half / self.shadow_size
        for axis in (lright, lup):
            d = float(centre @ axis)
            centre = centre + (np.round(d / texel) * texel - d) * axis
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        scale = 0.5 * self.shadow_size / half
        u = 0.5 * self.shadow_size + scale * (corners - centre) @ lright
        v = 0.5 * self.shadow_size - scale * (corners - centre) @ lup
        for k, vec in ((raster.P_LCENTRE, centre), (raster.P_LRIGHT, lright), (raster.P_LUP, lup), (raster.P_LDIR, ldir)):
            prm[k : k + 3] = vec
        prm[raster.P_LIGHT : raster.P_LIGHT + 3] = (half, self.shadow_size, cam.near)
        prm[raster.P_LBOX : raster.P_LBOX + 4] = (u.min(), v.min(), u.max(), v.max())

    def _rasterize(self, screen, buf, w: int, h: int, *, camera: bool) -> None:
        b = self._buf
        raster.rasterize(
            screen, b["tri"], b["face_item"], b["flags"], buf, w, h, b["large"], b["n_large"], MAX_BOX, camera
        )

    def visibility(self) -> tuple[np.ndarray, np.ndarray]:
        """The last frame's visibility buffer, decoded.

        Returns:
            Triangle ids (H, W) int64 (-1 where empty; ids count faces across
            the scene's items in order) and view depths (H, W) float32 in m
            (inf where empty).
        """
        key = self.vis.to_numpy().reshape(self.height, self.width)
        empty = key == raster.EMPTY
        ids = np.where(empty, -1, key & 0xFFFFFFFF)
        depth = (key >> 32).astype(np.uint32).view(np.float32).copy()
        depth[empty] = np.inf
        return ids, depth
