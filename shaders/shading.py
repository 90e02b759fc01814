"""Per-pixel shading pass: surfaces from the visibility buffer, ground and sky.

Lighting is computed in linear RGB and displayed through a tone curve and
gamma 2: a directional key light with a soft shadow (percentage-closer
filtering of the shadow map), a dim fill light from the camera, a sky/ground
hemisphere ambient and a small Blinn-Phong highlight. Two-sided items show
their back colour where the geometric normal faces away from the eye, and are
lit from that side. The ground is an analytic plane (ray intersection per
pixel) with a checker that fades out where it would alias, and distance fog.
"""

import numpy as np
import taichi as ti

from shaders.raster import (
    EMPTY,
    FLAG_SMOOTH,
    FLAG_TWO_SIDED,
    I1,
    I3,
    P_CAM,
    P_EYE,
    P_FWD,
    P_GROUND,
    P_LBOX,
    P_LCENTRE,
    P_LDIR,
    P_LIGHT,
    P_LRIGHT,
    P_LUP,
    P_RIGHT,
    P_SHADOWS,
    P_UP,
    PARAMS,
    SMAP,
    V3,
    VIS,
    edge,
    param3,
    vec3,
)

SKY_TOP = (0.32, 0.45, 0.66)  # linear RGB
SKY_HORIZON = (0.72, 0.76, 0.82)
GROUND_A = (0.50, 0.50, 0.50)
GROUND_B = (0.34, 0.35, 0.37)
AMBIENT_SKY = (0.42, 0.46, 0.52)
AMBIENT_GROUND = (0.20, 0.19, 0.18)
WHITE = 1.6  # linear intensity mapped to full white by the tone curve
FOG_CELLS = 90.0  # fog reaches the horizon colour this many checker cells away
LUT_SIZE = 2048
LUT_SCALE = (LUT_SIZE - 1) / WHITE


def tone_lut() -> np.ndarray:
    """(LUT_SIZE,) uint8: linear intensity -> display byte (extended Reinhard, gamma 2)."""
    x = np.arange(LUT_SIZE, dtype=np.float64) / LUT_SCALE
    mapped = x * (1.0 + x / WHITE**2) / (1.0 + x)
    return np.round(np.sqrt(np.clip(mapped, 0.0, 1.0)) * 255.0).astype(np.uint8)


@ti.func
def unpack_depth(key: ti.i64) -> ti.f32:
    """View depth in m stored in a visibility key."""
    return ti.bit_cast(ti.cast(key >> 32, ti.i32), ti.f32)


@ti.func
def shadow(smap: ti.template(), lbox, p, lcentre, lright, lup, ldir, light, bias: ti.f32) -> ti.f32:
    """Fraction of the key light reaching world point p (0 shadowed .. 1 lit).

    Percentage-closer filtering over 4 x 4 texels weighted (1-f, 1, 1, f) per
    axis, a 3-texel box filter that slides smoothly. Points whose footprint
    misses ``lbox`` (the texels any geometry can cover) are lit at once; the
    corners and inner 2 x 2 are tested next, and only a footprint on a shadow
    edge reads all 16 texels.
    """
    size = light[1]
    half = 0.5 * size / light[0]
    c = p - lcentre
    u = 0.5 * size + half * c.dot(lright) - 0.5
    v = 0.5 * size - half * c.dot(lup) - 0.5
    lit = 1.0
    if lbox[0] - 2.0 <= u <= lbox[2] + 1.0 and lbox[1] - 2.0 <= v <= lbox[3] + 1.0:
        db = ti.bit_cast(ti.max(light[0] - c.dot(ldir) - bias, 0.0), ti.i32)  # bits order as depths >= 0
        fu, fv = ti.floor(u), ti.floor(v)
        n = ti.cast(size, ti.i32)
        base = (ti.cast(fv, ti.i32) - 1) * n + ti.cast(fu, ti.i32) - 1  # the map's border is empty: no clamping
        probe = 0
        for j, i in ti.static([(0, 0), (0, 3), (3, 0), (3, 3), (1, 1), (1, 2), (2, 1), (2, 2)]):
            probe += ti.select(db > smap[base + j * n + i], 0, 1)
        lit = ti.cast(probe, ti.f32) * 0.125
        if 0 < probe < 8:
            wx = ti.Vector([1.0 - (u - fu), 1.0, 1.0, u - fu])
            wy = ti.Vector([1.0 - (v - fv), 1.0, 1.0, v - fv])
            acc = 0.0
            for j in ti.static(range(4)):
                row = 0.0
                for i in ti.static(range(4)):
                    row += wx[i] * ti.select(db > smap[base + j * n + i], 0.0, 1.0)
                acc += wy[j] * row
            lit = acc / 9.0
    return lit


@ti.func
def sky(dirn) -> vec3:
    """Background colour seen along a unit ray direction."""
    t = ti.sqrt(ti.min(ti.max(dirn[1], 0.0), 1.0))
    return vec3(SKY_HORIZON) * (1.0 - t) + vec3(SKY_TOP) * t


@ti.func
def lighting(
    n, v, base, p, smap: ti.template(), lbox, lcentre, lright, lup, ldir, light, shadows: ti.i32, bias: ti.f32
):
    """Linear colour of a surface point p with unit normal n seen along -v."""
    ndl = n.dot(ldir)
    s = 1.0
    if shadows and ndl > 0:
        s = shadow(smap, lbox, p + n * bias, lcentre, lright, lup, ldir, light, bias)
    hemi = 0.5 + 0.5 * n[1]
    amb = vec3(AMBIENT_GROUND) * (1.0 - hemi) + vec3(AMBIENT_SKY) * hemi
    key = ti.max(ndl, 0.0) * s
    fill = 0.15 * ti.max(n.dot(v), 0.0)
    hv = (ldir + v).normalized()
    sp = ti.max(n.dot(hv), 0.0)
    for _ in ti.static(range(5)):  # sp ** 32
        sp = sp * sp
    return base * (amb * 0.8 + key * 0.85 + fill) + 0.1 * sp * s


@ti.func
def camera_ray(x: ti.i32, y: ti.i32, right, up, fwd, cam):
    """Unit view ray through the centre of pixel (x, y); cam = (focal px, W/2, H/2)."""
    px = ti.cast(x, ti.f32) + 0.5
    py = ti.cast(y, ti.f32) + 0.5
    return (fwd + ((px - cam[1]) / cam[0]) * right - ((py - cam[2]) / cam[0]) * up).normalized()


@ti.func
def background_pixel(x: ti.i32, y: ti.i32, eye, right, up, fwd, cam, ldir, ground):
    """Sky or ground seen by pixel (x, y), split as A + B * (key-light visibility).

    Returns:
        a: linear colour without the key light (fog included).
        b: the key light's linear contribution (0 for the sky).
        g: ground point x, z (m) and its view depth (m; 3e38 for the sky).
    """
    ray = camera_ray(x, y, right, up, fwd, cam)
    a = sky(ray)
    b = vec3(0.0, 0.0, 0.0)
    g = vec3(0.0, 0.0, 3.0e38)
    if ground[0] > 0 and ray[1] < 0 and eye[1] > ground[1]:
        inv_cell = 1.0 / ground[2]
        tg = (ground[1] - eye[1]) / ray[1]
        p = eye + tg * ray
        cx = ti.cast(ti.floor(p[0] * inv_cell), ti.i32)
        cz = ti.cast(ti.floor(p[2] * inv_cell), ti.i32)
        chk = ti.cast((cx + cz) & 1, ti.f32)
        foot = tg * inv_cell / (cam[0] * ti.max(-ray[1], 1e-3))  # pixel footprint in cells
        chk = 0.5 + (chk - 0.5) * ti.max(1.0 - 1.5 * foot, 0.0)  # fade the checker where it would alias
        base = vec3(GROUND_A) * chk + vec3(GROUND_B) * (1.0 - chk)
        fog = ti.min(tg * inv_cell * (1.0 / FOG_CELLS), 1.0)
        fog = fog * fog
        # matte ground: the lighting model with n = +y and no highlight, fogged towards the horizon
        a = base * (vec3(AMBIENT_SKY) * 0.8 - 0.15 * ray[1]) * (1.0 - fog) + vec3(SKY_HORIZON) * fog
        b = base * (0.85 * ti.max(ldir[1], 0.0) * (1.0 - fog))
        g = vec3(p[0], p[2], tg * ray.dot(fwd))
    return a, b, g


@ti.kernel
def background(
    bg_a: V3,
    bg_b: V3,
    bg_g: V3,
    width: ti.i32,
    prm: PARAMS,
):
    """Cache ``background_pixel`` of every pixel (it depends on camera, light direction and ground only).

    Args:
        bg_a, bg_b, bg_g: (H * W,) out: a, b and g of ``background_pixel``.
        width: image width in pixels.
        prm: (P_SIZE,) parameter block (camera, light direction, ground).
    """
    eye, right, up = param3(prm, P_EYE), param3(prm, P_RIGHT), param3(prm, P_UP)
    fwd, cam = param3(prm, P_FWD), param3(prm, P_CAM)
    ldir, ground = param3(prm, P_LDIR), param3(prm, P_GROUND)
    for y in range(bg_a.shape[0] // width):
        for x in range(width):
            i = y * width + x
            bg_a[i], bg_b[i], bg_g[i] = background_pixel(x, y, eye, right, up, fwd, cam, ldir, ground)


@ti.kernel
def shade(
    vis: VIS,
    smap: SMAP,
    bg_a: V3,
    bg_b: V3,
    bg_g: V3,
    pos: V3,
    nrm: V3,
    scr: V3,
    tri: I3,
    face_item: I1,
    item_flags: I1,
    item_front: V3,
    item_back: V3,
    fnrm: V3,
    lut: ti.types.ndarray(dtype=ti.u8, ndim=1),
    img: ti.types.ndarray(dtype=ti.u8, ndim=1),
    prm: PARAMS,
    cached: ti.template(),
):
    """Shade every pixel into ``img``: the nearer of the visible surface and the background.

    Args:
        vis: (H * W,) camera visibility buffer (row-major, row 0 at the top).
        smap: (S * S,) shadow map: light depth bits (m as float32) per texel.
        bg_a, bg_b, bg_g: the cached background (``background``), read when
            ``cached``; otherwise each pixel computes ``background_pixel``.
        pos, nrm, scr, tri: vertex positions (m), unit normals, screen vertices
            (x px, y px, 1/z) and faces of the frame's meshes.
        face_item, item_flags, item_front, item_back: per-face item, per-item
            flags and linear front/back colours.
        fnrm: (m,) area-weighted face normals (orient the faces).
        lut: (LUT_SIZE,) display byte of each linear intensity step (``tone_lut``).
        img: (H * W * 3,) out: RGB bytes, row-major.
        prm: (P_SIZE,) parameter block: camera, key-light frame, ground, the
            texels geometry can cover and whether to sample shadows.
        cached: static flag, see ``bg_a``.
    """
    eye, right, up = param3(prm, P_EYE), param3(prm, P_RIGHT), param3(prm, P_UP)
    fwd, cam = param3(prm, P_FWD), param3(prm, P_CAM)
    lcentre, lright = param3(prm, P_LCENTRE), param3(prm, P_LRIGHT)
    lup, ldir = param3(prm, P_LUP), param3(prm, P_LDIR)
    light, ground = param3(prm, P_LIGHT), param3(prm, P_GROUND)
    lbox = ti.Vector([prm[P_LBOX], prm[P_LBOX + 1], prm[P_LBOX + 2], prm[P_LBOX + 3]])
    shadows = prm[P_SHADOWS] > 0.5
    bias = 1.5 * 2.0 * light[0] / light[1]
    width = ti.cast(2.0 * cam[1] + 0.5, ti.i32)
    for y in range(vis.shape[0] // width):  # rows in parallel: loop invariants stay hoisted
        for x in range(width):
            i = y * width + x
            key = vis[i]
            col, bk, g = vec3(0.0), vec3(0.0), vec3(0.0)
            if ti.static(cached):
                col, g = bg_a[i], bg_g[i]
            else:
                col, bk, g = background_pixel(x, y, eye, right, up, fwd, cam, ldir, ground)
            if key != ti.i64(EMPTY) and unpack_depth(key) < g[2]:
                ray = camera_ray(x, y, right, up, fwd, cam)
                px = ti.cast(x, ti.f32) + 0.5
                py = ti.cast(y, ti.f32) + 0.5
                f = ti.cast(key & ti.i64(0xFFFFFFFF), ti.i32)
                t = tri[f]
                a, b, c = scr[t[0]], scr[t[1]], scr[t[2]]
                w = vec3(edge(b, c, px, py) * a[2], edge(c, a, px, py) * b[2], edge(a, b, px, py) * c[2])
                w = w / (w[0] + w[1] + w[2])  # perspective-correct barycentrics
                p = w[0] * pos[t[0]] + w[1] * pos[t[1]] + w[2] * pos[t[2]]
                ng = fnrm[f]
                item = face_item[f]
                flags = item_flags[item]
                n = ng
                if flags & FLAG_SMOOTH:
                    n = w[0] * nrm[t[0]] + w[1] * nrm[t[1]] + w[2] * nrm[t[2]]
                n = n.normalized()
                v = -ray
                base = item_front[item]
                if ng.dot(v) < 0:
                    n = -n
                    if flags & FLAG_TWO_SIDED:
                        base = item_back[item]
                if n.dot(v) < 0.05:  # smooth normal turned away at a silhouette
                    n = (n + (0.05 - n.dot(v)) * v).normalized()
                col = lighting(n, v, base, p, smap, lbox, lcentre, lright, lup, ldir, light, shadows, bias)
            elif g[2] < 3.0e38:  # ground: add the key light where it reaches
                s = 1.0
                if shadows:
                    s = shadow(smap, lbox, vec3(g[0], ground[1] + bias, g[1]), lcentre, lright, lup, ldir, light, bias)
                if ti.static(cached):
                    bk = bg_b[i]
                col += bk * s
            for k in ti.static(range(3)):  # tone curve and gamma through the look-up table
                idx = ti.min(ti.cast(ti.max(col[k], 0.0) * LUT_SCALE, ti.i32), LUT_SIZE - 1)
                img[3 * i + k] = lut[idx]
