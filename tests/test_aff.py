"""The BART .aff loader on small handwritten files: every directive, includes, transforms,
keyframe interpolation at and between keys, and malformed input reported as FILE:LINE."""
from __future__ import annotations

import math
import re
import textwrap

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from engine.core.errors import ConfigError, SceneError
from scenes.aff import Track, cone_triangles, sphere_triangles
from scenes.aff_animation import aff_scene, load_aff

TRIANGLE_MESH = """
m
 vertices 3
   0 0 0
   1 0 0
   0 1 0
 triangles 1
   0 1 2
"""


def write(folder, name, text):
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def load(folder, text, time=0.0, **params):
    return aff_scene([write(folder, "scene.aff", text)], params, time)


def corners(scene):
    """f32[T,3,3] triangle corners in file order."""
    t = scene.triangles
    return np.stack([t.v0, t.v1, t.v2], axis=1)


def write_ppm(path, colour=(255, 0, 0)):
    from PIL import Image
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (2, 2), colour).save(path, format="PPM")


# ---------------------------------------------------------------------------------- directives

def test_view_background_lights_ambient_and_animation(tmp_path):
    scene = load(tmp_path, """
        b 0.5 0.5 1.0
        v
        from 1 2 3
        at 1 2 0
        up 0 1 0
        angle 40
        hither 0.01
        resolution 800 600
        am 2.5 2.5 2.5
        l 1 5 1
        l 2 5 2  0.3 0.4 0.5   # coloured
        a 0.0 20.0 800
    """ + TRIANGLE_MESH)
    assert scene.camera.eye == (1, 2, 3) and scene.camera.look_at == (1, 2, 0)
    assert scene.camera.fov == 40
    assert scene.background == (0.5, 0.5, 1.0) and scene.ambient_light == (2.5, 2.5, 2.5)
    assert [l.position for l in scene.lights] == [(1, 5, 1), (2, 5, 2)]
    assert [l.color for l in scene.lights] == [(1, 1, 1), (0.3, 0.4, 0.5)]
    assert scene.info["resolution"] == (800, 600) and scene.info["hither"] == 0.01
    assert scene.info["animation"] == {"start": 0.0, "end": 20.0, "frames": 800}
    assert scene.n_triangles == 1 and not scene.animated


def test_fm_and_nff_f_materials(tmp_path):
    scene = load(tmp_path, """
        fm 0.1 0.2 0.3  0.4 0.5 0.6  0.7 0.8 0.9  20 0.85 1.55
    """ + TRIANGLE_MESH + """
        f 1 0.5 0  0.8 0.3 40 0.25 1.3
        p 3  0 0 1  1 0 1  0 1 1
    """)
    fm, f = (scene.materials[i] for i in scene.triangles.material)
    assert fm.ambient == (0.1, 0.2, 0.3) and fm.diffuse == (0.4, 0.5, 0.6)
    assert fm.specular == (0.7, 0.8, 0.9) and fm.reflectance == (0.7, 0.8, 0.9)  # NFF: Ks mirrors
    assert (fm.shininess, fm.transmission, fm.ior) == (20, 0.85, 1.55)
    assert f.ambient == (0, 0, 0) and f.diffuse == pytest.approx((0.8, 0.4, 0.0))
    assert f.specular == f.reflectance == (0.3, 0.3, 0.3)
    assert (f.shininess, f.transmission, f.ior) == (40, 0.25, 1.3)


def test_material_state_carries_into_includes(tmp_path):
    write(tmp_path, "part.aff", TRIANGLE_MESH)
    scene = load(tmp_path, "fm 0 0 0  1 0 0  0 0 0  1 0 0\ni 0 part.aff\n")
    assert scene.materials[scene.triangles.material[0]].diffuse == (1, 0, 0)


def test_mesh_with_normals_and_texture_coordinates(tmp_path):
    write_ppm(tmp_path / "TextureFiles" / "red.ppm")
    scene = aff_scene([write(tmp_path, "aff/scene.aff", """
        m
        vertices 4
          0 0 0   1 0 0   1 1 0   0 1 0
        normals 2
          0 0 1   0 0 -1
        texturecoords 3 red.ppm
          0 0   1 0   1 1
        triangles 2
          0 1 2   0 0 0   0 1 2
          0 2 3   1 1 1   0 2 1
    """)], {}, 0.0)
    c = corners(scene)
    assert c.shape == (2, 3, 3)
    np.testing.assert_array_equal(c[1], [[0, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(scene.triangles.normals[1], [[0, 0, -1]] * 3)
    np.testing.assert_array_equal(scene.triangles.uvs[1], [[0, 0], [1, 1], [1, 0]])
    material = scene.materials[scene.triangles.material[0]]
    assert material.texture.shape == (2, 2, 3) and material.texture[0, 0].tolist() == [1, 0, 0]
    assert material.texture_name == "red.ppm"


def test_texture_next_to_the_including_file(tmp_path):
    write_ppm(tmp_path / "green.ppm", (0, 255, 0))
    scene = load(tmp_path, "tt green.ppm  0 0 0 0 0  1 0 0 1 0  0 1 0 0 1\n")
    assert scene.materials[0].texture[1, 1].tolist() == [0, 1, 0]
    np.testing.assert_array_equal(scene.triangles.uvs[0], [[0, 0], [1, 0], [0, 1]])


def test_polygons_are_fan_triangulated(tmp_path):
    scene = load(tmp_path, """
        p 5
          0 0 0  1 0 0  1.5 1 0  0.5 2 0  -0.5 1 0
        pp 4
          0 0 1  0 0 1   1 0 1  0 0 1   1 1 1  0 0 1   0 1 1  0 0 1
    """)
    c = corners(scene)
    assert len(c) == 3 + 2
    np.testing.assert_array_equal(c[:3, 0], [[0, 0, 0]] * 3)          # fan around vertex 0
    np.testing.assert_array_equal(c[2], [[0, 0, 0], [0.5, 2, 0], [-0.5, 1, 0]])
    np.testing.assert_array_equal(scene.triangles.normals[3:], np.tile([0, 0, 1], (2, 3, 1)))
    assert scene.info["primitives"]["p"] == 1 and scene.info["primitives"]["pp"] == 1


@pytest.mark.parametrize("resolution", [1, 2, 3])
def test_spheres_and_cones_are_tessellated(tmp_path, resolution):
    scene = load(tmp_path, "s 1 2 3 0.5\nc 0 0 0 0.2  0 1 0 0.1\n", tessellation=resolution)
    assert scene.n_triangles == 12 * resolution ** 2 + 8 * resolution
    sphere = corners(scene)[: 12 * resolution ** 2].reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(sphere - [1, 2, 3], axis=1), 0.5, rtol=1e-6)
    c, n = sphere_triangles((0, 0, 0), 1.0, resolution)
    assert np.all(np.einsum("tij,tj->t", n, np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])) > 0)  # outwards
    c, n = cone_triangles((0, 0, 0), 1.0, (0, 2, 0), 1.0, resolution)
    np.testing.assert_allclose(np.hypot(c[..., 0], c[..., 2]), 1.0)


def test_static_transform_scales_then_rotates_then_translates(tmp_path):
    scene = load(tmp_path, """
        xs 2 2 2
           0 0 1 90
           10 0 0
        {
          p 3  1 0 0  0 1 0  0 0 1
        }
    """)
    np.testing.assert_allclose(corners(scene)[0], [[10, 2, 0], [8, 0, 0], [10, 0, 2]], atol=1e-6)


def test_nested_transforms_and_includes_relative_to_the_including_file(tmp_path):
    write(tmp_path, "sub/leaf.aff", "p 3  0 0 0  1 0 0  0 1 0\n")
    write(tmp_path, "sub/branch.aff", "xs 1 1 1  1 0 0 0  0 5 0 { i 0 leaf.aff }\n")
    scene = load(tmp_path, """
        xs 1 1 1  1 0 0 0  100 0 0
        {
          i 0 sub/branch.aff
        }
        i 0 sub/leaf.aff
    """)
    c = corners(scene)
    np.testing.assert_allclose(c[0, 0], [100, 5, 0])
    np.testing.assert_allclose(c[1, 0], [0, 0, 0])
    assert scene.info["files"] == 3


def test_normals_follow_the_inverse_transpose(tmp_path):
    scene = load(tmp_path, """
        xs 1 4 1  0 0 1 0  0 0 0 {
          pp 3  0 0 0  1 1 0   1 0 0  1 1 0   0 1 0  1 1 0
        }
    """)
    n = scene.triangles.normals[0, 0]
    np.testing.assert_allclose(n, np.array([4, 1, 0]) / math.sqrt(17), rtol=1e-6)


# ------------------------------------------------------------------------------------ animation

def keyed(name, channel, keys):
    rows = "\n".join(" ".join(str(x) for x in key) for key in keys)
    return f"k {name}\n{{\n{channel} {len(keys)}\n{rows}\n}}\n"


def moved_origin(tmp_path, keyframes, time):
    """Where the animated block's vertex (0, 0, 0) is at ``time``."""
    scene = load(tmp_path, "x mover\n{\n p 3  0 0 0  1 0 0  0 1 0\n}\n" + keyframes, time)
    return corners(scene)[0, 0].astype(np.float64), scene


def test_translation_keys_hit_their_values_and_interpolate(tmp_path):
    keys = keyed("mover", "transl", [(0, 0, 0, 0, 0, 0, 0), (1, 1, 0, 0, 0, 0, 0), (2, 1, 2, 0, 0, 0, 0)])
    for time, expected in ((0, (0, 0, 0)), (1, (1, 0, 0)), (2, (1, 2, 0)), (-5, (0, 0, 0)), (9, (1, 2, 0))):
        np.testing.assert_allclose(moved_origin(tmp_path, keys, time)[0], expected, atol=1e-6)
    # Catmull-Rom (T = C = B = 0): the tangent at key 1 is (P2 - P0) / 2 = (0.5, 1, 0); the end
    # tangents are the chords, so at t = 0.5: P = 0.5 P0 + 0.125 T0 + 0.5 P1 - 0.125 T1.
    expected = 0.5 * np.array([1, 0, 0]) + 0.125 * np.array([1, 0, 0]) - 0.125 * np.array([0.5, 1, 0])
    np.testing.assert_allclose(moved_origin(tmp_path, keys, 0.5)[0], expected, atol=1e-6)


def test_tension_one_eases_in_and_out(tmp_path):
    keys = keyed("mover", "transl", [(0, 0, 0, 0, 1, 0, 0), (1, 4, 0, 0, 1, 0, 0)])
    np.testing.assert_allclose(moved_origin(tmp_path, keys, 0.25)[0], (4 * 0.15625, 0, 0), atol=1e-6)
    np.testing.assert_allclose(moved_origin(tmp_path, keys, 0.5)[0], (2, 0, 0), atol=1e-6)


def test_non_uniform_key_spacing_keeps_the_velocity_continuous():
    track = Track("transl", np.array([0.0, 1.0, 3.0]), np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]]),
                  np.zeros((3, 3)))
    # Keys on a straight line at unit speed: the spline must be that line, not bulge.
    for t in np.linspace(0, 3, 13):
        np.testing.assert_allclose(track.at(t), [t, 0, 0], atol=1e-9)


def test_rotation_keys_about_one_axis_spin_through_many_turns(tmp_path):
    keys = keyed("mover", "rot", [(t, 0, 0, 1, 90 * t, 0, 0, 0) for t in range(9)])   # 720 degrees
    scene_text = "x mover\n{\n p 3  1 0 0  2 0 0  1 1 0\n}\n" + keys
    for time in (0, 1, 2.5, 3, 6.5, 8):
        vertex = corners(load(tmp_path, scene_text, time))[0, 0]
        angle = math.radians(90 * time)
        np.testing.assert_allclose(vertex, (math.cos(angle), math.sin(angle), 0), atol=1e-5)


def test_rotation_between_two_axes_passes_through_both_keys(tmp_path):
    keys = keyed("mover", "rot", [(0, 0, 1, 0, 90, 0, 0, 0), (1, 1, 0, 0, 90, 0, 0, 0)])
    text = "x mover\n{\n p 3  0 0 1  1 0 0  0 1 0\n}\n" + keys
    np.testing.assert_allclose(corners(load(tmp_path, text, 0))[0, 0], (1, 0, 0), atol=1e-6)   # y-turn
    np.testing.assert_allclose(corners(load(tmp_path, text, 1))[0, 0], (0, -1, 0), atol=1e-6)  # x-turn
    middle = corners(load(tmp_path, text, 0.5))[0, 0]
    assert abs(np.linalg.norm(middle) - 1) < 1e-5                                        # rigid


def test_scale_keys_and_repeated_or_restarted_keys():
    track = Track("scale", np.array([0.0, 0.0, 1.0, 2.0, 1.0, 2.0]),
                  np.array([[5.0] * 3, [1.0] * 3, [2.0] * 3, [9.0] * 3, [3.0] * 3, [4.0] * 3]),
                  np.zeros((6, 3)))
    # Later keys win: (0: 1), then the restart at 1 replaces (1: 2) and (2: 9).
    assert track.times.tolist() == [0.0, 1.0, 2.0]
    np.testing.assert_allclose(track.at(0.0), [1, 1, 1])
    np.testing.assert_allclose(track.at(1.0), [3, 3, 3])
    np.testing.assert_allclose(track.at(2.0), [4, 4, 4])


def test_animated_camera_named_camera(tmp_path):
    text = ("v from 0 0 5 at 0 0 0 up 0 1 0 angle 30\n" + TRIANGLE_MESH
            + "k camera {\n transl 2\n 0 1 2 3 0 0 0\n 2 3 2 3 0 0 0\n"
              " rot 1\n 0 0 1 0 180 0 0 0\n}\n")
    scene = load(tmp_path, text, 1.0)
    assert scene.animated and scene.info["camera"] == "animated" and scene.camera.fov == 30
    np.testing.assert_allclose(scene.camera.eye, (2, 2, 3), atol=1e-9)
    np.testing.assert_allclose(np.subtract(scene.camera.look_at, scene.camera.eye), (0, 0, 1), atol=1e-9)
    static = load(tmp_path, text, 1.0, camera="static")
    assert static.camera.eye == (0, 0, 5) and static.info["camera"] == "static"


def test_animated_triangles_blend_linearly_between_keys(tmp_path):
    text = """
        tpa 2
          0
          0 0 0  0 0 1
          1 0 0  0 0 1
          0 1 0  0 0 1
          2
          0 0 4  0 1 0
          1 0 4  0 1 0
          0 1 4  0 1 0
    """
    for time, z in ((0, 0), (0.5, 1), (2, 4), (3, 4), (-1, 0)):
        scene = load(tmp_path, text, time)
        assert corners(scene)[0, :, 2].tolist() == [z] * 3
    normal = load(tmp_path, text, 1.0).triangles.normals[0, 0]
    np.testing.assert_allclose(normal, np.array([0, 1, 1]) / math.sqrt(2), rtol=1e-6)
    assert load(tmp_path, text, 1.0).info["tpa_triangles"] == 1


def test_transform_without_keyframes_is_the_identity_and_is_reported(tmp_path):
    scene = load(tmp_path, "x lonely { p 3  0 0 0  1 0 0  0 1 0 }\n")
    np.testing.assert_array_equal(corners(scene)[0, 1], [1, 0, 0])
    assert scene.info["unkeyed_transforms"] == ["lonely"]


def test_keyframes_may_come_after_their_use_and_from_another_file(tmp_path):
    write(tmp_path, "anim.aff", keyed("mover", "transl", [(0, 0, 0, 0, 0, 0, 0), (1, 0, 0, 10, 0, 0, 0)]))
    scene = load(tmp_path, "x mover { p 3  0 0 0  1 0 0  0 1 0 }\ni 0 anim.aff\n", 0.5)
    np.testing.assert_allclose(corners(scene)[0, 0], (0, 0, 5), atol=1e-6)
    assert scene.info["animated_triangles"] == 1 and scene.info["static_triangles"] == 0


# ---------------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("text, line, words", [
    ("b 0 0 0\nbogus 1 2 3\n", 2, "unknown directive 'bogus'"),
    ("m\n vertices 3\n 0 0 0\n 1 0 0\n 0 1 0\n triangles 2\n 0 1 2\n", 7, "expected 6 integers"),
    ("m\n vertices 3\n 0 0 0\n 1 0 0\n 0 1\n", 5, "expected 9 numbers"),
    ("s 0 0 zero 1\n", 1, "expected a number for 's'"),
    ("l 1 2 3\nl 4 x 6\n", 2, "got 'x'"),
    ("m\n vertices 3\n 0 0 0\n 1 0 0\n 0 1 0\n triangles 1\n 0 1 3\n", 1, "vertex 3"),
    ("m\n triangles 1\n", 2, "'vertices'"),
    ("xs 1 1 1  0 0 1 0  0 0 0\np 3 0 0 0 1 0 0 0 1 0\n", 2, "expected '{'"),
    ("xs 1 1 1  0 0 1 0  0 0 0 {\np 3 0 0 0 1 0 0 0 1 0\n", 1, "not closed"),
    ("p 3 0 0 0 1 0 0 0 1 0\n}\n", 2, "closes no block"),
    ("p 2 0 0 0 1 0 0\n", 1, "at least 3 vertices"),
    ("\n\ni 0 missing.aff\n", 3, "'missing.aff' not found"),
    ("tt nowhere.ppm 0 0 0 0 0 1 0 0 1 0 0 1 0 0 1\n", 1, "texture 'nowhere.ppm' not found"),
    ("k cam {\n transl 1\n 0 1 2 3 0 0 0\n wobble 1\n}\n", 4, "got 'wobble'"),
    ("v\nfrom 0 0 1\nat 0 0 0\n", 1, "missing up, angle"),
])
def test_malformed_input_names_file_and_line(tmp_path, text, line, words):
    path = write(tmp_path, "bad.aff", text)
    with pytest.raises(SceneError) as caught:
        aff_scene([path], {}, 0.0)
    message = str(caught.value)
    assert message.startswith(f"{path}:{line}: "), message
    assert words in message and "\n" not in message


def test_error_inside_an_include_names_the_included_file(tmp_path):
    broken = write(tmp_path, "parts/broken.aff", "p 3\n 0 0 0\n 1 0 0\n 0 one 0\n")
    with pytest.raises(SceneError, match=f"^{re.escape(str(broken))}:4: expected a number"):
        load(tmp_path, "i 0 parts/broken.aff\n")


def test_self_include_is_reported(tmp_path):
    write(tmp_path, "loop.aff", "i 0 loop.aff\n")
    with pytest.raises(SceneError, match="includes itself"):
        load(tmp_path, "i 0 loop.aff\n")


def test_empty_scene_and_missing_root(tmp_path):
    with pytest.raises(SceneError, match="no geometry"):
        load(tmp_path, "b 0 0 0\n")
    with pytest.raises(SceneError, match="not found"):
        load_aff(tmp_path / "absent.aff")


@pytest.mark.parametrize("params", [{"tessellation": 0}, {"tessellation": 2.5}, {"camera": "moving"}])
def test_bad_parameters_are_config_errors(tmp_path, params):
    with pytest.raises(ConfigError):
        load(tmp_path, TRIANGLE_MESH, **params)


def test_aff_files_load_by_path(tmp_path):
    from scenes.catalog import load_path
    scene = load_path(str(write(tmp_path, "direct.aff", TRIANGLE_MESH)))
    assert scene.n_triangles == 1 and scene.name == "direct"


# ---------------------------------------------------------------------------------- lights = N

LIGHTS_MAIN = """
l 1 5 1
i 1 more.aff
l 3 5 3
""" + TRIANGLE_MESH


def test_lights_keeps_the_first_n_in_file_order_includes_where_they_stand(tmp_path):
    write(tmp_path, "more.aff", "l 2 5 2\n")
    every = load(tmp_path, LIGHTS_MAIN)
    assert [l.position for l in every.lights] == [(1, 5, 1), (2, 5, 2), (3, 5, 3)]
    assert every.info["file_lights"] == 3
    assert load(tmp_path, LIGHTS_MAIN, lights="all").lights == every.lights
    for n in range(4):
        assert load(tmp_path, LIGHTS_MAIN, lights=n).lights == every.lights[:n]


def test_lights_zero_leaves_no_light_not_a_made_up_one(tmp_path):
    assert load(tmp_path, TRIANGLE_MESH, lights=0).lights == []
    assert len(load(tmp_path, TRIANGLE_MESH).lights) == 1       # "all" of none: the default light, as before
    assert load(tmp_path, "l 1 1 1\n" + TRIANGLE_MESH, lights=0).lights == []


def test_lights_beyond_the_file_names_its_count(tmp_path):
    with pytest.raises(ConfigError, match=r"^lights = 3, but scene.aff has 2 point light\(s\); give 0..2 or \"all\"$"):
        load(tmp_path, "l 1 1 1\nl 2 2 2\n" + TRIANGLE_MESH, lights=3)


@pytest.mark.parametrize("bad", [-1, 1.5, True, "two", "ALL", [1]])
def test_bad_lights_values_are_one_line_config_errors(tmp_path, bad):
    with pytest.raises(ConfigError, match=r"^scene parameter lights must be \"all\" or an integer >= 0 .*got ") as caught:
        load(tmp_path, TRIANGLE_MESH, lights=bad)
    assert "\n" not in str(caught.value)


# Every character ``str.split()`` treats as a gap in latin-1 text, beside word characters.
_TOKEN_TEXT = st.text(alphabet=" \t\n\r\x0b\x0c\x1c\x1d\x1e\x1f\x85\xa0ab1.-{}\xff\x00", max_size=60)


@given(_TOKEN_TEXT)
def test_words_and_their_lines_are_those_of_a_split_per_line(text):
    """``words_and_lines`` counts newlines in one numpy pass; it must give the words and lines
    that splitting each line would, whatever whitespace (latin-1's \\x85 and \\xa0 included)."""
    from scenes.aff import words_and_lines

    per_line = [line.split() for line in text.split("\n")]
    words, line_of, last_line = words_and_lines(text)
    assert words == [w for line in per_line for w in line]
    assert line_of.dtype == np.int32
    assert line_of.tolist() == [n + 1 for n, line in enumerate(per_line) for _ in line]
    assert last_line == len(per_line)


@pytest.mark.parametrize("ior, kept", [(0.0, 1.0), (1.33, 1.33)])
def test_an_ior_of_zero_means_none_given(tmp_path, ior, kept):
    scene = load(tmp_path, f"f 1 1 1  0.5 0.5 10 0.5 {ior}\n" + TRIANGLE_MESH)
    assert scene.materials[scene.triangles.material[0]].ior == pytest.approx(kept)


def test_a_negative_ior_is_an_error_not_one(tmp_path):
    with pytest.raises(SceneError, match=r"ior must be a number in \[0.001, 1000\], got -1.5"):
        load(tmp_path, "f 1 1 1  0.5 0.5 10 0.5 -1.5\n" + TRIANGLE_MESH)
