"""The scene library: triangle counts of the real and procedural catalog scenes, animation at
two times, and the cosine scene's fallback room. Real scenes skip only when the shared scene
folder beside the checkout is absent."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from engine.core.errors import ConfigError, SceneError
from scenes.catalog import describe, entries, load_named

SHARED_SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


@pytest.fixture
def scene_path(monkeypatch):
    """PACKETRT_SCENE_PATH = the shared scene folder (skip when it is not there)."""
    if not SHARED_SCENES.is_dir():
        pytest.skip(f"shared scene data not found at {SHARED_SCENES}")
    monkeypatch.setenv("PACKETRT_SCENE_PATH", str(SHARED_SCENES))
    return SHARED_SCENES


@pytest.fixture
def no_scene_path(monkeypatch):
    monkeypatch.setenv("PACKETRT_SCENE_PATH", "")


def test_kitchen_has_the_published_triangle_count(scene_path):
    scene = load_named("bart-kitchen")
    assert scene.n_triangles == 110_561
    assert scene.info["triangles"] == 110_561 and scene.animated
    assert scene.info["textures"] == 8 and len(scene.lights) == 6
    assert scene.triangles.uvs.shape == (110_561, 3, 2)


def test_kitchen_toy_car_and_camera_move(scene_path):
    early, late = load_named("bart-kitchen", time=0.0), load_named("bart-kitchen", time=5.0)
    assert early.n_triangles == late.n_triangles
    moved = np.any(early.triangles.v0 != late.triangles.v0, axis=1)
    assert moved.sum() == early.info["animated_triangles"] > 0          # only the toy car
    assert early.camera.eye != late.camera.eye
    np.testing.assert_allclose(late.camera.eye, (3.5, 0.2, 0.1), atol=1e-9)   # the key at 5 s


@pytest.mark.parametrize("tessellation, cone_triangles", [(1, 8), (3, 24)])
def test_museum_counts(scene_path, tessellation, cone_triangles):
    scene = load_named("bart-museum", {"tessellation": tessellation}, time=2.0)
    # pillar mesh 10,000 + 133 fan-triangulated polygons (274) + 10 textured triangles,
    # 1,024 animated triangles, 8 cones.
    assert scene.info["static_triangles"] == 10_284 + 8 * cone_triangles
    assert scene.info["tpa_triangles"] == 1_024
    assert scene.n_triangles == 10_284 + 1_024 + 8 * cone_triangles


def test_robots_at_two_times_differ(scene_path):
    a, b = load_named("bart-robots", time=0.0), load_named("bart-robots", time=20.0)
    assert a.n_triangles == b.n_triangles == 71_708
    moving = np.any(a.triangles.v0 != b.triangles.v0, axis=1)
    assert moving.sum() > 10_000
    assert a.camera.eye != b.camera.eye
    assert a.info["unkeyed_transforms"] == ["grip_lift1", "grip_rot1", "gun_lift2", "gun_rot2", "head_rot2"]


@pytest.mark.parametrize("lod, count", [(3, 948), (2, 3_851), (1, 16_301), (0, 69_451)])
def test_bunny_levels_of_detail(scene_path, lod, count):
    assert load_named("bunny", {"lod": lod}).n_triangles == count


@pytest.mark.parametrize("size_factor, tessellation", [(1, 1), (1, 3), (2, 2), (3, 1)])
def test_spd_rings_counts(no_scene_path, size_factor, tessellation):
    scene = load_named("spd-rings", {"size_factor": size_factor, "tessellation": tessellation})
    units = size_factor * (size_factor + 1) * (2 * size_factor + 1) // 6
    per_unit = 30 * (8 * tessellation + 12 * tessellation ** 2)
    assert scene.n_triangles == units * per_unit + 2 == scene.info["triangles"]
    assert scene.info["units"] == units and len(scene.lights) == 3
    assert len({m.diffuse for m in scene.materials}) == 7                 # six rings + backdrop


def test_spd_rings_default_is_spd_size_factor_7(no_scene_path):
    scene = load_named("spd-rings")
    assert scene.info["units"] == 140 and scene.info["cylinders"] == scene.info["spheres"] == 4_200
    assert scene.n_triangles == 554_402


def test_spd_ring_unit_lies_on_dodecahedron_edge_midpoints():
    from scenes.spd_rings import unit_vertices
    v = unit_vertices(0.0)                                   # unscaled: circumradius 1
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)
    d = np.linalg.norm(v[:, None] - v[None], axis=2)
    edge = 2 / (1 + 5 ** 0.5)                                # icosidodecahedron edge / radius
    assert (np.abs(d - edge) < 1e-9).sum(axis=1).tolist() == [4] * 30


@pytest.mark.parametrize("subdivisions", [8, 2])
def test_erw6_counts(no_scene_path, subdivisions):
    scene = load_named("erw6", {"subdivisions": subdivisions})
    assert scene.n_triangles == 12 * subdivisions ** 2 + 36
    assert len(scene.lights) == 1


def test_cosine_falls_back_to_erw6_without_the_kitchen(no_scene_path):
    scene = load_named("cosine-n", {"n": 3, "resolution": 16})
    assert scene.info["host"] == "erw6"
    assert scene.n_triangles == 804 + 2 * 16 ** 2
    mirror = scene.materials[int(scene.triangles.material[-1])]
    assert max(mirror.reflectance) >= 0.9


def test_cosine_sits_in_the_kitchen_when_it_is_found(scene_path):
    scene = load_named("cosine-n", {"resolution": 8}, time=5.0)
    assert scene.info["host"] == "bart-kitchen"
    assert scene.n_triangles == 110_561 + 128


def test_cosine_surface_follows_its_formula():
    from scenes.cosine import cosine_surface
    vertices, faces, normals = cosine_surface(3.0, 12)
    x, y, z = vertices.T
    np.testing.assert_allclose(z, np.cos(3 * x) * np.cos(3 * y))
    assert len(faces) == 2 * 12 ** 2 and np.all(normals[:, 2] > 0)


@pytest.mark.parametrize("name, params", [("spd-rings", {"size_factor": 0}), ("erw6", {"subdivisions": -1}),
                                          ("cosine-n", {"n": 0}), ("cosine-n", {"resolution": 1.5})])
def test_bad_procedural_parameters(no_scene_path, name, params):
    with pytest.raises(ConfigError):
        load_named(name, params)


def test_catalog_lists_the_library(no_scene_path):
    catalog = entries()
    for name in ("bart-kitchen", "bart-museum", "bart-robots", "spd-rings", "erw6", "cosine-n"):
        assert name in catalog
    assert all(catalog[n].animated for n in ("bart-kitchen", "bart-museum", "bart-robots"))
    rows = {row["name"]: row for row in describe(load=False)}
    assert not rows["bart-kitchen"]["files_found"] and rows["erw6"]["files_found"]


def test_obj_relative_indices_refer_to_the_vertices_just_before(tmp_path):
    """``f -4 -3 -2 -1`` after a second object's vertices means those four vertices (trimesh alone
    resolved them against the wrong list and put the Cornell box's walls onto its blocks)."""
    from scenes.catalog import load_path

    obj = tmp_path / "two.obj"
    obj.write_text("o floor\nv 0 0 0\nv 10 0 0\nv 10 0 10\nv 0 0 10\nf -4 -3 -2 -1\n"
                   "o wall\nv 0 0 10\nv 10 0 10\nv 10 5 10\nv 0 5 10\nf -4 -3 -2 -1\n"
                   "o roof\nv 0 5 0\nv 10 5 0\nv 10 5 10\nf 9 -2 -1\n")
    tris = load_path(str(obj)).triangles
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1)
    assert corners.shape == (5, 3, 3)
    floor = corners[np.all(corners[:, :, 1] == 0, axis=1)]
    wall = corners[np.all(corners[:, :, 2] == 10, axis=1) & np.any(corners[:, :, 1] == 5, axis=1)]
    roof = corners[np.all(corners[:, :, 1] == 5, axis=1)]
    assert len(floor) == 2 and len(wall) == 2 and len(roof) == 1
    assert sorted(map(tuple, roof[0].tolist())) == [(0, 5, 0), (10, 5, 0), (10, 5, 10)]


def test_cornell_box_walls_span_the_room(scene_path):
    from scenes.catalog import load_named

    scene = load_named("cornell-box")
    by_material = {}
    tris = scene.triangles
    for m, material in enumerate(scene.materials):
        sel = tris.material == m
        by_material[material.name] = np.concatenate([tris.v0[sel], tris.v1[sel], tris.v2[sel]])
    red, green = by_material["red"], by_material["green"]
    assert np.all(red[:, 0] > 549) and np.ptp(red[:, 2]) > 559 and np.ptp(red[:, 1]) > 548
    assert np.all(green[:, 0] == 0) and np.ptp(green[:, 2]) > 559


def test_kitchen_lights_parameter_keeps_the_first_lights(scene_path):
    """lights = N keeps the first N of the kitchen's six point lights, in kitchen.aff's order."""
    full = load_named("bart-kitchen")
    assert len(full.lights) == 6
    one = load_named("bart-kitchen", {"lights": 1})
    assert [(l.position, l.color) for l in one.lights] == [(full.lights[0].position, full.lights[0].color)]
    assert one.lights[0].position == (2.15, 2.0, 0.9)           # the file's first `l`
    assert [l.position for l in load_named("bart-kitchen", {"lights": 4}).lights] == \
        [l.position for l in full.lights[:4]]
    assert load_named("bart-kitchen", {"lights": 0}).lights == []
    assert one.n_triangles == full.n_triangles
    np.testing.assert_array_equal(one.triangles.v0, full.triangles.v0)
    with pytest.raises(ConfigError, match="has 6 point light"):
        load_named("bart-kitchen", {"lights": 7})
    with pytest.raises(ConfigError, match="lights must be"):
        load_named("bart-kitchen", {"lights": -1})


def test_lights_parameter_from_the_command_line(scene_path, tmp_path):
    """``--param lights=N`` reaches the loader: the museum's shadow rays follow its light count."""
    import json

    from engine.cli import main

    shadow = {}
    for value in ("0", "1", "all"):
        stats = tmp_path / f"{value}.json"
        assert main(["render", "--scene", "bart-museum", "--param", f"lights={value}", "--size", "16x16",
                     "--depth", "0", "-o", str(tmp_path / f"{value}.png"), "--stats", str(stats)]) == 0
        shadow[value] = json.loads(stats.read_text())["rays"]["shadow"]
    assert shadow["0"] == 0 < shadow["1"] < shadow["all"]
    assert main(["render", "--scene", "bart-museum", "--param", "lights=3", "--size", "16x16"]) == 2


#: An open room (floor, ceiling, back wall at z=10, side walls; no front wall at z=0), every
#: face turned inwards, with a small emitter under the ceiling near the back; then a box.
OPEN_ROOM_OBJ = """mtllib room.mtl
o walls
usemtl white
v 0 0 0
v 10 0 0
v 10 0 10
v 0 0 10
v 0 10 0
v 10 10 0
v 10 10 10
v 0 10 10
f 1 4 3 2
f 5 6 7 8
f 4 8 7 3
f 1 5 8 4
f 2 3 7 6
o lamp
usemtl light
v 6 9.9 7
v 8 9.9 7
v 8 9.9 9
v 6 9.9 9
f -4 -1 -2 -3
o block
usemtl white
v 1 0 1
v 2 0 1
v 2 1 1
v 1 1 1
f -4 -3 -2 -1
"""


def write_open_room(folder: Path) -> Path:
    (folder / "room.mtl").write_text("newmtl white\nKd 0.8 0.8 0.8\nnewmtl light\nKa 5 5 5\nKd 1 1 1\n")
    path = folder / "room.obj"
    path.write_text(OPEN_ROOM_OBJ)
    return path


def test_mesh_file_emitter_places_the_light_under_that_emitter(tmp_path):
    """The point light stands just inside the room from the emitter's own corners (x 6..8, z
    7..9 under y 9.9), not at the mean of the file's vertices: trimesh's maintain_order gives
    every geometry the whole vertex list, and the Cornell box's light landed in its tall block."""
    from scenes.catalog import load_path

    scene = load_path(str(write_open_room(tmp_path)))
    (light,) = scene.lights
    x, y, z = np.asarray(light.position) + np.asarray(scene.origin)
    assert 6 < x < 8 and 7 < z < 9 and 9 < y < 9.9


def test_auto_camera_looks_into_an_open_room_through_its_open_side(tmp_path):
    """Five walls facing in: from +z the camera saw the outside of the back wall (unlit, black);
    it now stands on the open -z side and its centre ray meets the back wall's lit inside."""
    from engine.core.scene import open_side
    from scenes.catalog import load_path

    scene = load_path(str(write_open_room(tmp_path)))
    eye = np.asarray(scene.camera.eye) + np.asarray(scene.origin)
    assert eye[2] < 0 and 0 < eye[0] < 10
    assert open_side(scene.triangles).tolist() == [0.0, 0.0, -1.0]


def test_auto_camera_keeps_plus_z_for_closed_meshes_and_floors():
    """A closed box faces every side equally and a floor faces up: both keep the +z camera."""
    import trimesh

    from engine.core.scene import open_side
    from engine.core.scene import make_triangles

    box = trimesh.creation.box((2.0, 3.0, 4.0))
    floor = trimesh.Trimesh([[0, 0, 0], [0, 0, 9], [9, 0, 9], [9, 0, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    for mesh in (box, floor):
        tris = make_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces), 0)
        assert open_side(tris).tolist() == [0.0, 0.0, 1.0]


def test_cornell_box_light_is_under_its_ceiling_emitter(scene_path):
    """The emitter spans x 213..343, z 227..332 at y 548; the light stood at y 212, in the tall block."""
    scene = load_named("cornell-box")
    x, y, z = scene.lights[0].position
    assert 213 < x < 343 and 227 < z < 332 and 500 < y < 548


def test_scenes_animated_column_means_animate_renders_it(no_scene_path):
    """Every catalog scene flagged animated has an animation path (its loader can animate), and
    cosine-n, whose kitchen follows --time around a static surface, is not flagged: `packetrt
    scenes` listed it "animated" and `packetrt animate` refused it."""
    from scenes.catalog import ANIMATORS

    rows = {row["name"]: row for row in describe(load=False)}
    for name, entry in entries().items():
        assert rows[name]["animated"] == (entry.animated and entry.loader in ANIMATORS), name
    assert not rows["cosine-n"]["animated"]


def test_scenes_listing_tells_time_following_scenes_apart(monkeypatch, capsys):
    """The animated column: yes (animate renders it), time (render --time moves it), no."""
    import scenes.catalog
    from engine.cli import main

    row = {"files_found": True, "missing": [], "triangles": 10, "lights": 1, "description": "", "loader": "x",
           "params": {}}
    rows = [{**row, "name": "a", "animated": True, "moves_with_time": True},
            {**row, "name": "t", "animated": False, "moves_with_time": True},
            {**row, "name": "s", "animated": False, "moves_with_time": False}]
    monkeypatch.setattr(scenes.catalog, "describe", lambda load=True: rows)
    assert main(["scenes"]) == 0
    lines = {line.split()[0]: line.split()[3] for line in capsys.readouterr().out.splitlines()[2:5]}
    assert lines == {"a": "yes", "t": "time", "s": "no"}


def test_gltf_nodes_place_and_instance_their_meshes(tmp_path):
    """A glTF scene graph places a mesh by its nodes' transforms, once per node: one sphere at
    the origin, moved by +5 in x, and mirrored about x = -5 (which must keep its faces turned
    out). The loader took the meshes alone: every one at its own origin."""
    import trimesh

    from scenes.catalog import load_path

    ball = trimesh.creation.icosphere(subdivisions=1)
    scene = trimesh.Scene()
    moved, mirrored = np.eye(4), np.diag([-1.0, 1.0, 1.0, 1.0])
    moved[0, 3], mirrored[0, 3] = 5.0, -10.0
    for node, matrix in (("a", np.eye(4)), ("b", moved), ("c", mirrored)):
        scene.add_geometry(ball, node_name=node, geom_name=f"ball-{node}", transform=matrix)
    path = tmp_path / "balls.glb"
    scene.export(str(path))
    loaded = load_path(str(path))
    assert loaded.n_triangles == 3 * len(ball.faces)
    tris = loaded.triangles
    centroids = (tris.v0 + tris.v1 + tris.v2).astype(np.float64) / 3 + np.asarray(loaded.origin)
    lo, hi = centroids.min(axis=0), centroids.max(axis=0)
    assert lo[0] < -10.5 and hi[0] > 5.5
    centre = np.round(centroids[:, :1] / 5.0) * 5.0  # each ball's centre: x = -10, 0 or 5
    assert sorted(set(centre[:, 0].tolist())) == [-10.0, 0.0, 5.0]
    outward = centroids - np.hstack([centre, np.zeros((len(centre), 2))])
    assert np.all(np.einsum("ij,ij->i", np.asarray(tris.ng, np.float64), outward) > 0)


def test_gltf_and_ply_colours_become_materials(tmp_path):
    """glTF base colours, base colour textures and metallic smooth mirrors, and a PLY's vertex
    colours, reach the materials; they were dropped (every such mesh drawn default grey)."""
    import trimesh
    from PIL import Image
    from trimesh.visual.material import PBRMaterial

    from engine.core.scene import Material
    from scenes.catalog import load_path

    box = trimesh.creation.box()
    uv = np.random.default_rng(1).random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, material=PBRMaterial(
        name="red", baseColorFactor=[255, 0, 0, 255], metallicFactor=0.0))
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.apply_translation((3.0, 0.0, 0.0))
    texels = (np.arange(4 * 4 * 3) * 5 % 256).astype(np.uint8).reshape(4, 4, 3)
    ball.visual = trimesh.visual.TextureVisuals(uv=np.random.default_rng(2).random((len(ball.vertices), 2)),
                                                material=PBRMaterial(name="tex", baseColorTexture=Image.fromarray(texels)))
    mirror = trimesh.creation.box()
    mirror.apply_translation((0.0, 3.0, 0.0))
    mirror.visual = trimesh.visual.TextureVisuals(uv=uv, material=PBRMaterial(
        name="chrome", baseColorFactor=[204, 204, 204, 255], metallicFactor=1.0, roughnessFactor=0.1))
    path = tmp_path / "coloured.glb"
    trimesh.Scene([box, ball, mirror]).export(str(path))
    materials = {m.name: m for m in load_path(str(path)).materials}
    assert materials["red"].diffuse == (1.0, 0.0, 0.0) and materials["red"].reflectance == (0.0, 0.0, 0.0)
    assert materials["tex"].texture.shape == (4, 4, 3)
    assert np.allclose(materials["tex"].texture * 255, texels, atol=0.5)
    assert materials["chrome"].reflectance == materials["chrome"].diffuse == (0.8, 0.8, 0.8)

    ply = trimesh.creation.icosphere(subdivisions=1)
    ply.visual.vertex_colors = [0, 255, 0, 255]
    ply.export(str(tmp_path / "green.ply"))
    (green,) = load_path(str(tmp_path / "green.ply")).materials
    assert green.diffuse == (0.0, 1.0, 0.0)
    trimesh.creation.icosphere(subdivisions=1).export(str(tmp_path / "plain.stl"))
    (plain,) = load_path(str(tmp_path / "plain.stl")).materials
    assert (plain.diffuse, plain.ambient, plain.texture) == (Material().diffuse, Material().ambient, None)


# -- found by a sweep of the scene loaders (session 38) ------------------------------------------
def write_texture(folder: Path) -> None:
    from PIL import Image

    texels = np.zeros((8, 8, 3), np.uint8)
    texels[:4, :4] = (255, 0, 0)
    Image.fromarray(texels).save(folder / "checker.png")


@pytest.mark.parametrize("faces", ["f 1/1 2/2 3/3 4/4\n", "f 1/1 2/2 3/3\nf 3/3 4/4 1/1\n"])
def test_obj_quads_keep_their_texture_coordinates(tmp_path, faces):
    """trimesh, keeping the file's vertex order, dropped the uvs of a mesh with a textured
    polygon: the quads of a textured export were drawn untextured. Both forms now load the
    same texture coordinates."""
    from scenes.catalog import load_path

    write_texture(tmp_path)
    (tmp_path / "c.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd checker.png\n")
    (tmp_path / "q.obj").write_text("mtllib c.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                                    "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl tex\n" + faces)
    tris = load_path(str(tmp_path / "q.obj")).triangles
    assert tris.uvs.shape == (2, 3, 2)
    corners = {tuple(np.round(p, 3)): tuple(np.round(uv, 3)) for t in range(2)
               for p, uv in zip((tris.v0[t], tris.v0[t] + tris.e1[t], tris.v0[t] + tris.e2[t]), tris.uvs[t])}
    assert corners[(1.0, 1.0, 0.0)] == (1.0, 1.0) and corners[(0.0, 1.0, 0.0)] == (0.0, 1.0)


def test_obj_and_mtl_text_quirks_are_read_or_named(tmp_path, capsys):
    """Tab-separated numbers and byte order marks were misread (an unclear error, or a material
    dropped unsaid); "Kd 0.5 0.5" made up a colour; a usemtl naming no material was silent."""
    from engine.cli import main
    from scenes.catalog import load_path

    (tmp_path / "t.obj").write_text("v\t0\t0\t0\nv\t1 0 0\nv 0\t1 0\nf\t1\t2\t3\n")
    assert load_path(str(tmp_path / "t.obj")).n_triangles == 1
    (tmp_path / "b.mtl").write_bytes(b"\xef\xbb\xbfnewmtl red\nKd 1 0 0\n")
    (tmp_path / "b.obj").write_bytes(b"\xef\xbb\xbfmtllib b.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n")
    assert [(m.name, m.diffuse) for m in load_path(str(tmp_path / "b.obj")).materials] == [("red", (1.0, 0.0, 0.0))]
    (tmp_path / "two.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl odd\nKd 0.5 0.5\n")
    (tmp_path / "two.obj").write_text("mtllib two.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n")
    with pytest.raises(SceneError, match=r"two\.mtl:4: 'Kd' takes one value \(grey\) or three"):
        load_path(str(tmp_path / "two.obj"))
    (tmp_path / "u.obj").write_text("mtllib b.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl zzz\nf 1 2 3\n")
    out = ["--size", "8x8", "-o", str(tmp_path / "u.png")]
    assert main(["render", "--scene", str(tmp_path / "u.obj"), *out]) == 0
    assert "usemtl 'zzz' names no material" in capsys.readouterr().err
    assert main(["render", "--scene", str(tmp_path / "u.obj"), *out, "--strict"]) == 2


@pytest.mark.parametrize("name, text, message", [
    ("few.off", "OFF\n3 5 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "declares 5 faces, but the file holds 1"),
    ("cut.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 2\n", "declares 2 faces, but the file holds 1"),
    ("cut.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
                "3 0 1 2\n3 0 2\n", "face 1 ('3 0 2') lists fewer corners"),
])
def test_mesh_files_cut_short_in_their_faces_are_named(tmp_path, name, text, message):
    """An OFF or ASCII PLY cut short among its faces loaded what was left, without a word."""
    from scenes.catalog import load_path

    (tmp_path / name).write_text(text)
    with pytest.raises(SceneError, match=re.escape(message)):
        load_path(str(tmp_path / name))


@pytest.mark.parametrize("cut, message", [
    (lambda b, a: b[:len(b) // 2], "the binary STL header counts 80 triangles (4,084 bytes), but the file has 2,042"),
    (lambda b, a: b[:60], "a binary STL starts with an 84-byte header; the file has 60 bytes"),
    (lambda b, a: a[:1500], "the ASCII STL opens 6 facets and closes 5, and has no 'endsolid' line"),
])
def test_an_stl_cut_short_is_named(tmp_path, cut, message):
    """trimesh reads an STL cut short as one without triangles: the error said only that."""
    import trimesh

    from scenes.catalog import load_path

    sphere = trimesh.creation.icosphere(1)
    binary, text = trimesh.exchange.stl.export_stl(sphere), trimesh.exchange.stl.export_stl_ascii(sphere)
    piece = cut(binary, text)
    (tmp_path / "m.stl").write_bytes(piece if isinstance(piece, bytes) else piece.encode())
    with pytest.raises(SceneError, match=re.escape(message)):
        load_path(str(tmp_path / "m.stl"))
    (tmp_path / "whole.stl").write_bytes(binary)
    (tmp_path / "whole_ascii.stl").write_text(text)
    assert load_path(str(tmp_path / "whole.stl")).n_triangles == load_path(str(tmp_path / "whole_ascii.stl")).n_triangles == 80
