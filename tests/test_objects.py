"""Procedural object meshes and their named sites."""

import igl
import numpy as np
import pytest
import trimesh

from sandbox.objects import SHAPES, SITE_NAMES, build_mesh, is_analytic, named_sites

PROCEDURAL = [s for s in SHAPES if s != "mesh"]


@pytest.fixture(scope="module")
def meshes() -> dict[str, trimesh.Trimesh]:
    """Every procedural shape built with its defaults."""
    return {s: build_mesh(s, {}) for s in PROCEDURAL}


@pytest.mark.parametrize("shape", PROCEDURAL)
def test_shape_is_closed_and_rests_on_ground(meshes, shape):
    """Each shape is watertight with outward normals, rests on y = 0 and is centred on the y axis."""
    m = meshes[shape]
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0
    lo, hi = m.bounds
    assert abs(lo[1]) < 1e-9
    assert np.allclose((lo + hi)[[0, 2]] / 2, 0.0, atol=1e-9)


def test_primitive_dimensions_follow_params():
    """Bounds of the primitives equal the sizes asked for (y up, base on the ground)."""
    cases = [
        ("box", {"size": [0.2, 0.4, 0.6]}, [0.2, 0.4, 0.6]),
        ("sphere", {"radius": 0.1}, [0.2, 0.2, 0.2]),
        ("cylinder", {"radius": 0.1, "height": 0.5}, [0.2, 0.5, 0.2]),
        ("capsule", {"radius": 0.05, "height": 0.3}, [0.1, 0.3, 0.1]),
        ("torus", {"major_radius": 0.2, "minor_radius": 0.03}, [0.46, 0.06, 0.46]),
        ("wine_bottle", {"height": 0.3, "radius": 0.04, "neck_radius": 0.01}, [0.08, 0.3, 0.08]),
        ("jeep", {"length": 0.5, "width": 0.25, "height": 0.2}, [0.5, 0.2, 0.25]),
    ]
    for shape, params, extents in cases:
        m = build_mesh(shape, params)
        assert np.allclose(m.extents, extents, rtol=2e-3), (shape, m.extents)


def test_statue_is_irregular_and_seeded():
    """The statue is non-convex, reaches its height, and the seed changes it reproducibly."""
    a = build_mesh("statue", {"height": 0.5, "seed": 1})
    b = build_mesh("statue", {"height": 0.5, "seed": 1})
    c = build_mesh("statue", {"height": 0.5, "seed": 2})
    assert np.isclose(a.extents[1], 0.5)
    assert a.convex_hull.volume > 1.3 * a.volume
    assert np.array_equal(a.vertices, b.vertices)
    assert not np.allclose(a.vertices, c.vertices)
    assert len(a.split(only_watertight=False)) == 1


def test_basket_has_cavity_and_handle():
    """The basket is hollow (a point inside the bowl is outside the solid) and the handle rises above the rim."""
    p = {"radius": 0.15, "height": 0.12, "handle_height": 0.15}
    m = build_mesh("basket", p)
    inside_bowl = np.array([[0.0, 0.08, 0.0], [0.0, 0.005, 0.0]])
    w = igl.winding_number(np.asarray(m.vertices, float), np.asarray(m.faces, np.int64), inside_bowl)
    assert w[0] < 0.5 < w[1]
    assert m.bounds[1, 1] > 0.12 + 0.15


def test_mesh_file_is_scaled_and_recentred(tmp_path):
    """A mesh file is scaled and moved so that its base centre is at the origin."""
    box = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    box.apply_translation([5.0, 7.0, -2.0])
    box.export(tmp_path / "thing.obj")
    m = build_mesh("mesh", {"path": "thing.obj", "scale": 0.5}, base_dir=tmp_path)
    assert np.allclose(m.bounds, [[-0.25, 0.0, -0.75], [0.25, 1.0, 0.75]])


def test_a_mesh_file_is_read_once_until_it_changes(tmp_path, monkeypatch):
    """A level's check and its world read a mesh file once; each gets a copy of its own; a changed file is
    read again."""
    reads = []
    load = trimesh.load
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: reads.append(a[0]) or load(*a, **k))
    trimesh.creation.box(extents=[1.0, 2.0, 3.0]).export(tmp_path / "thing.obj")
    a = build_mesh("mesh", {"path": "thing.obj"}, base_dir=tmp_path)
    b = build_mesh("mesh", {"path": "thing.obj"}, base_dir=tmp_path)
    assert len(reads) == 1 and a is not b and np.array_equal(a.vertices, b.vertices)
    a.apply_translation([1.0, 0.0, 0.0])  # a caller's change stays its own
    assert np.allclose(build_mesh("mesh", {"path": "thing.obj"}, base_dir=tmp_path).bounds[0, 0], -0.5)
    assert len(build_mesh("mesh", {"path": "thing.obj", "scale": 2.0}, base_dir=tmp_path).faces) == 12
    assert len(reads) == 2  # another scale is another mesh
    trimesh.creation.box(extents=[4.0, 2.0, 3.0]).export(tmp_path / "thing.obj")
    import os
    os.utime(tmp_path / "thing.obj", ns=(1, 1))  # a new modification time, whatever the clock's resolution
    assert np.allclose(build_mesh("mesh", {"path": "thing.obj"}, base_dir=tmp_path).bounds[0, 0], -2.0)
    assert len(reads) == 3


def test_missing_mesh_file_names_the_path(tmp_path):
    """A missing mesh file raises FileNotFoundError naming the path."""
    with pytest.raises(FileNotFoundError, match="nothere.stl"):
        build_mesh("mesh", {"path": "nothere.stl"}, base_dir=tmp_path)


def test_bad_inputs_name_allowed_values():
    """Unknown shapes and parameters, and bad values, raise ValueError naming what is allowed."""
    with pytest.raises(ValueError) as err:
        build_mesh("teapot", {})
    assert all(s in str(err.value) for s in SHAPES)
    with pytest.raises(ValueError) as err:
        build_mesh("torus", {"radius": 1.0})
    assert "radius" in str(err.value) and "major_radius" in str(err.value) and "minor_radius" in str(err.value)
    for shape, params, word in [
        ("sphere", {"radius": -1.0}, "radius"),
        ("sphere", {"radius": "big"}, "radius"),
        ("box", {"size": [1.0, 2.0]}, "size"),
        ("capsule", {"radius": 0.2, "height": 0.3}, "height"),
        ("torus", {"major_radius": 0.1, "minor_radius": 0.2}, "minor_radius"),
        ("wine_bottle", {"neck_radius": 0.1}, "neck_radius"),
        ("statue", {"seed": 1.5}, "seed"),
        ("mesh", {}, "path"),
    ]:
        with pytest.raises(ValueError, match=word):
            build_mesh(shape, params)


def test_is_analytic():
    """Exactly the five primitives have a closed-form signed distance."""
    assert {s for s in SHAPES if is_analytic(s)} == {"box", "sphere", "cylinder", "capsule", "torus"}


@pytest.mark.parametrize("shape", PROCEDURAL)
def test_sites_lie_on_the_surface(meshes, shape):
    """Every site but the centre is on the surface, on its side of the bounds centre."""
    m = meshes[shape]
    sites = named_sites(m)
    assert set(sites) == set(SITE_NAMES)
    lo, hi = m.bounds
    c = (lo + hi) / 2
    assert np.allclose(sites["center"], c)
    pts = np.array([sites[n] for n in SITE_NAMES if n != "center"])
    d2, _, _ = igl.point_mesh_squared_distance(pts, np.asarray(m.vertices, float), np.asarray(m.faces, np.int64))
    assert np.sqrt(d2).max() < 1e-7 * max(m.extents.max(), 1.0)
    side = {"top": (1, 1), "bottom": (1, -1), "front": (2, 1), "back": (2, -1), "left": (0, -1), "right": (0, 1)}
    for name, (axis, sign) in side.items():
        assert sign * (sites[name][axis] - c[axis]) > 0, name


def test_sites_of_a_box_are_face_centres():
    """On a box the six surface sites are the face centres."""
    s = named_sites(build_mesh("box", {"size": [0.2, 0.4, 0.6]}))
    expect = {"top": [0, 0.4, 0], "bottom": [0, 0, 0], "front": [0, 0.2, 0.3], "back": [0, 0.2, -0.3],
              "left": [-0.1, 0.2, 0], "right": [0.1, 0.2, 0], "center": [0, 0.2, 0]}
    for name, p in expect.items():
        assert np.allclose(s[name], p, atol=1e-12), name


def test_shipped_rock_asset_loads(root):
    """levels/assets/rock.obj loads through the mesh shape, closed and resting on y = 0."""
    m = build_mesh("mesh", {"path": "assets/rock.obj", "scale": 2.0}, base_dir=root / "levels")
    assert m.is_watertight and m.volume > 0
    assert abs(m.bounds[0, 1]) < 1e-9 and np.isclose(m.extents[1], 2 * 0.16477, rtol=1e-4)
