"""Software rasterizer, frame recorder and viewer fallback."""

import os
import pathlib
import subprocess
import sys
import types

import numpy as np
import pytest

from shaders import Camera, MeshItem, Renderer, RenderScene, auto_camera, crease_split, tube_mesh
from shaders.scene import rotation_minimising_frames

pytestmark = pytest.mark.keeps_runtime  # the module's Renderer holds Taichi arrays outside a world

GOLDEN = pathlib.Path(__file__).parent / "golden"
UPDATE = os.environ.get("SANDBOX_UPDATE_GOLDEN") == "1"


@pytest.fixture(scope="module")
def small() -> Renderer:
    """One 96 x 72 renderer shared by the module (kernels compile once)."""
    return Renderer(96, 72, shadow_size=256)


def icosphere(radius: float = 0.5, centre=(0.0, 0.5, 0.0)):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return (m.vertices + centre).astype(np.float32), m.faces.astype(np.int32)


def check_golden(name: str, img: np.ndarray) -> None:
    """Compare with tests/golden/<name>.png: mean |diff| <= 1 and under 1% of pixels off by > 24."""
    import imageio.v3 as iio

    path = GOLDEN / f"{name}.png"
    if UPDATE or not path.exists():
        if not UPDATE:
            pytest.fail(f"missing golden image {path}; create it with SANDBOX_UPDATE_GOLDEN=1")
        GOLDEN.mkdir(exist_ok=True)
        iio.imwrite(path, img)
    ref = iio.imread(path)
    assert ref.shape == img.shape
    diff = np.abs(ref.astype(np.int16) - img.astype(np.int16)).max(axis=2)
    assert diff.mean() <= 1.0, f"{name}: mean difference {diff.mean():.2f}"
    assert (diff > 24).mean() < 0.01, f"{name}: {(diff > 24).mean():.2%} pixels differ"


def two_triangles():
    """A red triangle at z = -1 behind a blue one at z = 0, overlapping in the middle."""
    v = np.array(
        [[-1.0, -0.8, -1.0], [0.6, -0.8, -1.0], [-0.2, 0.9, -1.0]]  # back, z = -1
        + [[-0.6, -0.6, 0.0], [1.0, -0.6, 0.0], [0.2, 0.7, 0.0]],  # front, z = 0
        np.float32,
    )
    back = MeshItem(v[:3], [[0, 1, 2]], color=(0.9, 0.2, 0.2), two_sided=True)
    front = MeshItem(v[3:], [[0, 1, 2]], color=(0.2, 0.3, 0.9), two_sided=True)
    return RenderScene(items=[back, front]), Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov=50.0)


def test_golden_sphere(small):
    """A lit sphere over a checker ground with its shadow matches the stored image."""
    v, f = icosphere()
    scene = RenderScene(items=[MeshItem(v, f, color=(0.85, 0.6, 0.3))], ground_height=0.0)
    img = small.render(scene, Camera((1.2, 1.4, 2.2), (0.0, 0.4, 0.0), fov=45.0))
    assert img.shape == (72, 96, 3) and img.dtype == np.uint8
    centre = img[30:42, 42:54].astype(float).mean(axis=(0, 1))
    assert centre[0] > centre[2] + 40, "the sphere's orange should show in the middle"
    check_golden("sphere", img)


def test_cached_background_matches_inline(small):
    """A new view shaded inline equals the same view read from the sky/ground cache."""
    v, f = icosphere()
    scene = RenderScene(items=[MeshItem(v, f, color=(0.3, 0.7, 0.4))], ground_height=0.0)
    cam = Camera((-1.5, 1.0, 2.0), (0.0, 0.4, 0.0), fov=40.0)
    small.render(scene, Camera((2.0, 1.0, 2.0), (0.0, 0.4, 0.0)))  # some other view holds the cache
    inline = small.render(scene, cam)
    cached_key = small._bg_key
    cached = small.render(scene, cam)  # seen twice running: cached now
    assert small._bg_key != cached_key, "the second frame of a view should refill the cache"
    assert np.abs(cached.astype(int) - inline).max() <= 1
    assert (cached != inline).mean() < 0.01


def test_golden_two_triangles(small):
    """Two overlapping triangles at different depths match the stored image, the near one on top."""
    scene, cam = two_triangles()
    img = small.render(scene, cam)
    ids, _ = small.visibility()
    px, _ = cam.project(np.array([[-0.1, -0.3, 0.0]]), 96, 72)  # inside both triangles
    x, y = px[0].astype(int)
    assert ids[y, x] == 1 and img[y, x, 2] > img[y, x, 0]
    check_golden("two_triangles", img)


def test_nearest_surface_wins(small):
    """The id buffer equals a per-pixel NumPy depth test over random overlapping triangles."""
    rng = np.random.default_rng(7)
    n = 40
    centres = rng.uniform([-1.0, -0.8, -1.5], [1.0, 0.8, 1.0], size=(n, 1, 3))
    verts = (centres + rng.normal(scale=0.45, size=(n, 3, 3))).reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * n).reshape(n, 3)
    cam = Camera((0.3, 0.2, 4.0), (0.0, 0.0, 0.0), fov=50.0)
    small.render(RenderScene(items=[MeshItem(verts, faces, two_sided=True)]), cam)
    ids, depth = small.visibility()

    h, w = ids.shape
    xy, z = cam.project(verts, w, h)
    a, b, c = (xy[faces[:, k]] for k in range(3))
    za, zb, zc = (z[faces[:, k]] for k in range(3))
    gy, gx = np.mgrid[0:h, 0:w] + 0.5
    p = np.stack([gx.ravel(), gy.ravel()], 1)[:, None, :]

    def cross(u, v):
        return (u[..., 0] - p[..., 0]) * (v[..., 1] - p[..., 1]) - (u[..., 1] - p[..., 1]) * (v[..., 0] - p[..., 0])

    e0, e1, e2 = cross(b, c), cross(c, a), cross(a, b)
    area = e0 + e1 + e2
    inside = (e0 * area >= 0) & (e1 * area >= 0) & (e2 * area >= 0)
    margin = np.minimum(np.minimum(np.abs(e0), np.abs(e1)), np.abs(e2)) / np.abs(area).clip(1e-9)
    zref = 1.0 / ((e0 / za + e1 / zb + e2 / zc) / area)
    zref = np.where(inside, zref, np.inf)
    order = np.sort(zref, axis=1)
    best = np.where(np.isfinite(order[:, 0]), np.argmin(zref, axis=1), -1)
    # pixels where coverage and the winner are unambiguous under float rounding
    near_edge = (inside & (margin < 1e-3)).any(axis=1)
    with np.errstate(invalid="ignore"):
        separated = ~np.isfinite(order[:, 1]) | ((order[:, 1] - order[:, 0]) > 1e-4 * order[:, 0])
    clear = ~near_edge & separated
    assert clear.mean() > 0.8
    assert (best >= 0).sum() > 500, "the triangles should cover a good part of the image"
    np.testing.assert_array_equal(ids.ravel()[clear], best[clear])
    covered = best >= 0
    np.testing.assert_allclose(depth.ravel()[covered & clear], order[covered & clear, 0], rtol=1e-4)


def test_equal_depth_lowest_id(small):
    """Coplanar copies of one triangle resolve to the lowest triangle id on every pixel."""
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]], np.float32)
    copies = 64
    scene = RenderScene(items=[MeshItem(np.tile(v, (copies, 1)), np.arange(3 * copies).reshape(copies, 3))])
    small.render(scene, Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)))
    ids, _ = small.visibility()
    covered = ids >= 0
    assert covered.sum() > 300
    assert (ids[covered] == 0).all()


@pytest.mark.parametrize("aspect_wh", [(96, 72), (72, 96), (160, 40)])
def test_auto_camera_keeps_all_vertices_in_view(aspect_wh):
    """Automatic framing projects every vertex of irregular scenes inside the image, in front of the eye."""
    w, h = aspect_wh
    rng = np.random.default_rng(w)
    for scale in (0.01, 1.0, 30.0):
        pts = (rng.normal(size=(500, 3)) * [3.0, 0.5, 1.0] * scale + rng.normal(size=3) * 5).astype(np.float32)
        scene = RenderScene(items=[MeshItem(pts, np.arange(498).reshape(-1, 3))])
        cam = auto_camera(scene, w / h)
        xy, z = cam.project(pts, w, h)
        assert (z > cam.near).all()
        assert (xy[:, 0] >= 0).all() and (xy[:, 0] <= w).all()
        assert (xy[:, 1] >= 0).all() and (xy[:, 1] <= h).all()
        # and it is not absurdly far: the sphere nearly touches the narrow side
        span = max(np.ptp(xy[:, 0]) / w, np.ptp(xy[:, 1]) / h)
        assert span > 0.15


def test_tube_mesh_radius_and_frames():
    """Tube rings sit at the rope radius, normal to the tangent, and frames do not twist in a plane."""
    t = np.linspace(0.0, 1.5 * np.pi, 50)
    line = np.stack([np.cos(t), np.zeros_like(t), np.sin(t)], 1)  # planar arc in y = 0
    radius, sides = 0.07, 8
    verts, faces = tube_mesh(line, radius, sides=sides)
    rings = verts[: len(line) * sides].reshape(len(line), sides, 3) - line[:, None].astype(np.float32)
    np.testing.assert_allclose(np.linalg.norm(rings, axis=2), radius, rtol=1e-5)
    tan, nrm, binormal = rotation_minimising_frames(line)
    np.testing.assert_allclose(np.einsum("nsk,nk->ns", rings, tan), 0.0, atol=1e-6)
    # rotation-minimising on a planar curve: the binormal keeps pointing along the plane normal
    np.testing.assert_allclose(np.abs(binormal[:, 1]), 1.0, atol=1e-9)
    assert faces.min() >= 0 and faces.max() < len(verts)
    # outward winding: face normals point away from the axis
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    side = faces[: 2 * sides * (len(line) - 1)]
    mid = verts[side].mean(axis=1)
    nearest = line[np.argmin(np.linalg.norm(mid[:, None] - line[None], axis=2), axis=1)]
    assert (np.einsum("ij,ij->i", fn[: len(side)], mid - nearest) > 0).all()


def test_crease_split_keeps_box_sharp():
    """A box splits into 24 vertices (4 per side) while a sphere stays welded."""
    import trimesh

    box = trimesh.creation.box()
    src, faces = crease_split(box.vertices, box.faces)
    assert len(src) == 24 and faces.shape == box.faces.shape
    np.testing.assert_allclose(box.vertices[src][faces], box.vertices[box.faces])
    v, f = icosphere()
    src, _ = crease_split(v, f)
    assert len(src) == len(v)


class FakeSim:
    """The slice of ``sandbox.api.Sandbox`` the recorder reads, with scripted state."""

    rope_names = ["r"]
    cloth_names = ["c"]
    object_names = ["ball"]
    camera = None
    ground_height = 0.0

    def __init__(self) -> None:
        self.frame, self.time, self.fsm_state = 0, 0.0, "Start"
        n = 12
        x, z = np.meshgrid(np.linspace(-0.6, 0.6, n), np.linspace(-0.6, 0.6, n))
        self._cloth = np.stack([x, 0.9 - 0.3 * (x**2 + z**2), z], -1).reshape(-1, 3).astype(np.float32)
        i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
        a = (j * n + i).ravel()
        self._faces = np.concatenate([np.stack([a, a + n, a + n + 1], 1), np.stack([a, a + n + 1, a + 1], 1)])
        self._ball = icosphere(0.3, (0.0, 0.3, 0.0))

    def rope_positions(self, name):
        t = np.linspace(0.0, 1.0, 30)
        return np.stack([t - 0.5, 0.05 + 0.1 * np.sin(6 * t + self.frame), 0.5 + 0 * t], 1).astype(np.float32)

    def rope_radius(self, name):
        return 0.02

    def strand_positions(self, name):  # the followed knot's strands are its ropes
        return self.rope_positions(name)

    def strand_radius(self, name):
        return self.rope_radius(name)

    def cloth_positions(self, name):
        return self._cloth

    def cloth_faces(self, name):
        return self._faces

    def object_mesh(self, name):
        return self._ball

    def step(self) -> None:
        self.frame += 1
        self.time = self.frame / 60.0
        self.fsm_state = {4: "Wrap", 9: "Tighten"}.get(self.frame, self.fsm_state)


def test_frame_recorder_outputs(tmp_path):
    """The recorder writes the due PNG frames, an MP4 with as many frames, a GIF and a contact sheet."""
    import imageio.v2 as imageio
    import imageio.v3 as iio

    from sandbox.io.frames import FrameRecorder

    rec = FrameRecorder(tmp_path, every=3, video=True, gif=True, width=96, height=72)
    sim = FakeSim()
    prev = sim.fsm_state
    for _ in range(12):
        sim.step()
        rec.on_frame(sim, sim.frame, sim.fsm_state, sim.fsm_state != prev)
        prev = sim.fsm_state
    stats = rec.close(sim)
    pngs = sorted(p.name for p in (tmp_path / "frames").glob("*.png"))
    assert pngs == ["00003.png", "00006.png", "00009.png", "00012.png"]
    assert iio.imread(tmp_path / "frames" / "00006.png").shape == (72, 96, 3)
    with imageio.get_reader(tmp_path / "anim.mp4") as reader:
        frames = [f for f in reader]
    assert len(frames) == 4 and frames[0].shape == (72, 96, 3)
    assert iio.imread(tmp_path / "anim.gif").shape[0] == 4
    sheet = iio.imread(tmp_path / "sheet.png")
    assert sheet.shape[1] == 4 * 48  # tiles: Start (frame 1), Wrap (frame 4), Tighten (frame 9), last frame
    assert stats["frames_rendered"] == 6  # 4 due frames + the off-beat tiles of frames 1 and 4
    assert 0 < stats["render_ms_p50"] <= stats["render_ms_p95"]


def test_rendering_off_costs_nothing(root):
    """Importing the frame recorder and building a scene neither imports Taichi nor allocates anything."""
    code = (
        "import sys; from sandbox.io.frames import FrameRecorder, scene_from_sim; import shaders;"
        "shaders.RenderScene(items=[shaders.MeshItem(*shaders.tube_mesh([[0, 0, 0], [1, 0, 0]], 0.1))]);"
        "sys.exit(int('taichi' in sys.modules))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_play_headless_exits_2_with_one_line(root):
    """Without a display ``play`` prints one line pointing to ``sandbox run`` and exits 2, no traceback."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    code = "import sys; from sandbox.viewer.play import main; sys.exit(main('levels/drape_box.yaml'))"
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=60)
    out = (proc.stdout + proc.stderr).strip().splitlines()
    assert proc.returncode == 2
    assert len(out) == 1 and "Traceback" not in out[0]
    assert "sandbox run levels/drape_box.yaml --frames-every" in out[0] and "display" in out[0]


def test_play_without_vulkan_exits_2_with_one_line(root):
    """With a display but no Vulkan loader ``play`` says so in one line and exits 2."""
    import ctypes

    try:
        ctypes.CDLL("libvulkan.so.1")
        pytest.skip("a Vulkan loader is installed here")
    except OSError:
        pass
    env = dict(os.environ, DISPLAY=":99")
    code = "import sys; from sandbox.viewer.play import main; sys.exit(main('levels/rope_hang.yaml'))"
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=60)
    out = (proc.stdout + proc.stderr).strip().splitlines()
    assert proc.returncode == 2
    assert len(out) == 1 and "Vulkan" in out[0] and "sandbox run levels/rope_hang.yaml" in out[0]


def test_orbit_camera_round_trip():
    """The viewer's orbit camera starts exactly at the level's (or the automatic) eye position."""
    from sandbox.viewer.play import OrbitCamera

    orbit = OrbitCamera.from_look((1.0, 2.0, -3.0), (0.5, 0.2, 0.1), 50.0)
    np.testing.assert_allclose(orbit.eye(), (1.0, 2.0, -3.0), atol=1e-12)
    np.testing.assert_allclose(orbit.target, (0.5, 0.2, 0.1))


class _Recorder:
    """Accepts any GGUI call and counts it by name."""

    def __init__(self, calls: dict) -> None:
        self._calls = calls

    def __getattr__(self, name):
        def call(*args, **kwargs):
            self._calls[name] = self._calls.get(name, 0) + 1
            return self if name == "sub_window" else False

        return call

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class FakeWindow:
    """A GGUI window stand-in: scripted key presses, runs for a fixed number of frames."""

    def __init__(self, frames: int, presses: dict) -> None:
        self.frames, self.presses, self.calls, self.shown = frames, presses, {}, 0

    @property
    def running(self):
        return self.shown < self.frames

    @running.setter
    def running(self, value):
        if not value:
            self.frames = self.shown

    def get_events(self, tag=None):
        return [type("Event", (), {"key": k})() for k in self.presses.get(self.shown, [])]

    def is_pressed(self, *keys):
        return False

    def get_cursor_pos(self):
        return 0.5, 0.5

    def get_window_shape(self):
        return 320, 240

    def get_canvas(self):
        return _Recorder(self.calls)

    def get_scene(self):
        return _Recorder(self.calls)

    def get_gui(self):
        return _Recorder(self.calls)

    def show(self):
        self.shown += 1


def test_viewer_loop_steps_pauses_and_resets():
    """The viewer loop steps the sim per frame, pauses, single-steps, resets and draws every item."""
    from sandbox.viewer.play import Viewer

    class SteppingSim(FakeSim):
        closed = False

        def timings(self):
            return {"solve": 1.0}

        def close(self):
            self.closed = True

    built = []

    def build():
        built.append(SteppingSim())
        return built[-1]

    presses = {3: [" "], 5: ["n"], 6: ["n"], 7: [" "], 9: ["r"], 10: ["Escape"]}
    window = FakeWindow(frames=20, presses=presses)
    viewer = Viewer(window, build(), build)
    viewer.run()
    assert window.shown == 11  # Escape on frame 10 ends the loop after that frame
    first = built[0]
    assert first.frame == 3 + 2 + 2  # frames 0-2 run, paused 3-6 with two single steps, frames 7-8 run
    assert len(built) == 2 and built[1].frame == 2  # reset on frame 9, then frames 9 and 10 run
    assert built[0].closed and not built[1].closed  # the reset gave the old level's fields back
    assert window.calls["mesh"] >= 11 * 3  # ground + cloth + rope + ball every frame


def test_follow_camera_does_not_depend_on_how_often_frames_are_written(tmp_path):
    """The follow camera glides every simulated frame: written every frame or every 10th, frame 10 looks at the same
    point (the knot moves every frame here, so sampling it only when writing would lag behind)."""
    from sandbox.io.frames import FrameRecorder, KnotFollower

    class Moving(FakeSim):
        rope_names = ["a", "b"]
        camera = {"position": (0.0, 1.5, 3.0), "look_at": (0.0, 0.3, 0.0), "fov": 45.0,
                  "follow": ["a", "b"], "distance": 0.4, "smoothing": 0.1}

        def rope_positions(self, name):
            return CrossingRopes(cross=(0.02 * self.frame, 0.6, 0.0)).rope_positions(name)

        def rope_radius(self, name):
            return CrossingRopes.r

    looks = []
    for every in (1, 10):
        sim = Moving()
        rec = FrameRecorder(tmp_path / str(every), every=every, width=48, height=36,
                            follow=KnotFollower.from_camera(Moving.camera))
        for _ in range(10):
            sim.step()
            rec.on_frame(sim, sim.frame, sim.fsm_state, False)
        looks.append(rec._follow.look.copy())
    np.testing.assert_allclose(looks[0], looks[1], atol=1e-12)
    assert 0.1 < looks[0][0] < 0.2  # behind the knot (x = 0.2 at frame 10) by the glide's lag, not at frame 1's x


def test_viewer_follow_key_glides_the_orbit_to_the_knot():
    """With "f" the orbit's centre glides to where the ropes touch, keeping its yaw, pitch and distance;
    "f" again stops it where it is; a level camera that follows ropes starts the viewer following."""
    from sandbox.viewer.play import Viewer

    class Crossed(FakeSim):
        rope_names = ["a", "b"]
        ropes = CrossingRopes(cross=(0.2, 0.6, 0.1))

        def rope_positions(self, name):
            return self.ropes.rope_positions(name)

        def rope_radius(self, name):
            return self.ropes.r

    knot = np.array([0.2, 0.6 + 0.5 * Crossed.ropes.lift, 0.1])
    window = FakeWindow(frames=40, presses={2: ["f"], 30: ["f"]})
    viewer = Viewer(window, Crossed(), Crossed)
    start = viewer.orbit.target.copy()
    yaw, pitch, dist = viewer.orbit.yaw, viewer.orbit.pitch, viewer.orbit.distance
    assert not viewer.following
    viewer.run()
    assert not viewer.following  # toggled off on frame 30
    # followed on frames 2-29 (each steps 1/60 s first; 0.5 s time constant), then left where it was
    left = np.exp(-(30 - 2) / 60.0 / 0.5)
    np.testing.assert_allclose(viewer.orbit.target, knot + left * (start - knot), atol=1e-3)
    assert (viewer.orbit.yaw, viewer.orbit.pitch, viewer.orbit.distance) == (yaw, pitch, dist)

    class LevelFollows(Crossed):
        camera = {"position": (0.0, 1.0, 2.0), "look_at": (0.0, 0.5, 0.0), "fov": 45.0,
                  "follow": ["a", "b"], "distance": None, "smoothing": 0.0}

    viewer = Viewer(FakeWindow(frames=2, presses={}), LevelFollows(), LevelFollows)
    assert viewer.following
    viewer.run()
    np.testing.assert_allclose(viewer.orbit.target, knot, atol=1e-9)


class CrossingRopes:
    """Two straight ropes that touch where they cross at ``cross`` (rope "a" along x, "b" along z, 2 r above)."""

    rope_names = ["a", "b"]
    r = 0.01

    def __init__(self, cross=(0.3, 0.5, -0.2), apart: bool = False) -> None:
        self.cross = np.asarray(cross, dtype=np.float64)
        self.lift = 1.0 if apart else 2.0 * self.r * 0.999
        self.time = 0.0

    def rope_positions(self, name):
        t = np.linspace(-0.5, 0.5, 41)[:, None]
        if name == "a":
            return self.cross + t * [1.0, 0.0, 0.0]
        return self.cross + [0.0, self.lift, 0.0] + t * [0.0, 0.0, 1.0]

    def rope_radius(self, name):
        return self.r

    strand_positions, strand_radius = rope_positions, rope_radius


def test_knot_centre_is_where_ropes_touch():
    """Two ropes crossing in contact: the knot centre is midway between their axes at the crossing; apart: none."""
    from sandbox.geometry.knots import knot_centre

    sim = CrossingRopes()
    c = knot_centre([sim.rope_positions("a"), sim.rope_positions("b")], radius=sim.r)
    assert np.allclose(c, sim.cross + [0.0, 0.5 * sim.lift, 0.0], atol=1e-9)
    far = CrossingRopes(apart=True)
    assert knot_centre([far.rope_positions("a"), far.rope_positions("b")], radius=far.r) is None
    # one rope whose loop crosses itself (t^2 - 1, t^3 - t crosses at t = +-1, the two passes
    # 0.0198 apart in z): the centre is at the crossing, not in the loop
    t = np.linspace(-1.6, 1.6, 321)
    loop = np.stack([0.1 * (t * t - 1.0), 0.5 + 0.1 * (t**3 - t), 0.0099 * t], 1)
    c1 = knot_centre([loop], radius=0.01)
    assert c1 is not None and np.allclose(c1, [0.0, 0.5, 0.0], atol=2e-3)


def test_knot_follower_glides_to_the_knot_at_its_time_constant():
    """The camera's target moves by 1 - exp(-dt / smoothing) of the way to the knot; the eye keeps its offset."""
    from sandbox.io.frames import KnotFollower

    sim = CrossingRopes()
    start = np.array([0.0, 0.4, 0.0])
    f = KnotFollower(["a", "b"], look_at=start, direction=(0.0, 3.0, 4.0), distance=0.25, smoothing=0.5)
    goal = sim.cross + [0.0, 0.5 * sim.lift, 0.0]
    sim.time = 0.2
    cam = f.update(sim)
    expect = start + (1.0 - np.exp(-0.2 / 0.5)) * (goal - start)
    assert np.allclose(cam.look_at, expect, atol=1e-9)
    assert np.allclose(np.subtract(cam.position, cam.look_at), [0.0, 0.15, 0.2], atol=1e-9)
    sim.time = 0.5
    cam = f.update(sim)
    assert np.allclose(cam.look_at, goal + np.exp(-0.5 / 0.5) * (start - goal), atol=1e-9)
    apart = CrossingRopes(apart=True)  # nothing touches: it stays where it is
    apart.time = 2.0
    assert np.allclose(f.update(apart).look_at, cam.look_at)
    snap = KnotFollower(["a", "b"], look_at=start, direction=(1, 1, 1), distance=1.0, smoothing=0.0)
    sim.time = 0.01
    assert np.allclose(snap.update(sim).look_at, goal, atol=1e-9)


def test_knot_follower_from_camera():
    """A level camera's follow list, direction and distance make the follower; ropes given override it; none: None."""
    from sandbox.io.frames import KnotFollower

    level_cam = {"position": (0.0, 1.0, 2.0), "look_at": (0.0, 1.0, 0.0), "fov": 40.0,
                 "follow": ["a", "b"], "distance": None, "smoothing": 0.3}
    f = KnotFollower.from_camera(level_cam)
    assert f.ropes == ["a", "b"] and f.fov == 40.0 and f.smoothing == 0.3
    assert np.allclose(f.offset, [0.0, 0.0, 2.0]) and np.allclose(f.look, [0.0, 1.0, 0.0])
    g = KnotFollower.from_camera(level_cam, ["b"], distance=0.5)
    assert g.ropes == ["b"] and np.allclose(f.offset / 2.0 * 0.5, g.offset)
    assert KnotFollower.from_camera({**level_cam, "follow": []}) is None
    assert KnotFollower.from_camera(None) is None
    h = KnotFollower.from_camera(None, ["a", "b"])
    assert np.isclose(np.linalg.norm(h.offset), 0.4)
    apart = CrossingRopes(apart=True)  # no level camera, nothing touching: it looks at the ropes' centroid
    mid = np.vstack([apart.rope_positions("a"), apart.rope_positions("b")]).mean(axis=0)
    np.testing.assert_allclose(h.update(apart).look_at, mid, atol=1e-9)
    with pytest.raises(ValueError, match="distance > 0"):
        KnotFollower(["a"], look_at=(0, 0, 0), direction=(0, 0, 1), distance=0.0)


def test_frame_recorder_follows_a_knot_the_level_camera_names(tmp_path):
    """With a level camera that follows ropes, the recorder's frames are framed on their knot, not the level view."""
    from sandbox.io.frames import FrameRecorder, KnotFollower

    class Knotted(FakeSim):
        rope_names = ["a", "b"]
        camera = {"position": (0.0, 1.5, 3.0), "look_at": (0.0, 0.3, 0.0), "fov": 45.0,
                  "follow": ["a", "b"], "distance": 0.4, "smoothing": 0.0}
        ropes = CrossingRopes(cross=(0.2, 0.6, 0.1))

        def rope_positions(self, name):
            return self.ropes.rope_positions(name)

    sim = Knotted()
    rec = FrameRecorder(tmp_path, every=1, width=96, height=72, follow=KnotFollower.from_camera(sim.camera))
    sim.step()
    rec.on_frame(sim, sim.frame, sim.fsm_state, True)
    assert rec._follow is not None and np.allclose(rec._follow.look, [0.2, 0.6 + 0.5 * sim.ropes.lift, 0.1], atol=1e-9)
    Knotted.camera = {**Knotted.camera, "follow": []}
    plain = FrameRecorder(tmp_path / "plain", every=1, width=96, height=72,
                          follow=KnotFollower.from_camera(Knotted.camera))
    plain.on_frame(sim, sim.frame, sim.fsm_state, True)
    assert plain._follow is None
    a = rec._last[2].astype(int)
    b = plain._last[2].astype(int)
    assert np.abs(a - b).mean() > 5  # a close-up of the crossing, not the level's wide view


def test_two_cloth_lines_from_one_centre_are_followed_as_one_curve_through_it():
    """Two lines of one cloth share its centre particle: the tracker looks at where they cross away from it,
    not at the join (as two ropes they would touch there). Lines A (along x) and B (out along z, then
    back over A 2 r above it at x = 0.3) from a shared centre at the origin."""
    from sandbox.io.frames import KnotTracker

    r = 0.01
    t = np.linspace(0.0, 0.6, 61)[:, None]
    a = t * [1.0, 0.0, 0.0]
    b = np.vstack([t[:31] * [0.0, 0.0, 1.0],
                   [0.3, 2 * r * 0.999, 0.3] + (t[1:] - 0.3) * [0.0, 0.0, -1.0]])
    sim = types.SimpleNamespace(time=0.0, strand_radius=lambda n: r,
                                strand_positions=lambda n: a if n == "F.line1" else b)
    look = KnotTracker(["F.line1", "F.line3"], smoothing=0.0).update(sim)
    assert np.allclose(look, [0.3, r, 0.0], atol=0.01), look
    ropes = KnotTracker(["A", "B"], smoothing=0.0)  # two ropes are not joined: the start counts as a touch
    sim_r = types.SimpleNamespace(time=0.0, strand_radius=lambda n: r,
                                  strand_positions=lambda n: a if n == "A" else b)
    assert not np.allclose(ropes.update(sim_r), [0.3, r, 0.0], atol=0.01)
