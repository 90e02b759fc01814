"""Vertex and visibility passes of the software rasterizer (Taichi kernels).

The visibility buffer stores one int64 per pixel: the view depth's float32 bit
pattern (monotonic for depths >= 0) in the high 32 bits and the triangle id in
the low 32 bits. ``ti.atomic_min`` therefore keeps the nearest surface, and on
equal depths the lowest triangle id, whatever the thread order. GPUs need
64-bit atomics (CUDA has them; most Vulkan/Metal devices do not). The key
light's shadow map holds the depth bits alone, in int32.

Triangles are rasterised in parallel over triangles, each testing the pixel
centres of its clipped bounding box. Triangles whose box exceeds ``max_box``
pixels go to a list that a second loop rasterises in parallel over (triangle,
row) pairs, so a few big triangles do not serialise a thread. Triangles with a
vertex closer to the eye than the near distance are skipped, not clipped.
"""

import taichi as ti

vec3 = ti.types.vector(3, ti.f32)
ivec3 = ti.types.vector(3, ti.i32)

#: Empty camera visibility entry (largest int64) and empty shadow-map entry (largest int32).
EMPTY = 9223372036854775807
EMPTY32 = 2147483647
#: Bits of ``item_flags``.
FLAG_TWO_SIDED = 1
FLAG_SMOOTH = 2

#: Layout of the per-frame parameter block (float32): one array instead of many
#: vector kernel arguments, whose marshalling costs about 0.1 ms each.
P_EYE, P_RIGHT, P_UP, P_FWD = 0, 3, 6, 9  # camera position (m) and unit frame
P_CAM = 12  # focal length px, W / 2 px, H / 2 px
P_LCENTRE, P_LRIGHT, P_LUP, P_LDIR = 15, 18, 21, 24  # light frame: centre (m), unit axes, towards the light
P_LIGHT = 27  # shadow-map half-width m, shadow-map size px, camera near m
P_GROUND = 30  # has ground 0/1, ground height m, checker cell m
P_LBOX = 33  # shadow-map texels geometry can cover: u0, v0, u1, v1
P_SHADOWS = 37  # 1 to sample the shadow map
P_SIZE = 40

PARAMS = ti.types.ndarray(dtype=ti.f32, ndim=1)
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
I3 = ti.types.ndarray(dtype=ivec3, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
VIS = ti.types.ndarray(dtype=ti.i64, ndim=1)
SMAP = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def param3(prm: ti.template(), k: ti.template()) -> vec3:
    """The 3-vector at offset k of the parameter block."""
    return vec3(prm[k], prm[k + 1], prm[k + 2])


@ti.kernel
def face_normals(pos: V3, tri: I3, fnrm: V3):
    """Area-weighted face normals (m,) (twice the area in m^2 times the unit normal)."""
    for f in range(tri.shape[0]):
        t = tri[f]
        fnrm[f] = (pos[t[1]] - pos[t[0]]).cross(pos[t[2]] - pos[t[0]])


@ti.kernel
def transform(
    pos: V3,
    fnrm: V3,
    adj_face: I1,
    adj_off: I1,
    nrm: V3,
    scr: V3,
    lsc: V3,
    prm: PARAMS,
):
    """Project every vertex to the camera and to the key light's shadow map.

    Args:
        pos: (n,) world positions in m.
        fnrm: (m,) area-weighted face normals.
        adj_face, adj_off: faces around each vertex (CSR: vertex i owns
            ``adj_face[adj_off[i]:adj_off[i + 1]]``), summed in a fixed order
            so normals are deterministic.
        nrm: (n,) out: unit vertex normals.
        scr: (n,) out: pixel x, pixel y, 1/z (1/m; -1 when closer than near).
        lsc: (n,) out: shadow-map pixel x, y and depth from the light plane in m.
        prm: (P_SIZE,) parameter block: camera, light frame and ``P_LIGHT``.
    """
    eye, right, up = param3(prm, P_EYE), param3(prm, P_RIGHT), param3(prm, P_UP)
    fwd, cam = param3(prm, P_FWD), param3(prm, P_CAM)
    centre, lright = param3(prm, P_LCENTRE), param3(prm, P_LRIGHT)
    lup, ldir = param3(prm, P_LUP), param3(prm, P_LDIR)
    light = param3(prm, P_LIGHT)
    for i in range(pos.shape[0]):
        n = vec3(0.0, 0.0, 0.0)
        for k in range(adj_off[i], adj_off[i + 1]):
            n += fnrm[adj_face[k]]
        nrm[i] = n / ti.max(n.norm(), 1e-30)
        d = pos[i] - eye
        z = d.dot(fwd)
        s = vec3(0.0, 0.0, -1.0)
        if z > light[2]:
            s = vec3(cam[1] + cam[0] * d.dot(right) / z, cam[2] - cam[0] * d.dot(up) / z, 1.0 / z)
        scr[i] = s
        c = pos[i] - centre
        half = 0.5 * light[1] / light[0]
        u = 0.5 * light[1] + half * c.dot(lright)
        v = 0.5 * light[1] - half * c.dot(lup)
        lsc[i] = vec3(u, v, ti.max(light[0] - c.dot(ldir), 0.0))


@ti.func
def edge(u, v, px: ti.f32, py: ti.f32) -> ti.f32:
    """Twice the signed area of (u, v, p); exact negation when u and v swap."""
    return (u[0] - px) * (v[1] - py) - (u[1] - py) * (v[0] - px)


@ti.func
def pack(z: ti.f32, f: ti.i32) -> ti.i64:
    """Depth bits (high) and triangle id (low) in one int64."""
    return (ti.cast(ti.bit_cast(ti.max(z, 0.0), ti.i32), ti.i64) << 32) | ti.cast(f, ti.i64)


@ti.func
def bbox(a, b, c, w: ti.i32, h: ti.i32):
    """Pixel range whose centres may lie in the triangle, clipped to the image."""
    x0 = ti.max(ti.cast(ti.ceil(ti.min(a[0], b[0], c[0]) - 0.5), ti.i32), 0)
    x1 = ti.min(ti.cast(ti.floor(ti.max(a[0], b[0], c[0]) - 0.5), ti.i32), w - 1)
    y0 = ti.max(ti.cast(ti.ceil(ti.min(a[1], b[1], c[1]) - 0.5), ti.i32), 0)
    y1 = ti.min(ti.cast(ti.floor(ti.max(a[1], b[1], c[1]) - 0.5), ti.i32), h - 1)
    return x0, x1, y0, y1


@ti.func
def raster_row(
    buf: ti.template(), a, b, c, f: ti.i32, y: ti.i32, x0: ti.i32, x1: ti.i32, w: ti.i32, camera: ti.template()
):
    """Cover the pixel centres of row y in [x0, x1] inside triangle f.

    Edge functions are planes e_k = A_k x + B_k y + C_k built so that the two
    triangles sharing an edge get exactly opposite values there: every pixel
    centre on a shared edge goes to at least one of them (no cracks).
    ``camera`` (static): perspective depth (1/z interpolated) packed with the
    triangle id into int64; otherwise orthographic depth bits only, in int32.
    """
    area = edge(a, b, c[0], c[1])
    sgn = 1.0 if area > 0 else -1.0
    ea = vec3(b[1] - c[1], c[1] - a[1], a[1] - b[1])
    eb = vec3(c[0] - b[0], a[0] - c[0], b[0] - a[0])
    ec = vec3(b[0] * c[1] - b[1] * c[0], c[0] * a[1] - c[1] * a[0], a[0] * b[1] - a[1] * b[0])
    # depth attribute about vertex a (no cancellation): z = a.z + dzx (x - a.x) + dzy (y - a.y)
    d1, d2 = b[2] - a[2], c[2] - a[2]
    dzx = (ea[1] * d1 + ea[2] * d2) / area
    dzy = (eb[1] * d1 + eb[2] * d2) / area
    ea, eb, ec = ea * sgn, eb * sgn, ec * sgn
    py = ti.cast(y, ti.f32) + 0.5
    er = eb * py + ec
    dr = a[2] + dzy * (py - a[1])
    row = y * w
    for x in range(x0, x1 + 1):
        px = ti.cast(x, ti.f32) + 0.5
        e = ea * px + er
        if e[0] >= 0 and e[1] >= 0 and e[2] >= 0:
            z = dr + dzx * (px - a[0])
            if ti.static(camera):
                key = pack(1.0 / z, f)
                if key < buf[row + x]:  # plain read first: most hidden fragments skip the atomic
                    ti.atomic_min(buf[row + x], key)
            else:
                bits = ti.bit_cast(ti.max(z, 0.0), ti.i32)
                if bits < buf[row + x]:
                    ti.atomic_min(buf[row + x], bits)


@ti.func
def setup(scr: ti.template(), tri: ti.template(), f: ti.i32, camera: ti.template()):
    """Screen vertices of triangle f and whether it can be drawn (in front, not degenerate)."""
    t = tri[f]
    a, b, c = scr[t[0]], scr[t[1]], scr[t[2]]
    ok = ti.abs(edge(a, b, c[0], c[1])) > 1e-12
    if ti.static(camera):
        if a[2] <= 0 or b[2] <= 0 or c[2] <= 0:
            ok = False
    return a, b, c, ok


@ti.kernel
def rasterize(
    scr: V3,
    tri: I3,
    face_item: I1,
    item_flags: I1,
    buf: ti.types.ndarray(ndim=1),
    w: ti.i32,
    h: ti.i32,
    large: I1,
    n_large: I1,
    max_box: ti.i32,
    camera: ti.template(),
):
    """Clear ``buf`` and rasterise every triangle into it.

    Args:
        scr: (n,) screen vertices: x px, y px and a depth attribute (1/z in 1/m
            for the camera, z in m for the light).
        tri: (m,) vertex indices.
        face_item, item_flags: item of each face and its flags; the camera pass
            culls back faces of items without ``FLAG_TWO_SIDED``.
        buf: (h * w,) row-major; camera: int64 keys (depth bits << 32 | triangle
            id); light: int32 depth bits.
        w, h: buffer size in pixels.
        large: (m,) scratch: triangles deferred to the row-parallel loop;
            ``n_large[0]`` their count.
        max_box: largest pixel bounding box rasterised by one thread.
        camera: static flag selecting the pass (see ``buf``).
    """
    for i in range(h * w):
        if ti.static(camera):
            buf[i] = ti.i64(EMPTY)
        else:
            buf[i] = EMPTY32
    n_large[0] = 0
    for f in range(tri.shape[0]):
        a, b, c, ok = setup(scr, tri, f, camera)
        if ti.static(camera):
            if ok and (item_flags[face_item[f]] & FLAG_TWO_SIDED) == 0:
                ok = edge(a, b, c[0], c[1]) < 0  # front faces wind clockwise on screen (y down)
        if ok:
            x0, x1, y0, y1 = bbox(a, b, c, w, h)
            if x1 >= x0 and y1 >= y0:
                if (x1 - x0 + 1) * (y1 - y0 + 1) > max_box:
                    large[ti.atomic_add(n_large[0], 1)] = f
                else:
                    for y in range(y0, y1 + 1):
                        raster_row(buf, a, b, c, f, y, x0, x1, w, camera)
    for k in range(n_large[0] * h):  # deferred triangles: one (triangle, row) pair each
        f = large[k // h]
        y = k % h
        a, b, c, ok = setup(scr, tri, f, camera)
        x0, x1, y0, y1 = bbox(a, b, c, w, h)
        if y0 <= y <= y1:
            raster_row(buf, a, b, c, f, y, x0, x1, w, camera)
