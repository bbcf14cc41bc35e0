"""Issue 16, case by case: each user mistake or fault gives one line and exit code 2 (or a
correct result), never a traceback, and an earlier output survives a failed write.

Every test here failed on the code before the fix (noted where the old behaviour was a
traceback, a silent wrong answer or a lost file). The property-based side of the same
promise is tests/test_fuzz_inputs.py; the writer itself is tests/test_hardening_outputs.py.
"""
from __future__ import annotations

import json
import os
import re
import resource
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from engine.cli import main
from engine.core.errors import ConfigError, ConfigTypeError, PacketrtError, SceneError
from conftest import needs_shared_scenes

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "benchmarks" / "smoke.toml"
TINY = ["--size", "16x16", "--depth", "1"]


def run(argv, capsys):
    """(exit code, stderr lines) of the CLI run in this process (a command-line mistake exits
    through SystemExit(2), as argparse's own do)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.splitlines()


def one_error(argv, capsys, *fragments):
    """The run exits 2 with exactly one stderr line holding every fragment."""
    code, lines = run(argv, capsys)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("packetrt: error: ")
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def obj(tmp_path, text, name="m.obj"):
    path = tmp_path / name
    path.write_text(text)
    return path


TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"


# 1. Scene parameters are checked against the catalog's [limits] before any work ------------
@pytest.mark.parametrize("param, fragment", [("subdivisions=99", "subdivisions must be in 0..6"),
                                             ("checks=0", "checks must be in 1..256"),
                                             ("checks=nan", "checks"), ("subdivisions='x'", "subdivisions")])
def test_scene_parameters_have_a_type_and_a_range(param, fragment, capsys):
    # Before: subdivisions=99 allocated until the machine ran out, checks=0 was a traceback.
    one_error(["render", "--param", param, *TINY, "-o", "/nonexistent/never.png"], capsys, fragment)


def test_every_catalog_parameter_has_limits():
    from scenes.catalog import entries

    for entry in entries().values():
        assert set(entry.params) <= set(entry.limits), entry.name


# 2. Huge coordinates: far scenes are re-centred, what float32 cannot hold is refused --------
def test_a_scene_far_from_the_origin_renders_like_one_at_it(tmp_path, capsys):
    # Before: a unit triangle at x = 1e14 rendered silently black.
    near = obj(tmp_path, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "near.obj")
    far = obj(tmp_path, "v 100000000000000 0 0\nv 100000000000001 0 0\nv 100000000000000 1 0\nf 1 2 3\n",
              "far.obj")
    for scene in (near, far):
        assert run(["render", "--scene", scene, *TINY, "-o", tmp_path / f"{scene.stem}.png"], capsys)[0] == 0
    near_png, far_png = (tmp_path / "near.png").read_bytes(), (tmp_path / "far.png").read_bytes()
    assert far_png == near_png
    from PIL import Image

    assert np.asarray(Image.open(tmp_path / "far.png")).any()


@pytest.mark.parametrize("text, fragment", [
    ("v -1e16 0 0\nv 1e16 1 0\nv 0 1e16 1\nf 1 2 3\n", "supports geometry within"),  # before: traceback
    ("v 1e39 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n", "must be a number in [-1e+30, 1e+30], got 1e+39"),
])
def test_coordinates_beyond_the_supported_range_are_one_line(tmp_path, capsys, text, fragment):
    one_error(["render", "--scene", obj(tmp_path, text), *TINY, "-o", tmp_path / "x.png"], capsys, fragment)


def test_a_camera_too_far_away_is_one_line(tmp_path, capsys):
    aff = tmp_path / "far.aff"
    aff.write_text("v from 0 0 1e16 at 0 0 0 up 0 1 0 angle 45\nl 0 0 5\np 3 0 0 0 1 0 0 0 1 0\n")
    one_error(["render", "--scene", aff, *TINY, "-o", tmp_path / "x.png"], capsys, "camera eye", "1e+12")


# 3. A failed write leaves the earlier output as it was -------------------------------------
def test_a_full_disk_keeps_the_earlier_image(tmp_path):
    target = tmp_path / "render.png"
    earlier = os.urandom(50_000)
    target.write_bytes(earlier)

    def small_files():  # what `ulimit -f 2` does: writes past 2 KiB fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))

    # First the same render without the limit: numba's disk cache must hold the kernels, or
    # the limited run would fail writing the cache rather than the image. Here in the test's
    # process (the same command, so the same kernels): what it compiles numba writes to the disk
    # cache, and what it finds loaded costs nothing, where a second interpreter cost seconds.
    assert main(["render", "--size", "64x64", "-o", str(tmp_path / "warm" / "render.png")]) == 0
    shutil.rmtree(tmp_path / "warm")
    done = subprocess.run([sys.executable, "-m", "engine.cli", "render", "--size", "64x64", "-o", str(target)],
                          cwd=ROOT, capture_output=True, text=True, preexec_fn=small_files, timeout=600)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "cannot write image" in done.stderr
    assert target.read_bytes() == earlier
    assert [p.name for p in tmp_path.iterdir()] == ["render.png"]  # no temporary left behind


# 4. The memory check uses the memory available now -----------------------------------------
def test_memory_check_uses_available_not_total_memory():
    from engine.render.config import available_memory

    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    assert available_memory() < total  # before: it was the total


def test_running_out_of_memory_is_one_line(monkeypatch, capsys, tmp_path):
    from engine.render import whitted

    def exhausted(self, *args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(whitted.WhittedRenderer, "render", exhausted)
    one_error(["render", *TINY, "-o", tmp_path / "x.png"], capsys, "out of memory")


# 5, 8, 9, 13. MTL files: corrupt texture, mtllib without a name, illum nan, missing files ----
def test_a_corrupt_texture_is_one_line(tmp_path, capsys):
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 1 1\nmap_Kd bad.png\n")
    scene = obj(tmp_path, "mtllib m.mtl\nusemtl a\n" + TRIANGLE)
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "m.mtl:3", "bad.png")


def test_mtllib_without_a_name_is_one_line(tmp_path, capsys):
    scene = obj(tmp_path, "mtllib\n" + TRIANGLE)
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "m.obj:1", "mtllib")


@pytest.mark.parametrize("line, fragment", [("illum nan", "'illum'"), ("Kd nan 1 1", "'Kd'"),
                                            ("Ns inf", "'Ns'"), ("d 2", "'d'"), ("Ka -1 0 0", "'Ka'")])
def test_bad_mtl_numbers_are_one_line(tmp_path, capsys, line, fragment):
    (tmp_path / "m.mtl").write_text(f"newmtl a\n{line}\n")
    scene = obj(tmp_path, "mtllib m.mtl\nusemtl a\n" + TRIANGLE)
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "m.mtl:2", fragment)


@pytest.mark.parametrize("missing", ["texture", "library"])
def test_a_missing_texture_or_library_warns_and_fails_under_strict(tmp_path, capsys, missing):
    if missing == "texture":
        (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 1 1\nmap_Kd gone.png\n")
        named = "gone.png"
    else:
        named = "m.mtl"
    scene = obj(tmp_path, "mtllib m.mtl\nusemtl a\n" + TRIANGLE)
    code, lines = run(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys)
    warnings = [line for line in lines if line.startswith("packetrt: warning: ")]
    assert code == 0 and len(warnings) == 1 and named in warnings[0]  # before: not a word
    one_error(["render", "--scene", scene, *TINY, "--strict", "-o", tmp_path / "y.png"], capsys, named, "--strict")


# 6, 10. Config files: not UTF-8, a non-table under [options] --------------------------------
def test_a_config_that_is_not_utf8_is_one_line(tmp_path, capsys):
    config = tmp_path / "latin.toml"
    config.write_bytes("[render]\n# caf\xe9\nwidth = 16\n".encode("latin-1"))
    one_error(["render", config, "-o", tmp_path / "x.png"], capsys, "latin.toml", "UTF-8")


def test_an_option_that_is_not_a_table_is_one_line(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text("[options]\nrayspace = 3\n")
    one_error(["render", config, "-o", tmp_path / "x.png"], capsys, "c.toml", "rayspace must be a table")


# 11. NaN and infinities in materials, lights, camera and configs -----------------------------
def aff_text(eye="0 0 5", fov="45", light="0 0 5", material=""):
    """A one-triangle .aff scene with the given camera eye, field of view, light and material."""
    return f"v from {eye} at 0 0 0 up 0 1 0 angle {fov}\nl {light}\n{material}p 3 0 0 0 1 0 0 0 1 0\n"


@pytest.mark.parametrize("text, fragment", [
    (aff_text(material="fm nan 0 0 1 1 1 0 0 0 1 0 1\n"), "'fm'"), (aff_text(light="inf 0 5"), "'l'"),
    (aff_text(eye="0 nan 5"), "view 'from'"), (aff_text(light="0 0 5 -1 1 1"), "light colour"),
    (aff_text(fov="0"), "camera fov"),
])
def test_non_finite_or_nonsense_scene_numbers_are_one_line(tmp_path, capsys, text, fragment):
    aff = tmp_path / "s.aff"
    aff.write_text(text)
    one_error(["render", "--scene", aff, *TINY, "-o", tmp_path / "x.png"], capsys, "s.aff", fragment)


@pytest.mark.parametrize("table", ["[scene]\ntime = nan\n", "[scene]\ntime = inf\n"])
def test_non_finite_config_numbers_are_one_line(tmp_path, capsys, table):
    config = tmp_path / "c.toml"
    config.write_text(table)
    one_error(["render", config, "-o", tmp_path / "x.png"], capsys, "scene.time")


# 12, 14. The --stats document: extra is filled, --time nan is refused, JSON is strict -------
def test_stats_extra_is_filled_and_time_nan_is_refused(tmp_path, capsys):
    stats = tmp_path / "s.json"
    assert run(["render", *TINY, "-o", tmp_path / "x.png", "--stats", stats], capsys)[0] == 0
    extra = json.loads(stats.read_text())["extra"]
    assert extra["scene_origin"] == [0.0, 0.0, 0.0] and extra["scene_warnings"] == [] and "plugins" in extra
    one_error(["render", *TINY, "--time", "nan", "-o", tmp_path / "y.png", "--stats", tmp_path / "t.json"],
              capsys, "--time")
    assert not (tmp_path / "t.json").exists()


def test_json_output_never_holds_nan():
    from engine.core.atomic import json_text

    assert json.loads(json_text({"a": float("nan"), "b": [float("inf"), np.float32(2)]})) == {"a": None, "b": [None, 2.0]}


# 15. The pair budget a too-small budget's error suggests is enough ---------------------------
def test_the_suggested_pair_budget_is_enough(tmp_path, capsys):
    # erw6 is procedural: the test needs no scene data (a clean clone's CI has none).
    config = tmp_path / "c.toml"
    argv = ["render", config, "--scene", "erw6", "--traversal", "primary=rayspace", "--depth", "0",
            "--size", "16x16", "-o", tmp_path / "x.png"]
    config.write_text("[options.rayspace]\npair_budget = 3\n")
    line = one_error(argv, capsys, "pair_budget")
    suggested = int(re.search(r"at least (\d+)", line).group(1))
    config.write_text(f"[options.rayspace]\npair_budget = {suggested}\n")
    assert run(argv, capsys)[0] == 0  # before: the suggestion stopped at the overflowing level


# 7, 16. Benchmark outputs: --out a file; a third run keeps the first run's results ----------
def test_bench_out_that_is_a_file_is_one_line(tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("keep me")
    one_error(["bench", SMOKE, "--out", taken], capsys, "is a file")
    assert taken.read_text() == "keep me"


def test_every_earlier_run_keeps_its_results(tmp_path, monkeypatch, capsys):
    from engine.bench import runner

    def stop(todo, source=None):
        raise PacketrtError("stopped before any work")

    monkeypatch.setattr(runner, "preflight", stop)
    results = tmp_path / "results.jsonl"
    for run_number in (1, 2, 3):
        results.write_text(f'{{"id": "run {run_number}"}}\n')
        code, lines = run(["bench", SMOKE, "--out", tmp_path], capsys)
        assert code == 2 and lines[-1] == "packetrt: error: stopped before any work"
    kept = sorted(p.read_text() for p in tmp_path.glob("results.jsonl.prev*"))
    assert kept == [f'{{"id": "run {n}"}}\n' for n in (1, 2, 3)]  # before: run 1's were overwritten


# 18. User mistakes are ValueError (or TypeError for the wrong type) ---------------------------
def test_user_mistakes_are_value_or_type_errors():
    from scenes.catalog import load_named

    assert issubclass(SceneError, ValueError) and issubclass(ConfigError, ValueError)
    assert issubclass(ConfigTypeError, TypeError) and issubclass(ConfigTypeError, PacketrtError)
    with pytest.raises(TypeError):
        load_named("whitted", {"checks": "many"})
    with pytest.raises(ValueError):
        load_named("whitted", {"checks": 0})


# 20. A mistyped option is one line with the nearest valid option ----------------------------
@pytest.mark.parametrize("argv, fragments", [(["render", "--sizee", "16x16"], ["--sizee", "did you mean --size?"]),
                                             (["rendr"], ["invalid choice"]), ([], ["required"]),
                                             (["render", "--packet", "x"], ["--packet"])])
def test_a_mistyped_command_line_is_one_line(argv, fragments, capsys):
    one_error(argv, capsys, *fragments)


@pytest.mark.parametrize("command", ["render", "render-audit", "show", "audit"])
def test_an_output_that_cannot_be_written_stops_the_command_before_its_work(tmp_path, capsys, monkeypatch, command):
    """A render used to run whole, write its image and only then fail on --stats; every output
    path is now checked first (``engine.core.atomic.output_file``)."""
    import engine.cli as cli

    monkeypatch.setattr(cli, "_load_scene", lambda *a: pytest.fail("the scene was loaded before the check"))
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    image = tmp_path / "image.png"
    bad = blocker / "out.json"
    argv = {"render": ["render", *TINY, "-o", image, "--stats", bad],
            "render-audit": ["render", *TINY, "--audit", "-o", image, "--stats", tmp_path],
            "show": ["show", *TINY, "-o", tmp_path],
            "audit": ["audit", *TINY, "--json", bad]}[command]
    option = {"render": "--stats", "render-audit": "--stats", "show": "-o", "audit": "--json"}[command]
    one_error(argv, capsys, option)
    assert not image.exists()


AFF_HEAD = ("v from 0 0 5 at 0 0 0 up 0 1 0 angle 45 hither 0.01 resolution 16 16\nl 0 5 5\n"
            "fm 0.1 0.1 0.1 0.7 0.7 0.7 0 0 0 1 0 1\n")


@pytest.mark.parametrize("body,fragment", [
    ("m vertices 99999999999999999999 0 0 0 triangles 0\n", ":4: expected an integer for the vertex count"),
    ("m vertices -3 triangles 0\n", ":4: expected a non-negative count for the vertex count, got -3"),
    ("s 0 0 0 1\na 0 1e29 3\n", ":5: 'a' end time must be within +-86400 s"),
    ("s 0 0 0 1\na 0 2 2.5\n", ":5: 'a' frame count must be a whole number in 1..100,000, got 2.5"),
    ("s 0 0 0 1\na 0 2 -3\n", ":5: 'a' frame count must be a whole number"),
    ("s 0 0 0 1\na 2 0 3\n", ":5: 'a' end time 0 is before the start time 2"),
])
def test_bad_aff_counts_and_animation_lines_are_one_line(tmp_path, capsys, body, fragment):
    """Before: a count past int64 was an OverflowError traceback, a negative one was reported as
    3 times itself, and an 'a' line's times and frame count were taken unchecked (1e29 seconds
    failed in the preview after every frame; 2.5 frames became 2)."""
    scene = obj(tmp_path, AFF_HEAD + body, "s.aff")
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, fragment)


def test_a_decompression_bomb_texture_in_an_aff_is_one_line(tmp_path, capsys):
    """A PPM whose header claims 20000 x 20000 pixels: Pillow refuses it (DecompressionBombError),
    which was a traceback on the .aff path (the MTL path already caught it)."""
    (tmp_path / "bomb.ppm").write_bytes(b"P6 20000 20000 255\n" + bytes(30))
    scene = obj(tmp_path, AFF_HEAD + "tt bomb.ppm 0 0 0 0 0 1 0 0 1 0 0 1 0 0 1\n", "s.aff")
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "bomb.ppm: cannot read texture")


MATRIX = ('name = "{name}"\nrepeat = 1\nembree = false\n[axes]\nscene = ["whitted"]\nresolution = [{res}]\n'
          'traversal = ["single"]\nfrustum = ["none"]\npacket = [4]\nrecursion = ["shadows"]\n')


@pytest.mark.parametrize("name,res,fragment", [
    ("t", '"\u00b2x\u00b2"', "resolution"),     # '²' passes str.isdigit() but not int(): a traceback before
    ("a\\u0000b", "16", "name: must be 1-100 letters"),  # a NUL byte: mkdir's ValueError before
    ("../x y", "16", "name: must be 1-100 letters"),
])
def test_matrix_names_and_numbers_are_checked_before_use(tmp_path, capsys, name, res, fragment):
    matrix = obj(tmp_path, MATRIX.format(name=name, res=res), "m.toml")
    one_error(["bench", matrix], capsys, "m.toml", fragment)


def test_a_paired_variant_with_unicode_digits_is_one_line(tmp_path, capsys):
    matrix = obj(tmp_path, MATRIX.format(name="t", res="16") + '[paired]\nvariants = ["single/none/4", "single/none/\u00b2"]\n', "m.toml")
    one_error(["bench", matrix, "--out", tmp_path / "o"], capsys, "expected TRAVERSAL/FRUSTUM/PACKET")


@pytest.mark.parametrize("text,fragment", [
    ('kind = "trimesh"\nmesh = 5\n', "[[mesh]]"),
    ('kind = "trimesh"\nqueries = 5\n[[mesh]]\nscene = "whitted"\n', "queries must be a list"),
    ('kind = "trimesh"\n[[mesh]]\nscene = "whitted"\nlabel = ["x"]\n', "mesh[0].label: must be a string"),
])
def test_trimesh_matrix_types_are_checked_before_any_query(tmp_path, capsys, text, fragment):
    """Before: a TypeError traceback (mesh = 5, queries = 5), or every query run and then a
    TypeError formatting the table (a list as the label)."""
    one_error(["bench", obj(tmp_path, text, "tm.toml"), "--out", tmp_path / "o"], capsys, "tm.toml", fragment)


def test_a_damaged_bench_record_is_measured_again_not_a_traceback(tmp_path):
    """A record whose id is a cell's but whose fields the tables cannot read (edited by hand) is
    skipped when read, so --resume runs its cell again; before, the report raised TypeError."""
    from engine.bench import results

    path = tmp_path / results.RESULTS
    path.write_text(json.dumps({"id": "abc", "seconds": "x"}) + "\n" + json.dumps({"id": "d", "kind": "dynamic"})
                    + "\n")
    records, complete = results.read_results(path)
    assert [r["id"] for r in records] == ["d"] and complete == path.stat().st_size


def test_damaged_frame_records_are_rendered_again_on_resume(tmp_path, capsys):
    """frames.json with records that are not what a frame writes (hand-edited): those frames are
    rendered again; before, a TypeError in the path summary."""
    scene = obj(tmp_path, AFF_HEAD + "a 0 1 2\nk m { transl 2 0 0 0 0 0 0 0 1 1 0 0 0 0 0 }\nx m { s 0 0 0 1 }\n", "moving.aff")
    out = tmp_path / "anim"
    argv = ["animate", "--scene", scene, *TINY, "-o", out]
    assert run(argv, capsys)[0] == 0
    document = json.loads((out / "frames.json").read_text())
    assert sorted(document["frames"]) == ["0", "1"]
    document["frames"] = {"0": "notadict", "1": 5}
    (out / "frames.json").write_text(json.dumps(document))
    code, _ = run(argv + ["--resume", "--stats", tmp_path / "s.json"], capsys)
    assert code == 0
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["frames_rendered"] == 2 and stats["frames_resumed"] == 0


# Python API inputs the kernels would trust (session 31's audit) --------------------------------
def test_mesh_faces_past_the_vertices_are_a_query_input_error():
    import trimesh
    from engine import RayMeshIntersector
    from engine.query.errors import QueryInputError

    mesh = trimesh.Trimesh(np.eye(3).tolist() + [[0, 0, 0]], [[0, 1, 2]], process=False)
    intersector = RayMeshIntersector(mesh)
    mesh.faces = np.array([[0, 1, 9]])  # before: IndexError inside the structure's build
    with pytest.raises(QueryInputError, match=r"mesh.faces\[0\] = \[0, 1, 9\] refers to a vertex"):
        intersector.intersects_first([[0.2, 0.2, 5]], [[0, 0, -1]])


def test_max_hits_beyond_int64_means_no_limit():
    import trimesh
    from engine import RayMeshIntersector

    intersector = RayMeshIntersector(trimesh.creation.box())
    tri, ray = intersector.intersects_id([[0, 0, 5]], [[0, 0, -1]], max_hits=2 ** 70)  # before: OverflowError
    assert len(tri) == 2 and (ray == 0).all()


def good_triangles():
    from engine.core.scene import make_triangles

    return make_triangles(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), [[0, 1, 2]], 0)


@pytest.mark.parametrize("field,value,fragment", [
    ("v0", np.zeros((2, 3), np.float32), "Triangles.e1 must be float32 of shape (2, 3)"),  # rows differ
    ("v0", np.zeros((1, 2), np.float32), "Triangles.v0 must be float32 of shape (1, 3), got float32 (1, 2)"),
    ("v1", np.zeros((1, 3), np.float64), "Triangles.v1 must be float32"),
    ("v2", np.full((1, 3), np.nan, np.float32), "Triangles.v2 holds non-finite numbers"),
    ("normals", np.zeros((2, 3, 3), np.float32), "Triangles.normals must be float32 of shape (1, 3, 3) or (0, 3, 3)"),
    ("uvs", np.zeros((5, 3, 2), np.float32), "Triangles.uvs"),
])
def test_triangles_handed_to_the_api_keep_their_contract(field, value, fragment):
    """Before: mismatched rows were read past their ends (garbage hits), float64 fields a numba
    TypingError, shapes an IndexError, NaN corners a misleading camera error."""
    from engine import RayTracer
    from engine.core.errors import SceneError

    tris = good_triangles()
    if field == "v0" and value.shape[0] == 2:
        tris = tris._replace(v0=value, material=np.zeros(2, np.int32))
    else:
        tris = tris._replace(**{field: value})
    with pytest.raises(SceneError) as caught:
        RayTracer(tris)
    assert fragment in str(caught.value) and isinstance(caught.value, ValueError)


def test_a_material_index_past_the_table_is_one_error():
    from engine.core.errors import SceneError
    from engine.core.scene import Material, SceneBuilder

    for index in (7, -3):  # before: a Scene that rendered, reading past the material table
        builder = SceneBuilder("t")
        builder.add_material(Material())
        builder.add_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], index)
        with pytest.raises(SceneError, match=f"material index {index} does not exist"):
            builder.build()


def test_misshapen_normals_and_uvs_name_their_shape():
    from engine.core.errors import SceneError
    from engine.core.scene import make_triangles

    corners, faces = np.eye(3), [[0, 1, 2]]
    with pytest.raises(SceneError, match=r"normals must have shape \(3, 3\) per vertex or \(1, 3, 3\) per corner"):
        make_triangles(corners, faces, 0, normals=np.zeros((2, 3)))  # before: IndexError
    with pytest.raises(SceneError, match="texture coordinates .* are not finite"):
        make_triangles(corners, faces, 0, uvs=np.full((3, 2), np.nan))  # before: taken silently


def test_a_nan_texture_coordinate_in_an_obj_is_one_line(tmp_path, capsys):
    """A textured OBJ whose 'vt' is NaN: before, taken silently (the texel index became -2**63)."""
    from PIL import Image

    Image.new("RGB", (2, 2), (200, 10, 10)).save(tmp_path / "t.png")
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 1 1\nmap_Kd t.png\n")
    scene = obj(tmp_path, "mtllib m.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt nan nan\nvt 1 0\nvt 0 1\n"
                          "f 1/1 2/2 3/3\n")
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "m.obj", "not finite")


def test_running_out_of_memory_in_a_query_is_an_input_error(monkeypatch):
    """numpy's MemoryError for too many rays (3e9 rays, say) becomes the API's input error."""
    import trimesh
    from engine import RayMeshIntersector, RayTracer
    from engine.api import RayInputError
    from engine.query import intersector as module
    from engine.query.errors import QueryInputError

    mesh = trimesh.creation.box()

    def no_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 67.1 GiB")

    intersector = RayMeshIntersector(mesh)
    monkeypatch.setattr(module, "_points", no_memory)
    with pytest.raises(QueryInputError, match="contains_points: not enough free memory"):
        intersector.contains_points([[0, 0, 0]])
    tracer = RayTracer(mesh)
    monkeypatch.setattr(tracer, "_batch", no_memory)
    with pytest.raises(RayInputError, match="intersect: not enough free memory"):
        tracer.intersects_first([[0, 0, 5]], [[0, 0, -1]])


# Outputs checked before the work (session 31's audit) -----------------------------------------
def test_a_character_device_output_is_written_into(tmp_path, capsys):
    node = tmp_path / "null"
    try:
        os.mknod(node, 0o020666, os.makedev(1, 3))
    except (PermissionError, OSError):
        pytest.skip("cannot make a device node here (needs root)")
    code, _ = run(["render", *TINY, "-o", node, "--stats", node], capsys)
    assert code == 0 and node.is_char_device()  # before: replaced by a PNG file


def test_animation_and_audit_outputs_in_the_way_stop_before_the_work(tmp_path, capsys):
    (tmp_path / "stats").mkdir()
    scene = obj(tmp_path, AFF_HEAD + "a 0 1 2\nk m { transl 2 0 0 0 0 0 0 0 1 1 0 0 0 0 0 }\nx m { s 0 0 0 1 }\n",
                "moving.aff")
    one_error(["animate", "--scene", scene, *TINY, "-o", tmp_path / "a", "--stats", tmp_path / "stats"], capsys,
              "--stats", "folder")
    (tmp_path / "b" / "path.png").mkdir(parents=True)
    one_error(["animate", "--scene", scene, *TINY, "-o", tmp_path / "b"], capsys, "path.png", "folder")
    (tmp_path / "rep" / "audit.json").mkdir(parents=True)
    one_error(["audit", *TINY, "--report", tmp_path / "rep"], capsys, "--report", "audit.json", "folder")
    assert not (tmp_path / "a").exists() or not any((tmp_path / "a").glob("frame_*"))


def test_a_folder_in_place_of_results_jsonl_stops_the_bench_before_its_cells(tmp_path, capsys):
    (tmp_path / "results.jsonl").mkdir()
    one_error(["bench", SMOKE, "--out", tmp_path, "--resume"], capsys, "results.jsonl", "folder")


def test_a_bad_face_index_is_named_itself():
    """Before: the message named the largest index (vertex 1 for a face '0 1 -1')."""
    from engine.core.errors import SceneError
    from engine.core.scene import make_triangles

    with pytest.raises(SceneError, match=r"face 1 refers to vertex -1, but the vertices are 0\.\.2"):
        make_triangles(np.eye(3), [[0, 1, 2], [0, 1, -1]], 0)


def test_a_folder_given_as_the_config_is_named_a_folder(tmp_path, capsys):
    one_error(["render", tmp_path, *TINY], capsys, "is a folder, not a file")


def test_a_bad_scene_parameter_in_a_matrix_names_the_file_and_scene_first(tmp_path, capsys):
    """Before: the loader's message alone, after the 'N cells to run' line."""
    text = MATRIX.format(name="t", res="16").replace('scene = ["whitted"]', 'scene = [{name = "whitted", checks = 0}]')
    code, lines = run(["bench", obj(tmp_path, text, "m.toml"), "--out", tmp_path / "o"], capsys)
    assert code == 2 and len(lines) == 1, lines
    assert "m.toml" in lines[0] and "scene 'whitted' (checks = 0)" in lines[0], lines[0]


def test_an_open3d_audit_prints_nothing_on_stderr(tmp_path):
    """Open3D loads a TBB older than numba's TBB layer wants, and numba said so in two lines on
    stderr of an otherwise clean audit."""
    pytest.importorskip("open3d")
    done = subprocess.run([sys.executable, "-m", "engine.cli", "audit", *TINY, "--oracle", "open3d"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0 and done.stderr == "", done.stderr


def test_a_camera_looking_at_its_own_eye_names_the_file(tmp_path, capsys):
    scene = obj(tmp_path, AFF_HEAD.replace("from 0 0 5", "from 0 0 0") + "s 0 0 -3 1\n", "s.aff")
    one_error(["render", "--scene", scene, *TINY, "-o", tmp_path / "x.png"], capsys, "s.aff", "coincide")


def test_nan_vertices_name_the_first_bad_one():
    """Before: the check ran after the move to the mesh's frame, where every vertex reads NaN, so
    it named vertex 0 (finite) and counted 4 of 3."""
    import trimesh
    from engine import RayMeshIntersector
    from engine.query.errors import QueryInputError

    vertices = np.array([[0, 0, 0], [np.nan, 0, 0], [0, np.nan, 0], [0, 0, np.nan]])
    mesh = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    with pytest.raises(QueryInputError, match=r"mesh.vertices\[1\] = \[nan, 0.0, 0.0\] is not finite \(3 such"):
        RayMeshIntersector(mesh).intersects_first([[0, 0, 5]], [[0, 0, -1]])


# Session 37's sweep: each of these was a traceback, a silent wrong answer or a lost output -----
@pytest.mark.parametrize("keyword, fragment", [({"packet": 8.0}, "RayTracer packet"), ({"packet": np.int64(16)}, None),
                                               ({"leaf_size": "4"}, "leaf_size"), ({"leaf_size": 1.5}, "leaf_size"),
                                               ({"bins": None}, "bins"), ({"leaf_size": True}, "leaf_size")])
def test_ray_tracer_settings_must_be_integers(keyword, fragment):
    """Before: packet=8.0 was kept and the first query died in numba's typing (a TypingError of
    many lines); leaf_size="4" was Python's own TypeError from a comparison, naming nothing."""
    import trimesh
    from engine import RayTracer

    box = trimesh.creation.box()
    if fragment is None:
        assert RayTracer(box, **keyword).intersects_first([[0, 0, 5]], [[0, 0, -1]]).tolist() == [4]
        return
    with pytest.raises((ValueError, TypeError), match=fragment) as info:
        RayTracer(box, **keyword)
    assert isinstance(info.value, PacketrtError) and "\n" not in str(info.value)


def test_intersector_build_settings_are_checked_when_made():
    """Before: RayMeshIntersector(mesh, leaf_size="x") was accepted and its first query raised
    Python's comparison TypeError."""
    import trimesh
    from engine import RayMeshIntersector
    from engine.query.errors import QueryInputError, QueryTypeError

    with pytest.raises(QueryTypeError, match="leaf_size"):
        RayMeshIntersector(trimesh.creation.box(), leaf_size="x")
    with pytest.raises(QueryInputError, match="bins must be in 2..256"):
        RayMeshIntersector(trimesh.creation.box(), bins=1)


@pytest.mark.parametrize("dtype", [complex, str, object])
def test_vertices_must_be_real_numbers(dtype):
    """Before: complex vertices lost their imaginary part with only numpy's warning, and string
    or object vertices were parsed."""
    import trimesh
    from engine import RayTracer
    from engine.core.errors import SceneTypeError

    box = trimesh.creation.box()
    with pytest.raises(SceneTypeError, match="vertices must be real numbers"):
        RayTracer((np.asarray(box.vertices).astype(dtype), box.faces))


@pytest.mark.parametrize("scale, refused", [(1e-6, False), (1e-10, False), (1e-11, True), (1e-20, True)])
def test_a_scene_too_small_for_float32_is_refused_not_missed(scale, refused):
    """Before: a box 1e-20 across answered every ray as a miss (Embree's answers too), and at
    1e-15 the hits named other faces than Embree's; RayMeshIntersector rescales and answers."""
    import trimesh
    from engine import RayMeshIntersector, RayTracer

    box = trimesh.creation.box()
    mesh = trimesh.Trimesh(box.vertices * scale, box.faces, process=False)
    origin, direction = [[0.1 * scale, 0.2 * scale, 5 * scale]], [[0, 0, -1.0]]
    assert RayMeshIntersector(mesh).intersects_first(origin, direction).tolist() == [4]
    if refused:
        with pytest.raises(SceneError, match="across; packetrt's float32 kernels need"):
            RayTracer(mesh)
    else:
        assert RayTracer(mesh).intersects_first(origin, direction).tolist() == [4]


def test_a_far_bound_is_infinite_without_a_warning():
    """Before: tmax=1e300 answered right but printed numpy's overflow warning from the cast."""
    import warnings

    import trimesh
    from engine import RayTracer

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hits = RayTracer(trimesh.creation.box()).intersect([[0, 0, 5]], [[0, 0, -1]], tmax=1e300)
    assert hits.prim.tolist() == [4]


def test_two_outputs_on_one_path_stop_before_the_work(tmp_path, capsys, monkeypatch):
    """Before: -o and --stats on one path exited 0 with the image replaced by the JSON; audit's
    --json on its --report folder failed only after the audit, leaving the folder made."""
    import engine.cli as cli

    monkeypatch.setattr(cli, "_load_scene", lambda *a: pytest.fail("the scene was loaded before the check"))
    same = tmp_path / "x.png"
    one_error(["render", *TINY, "-o", same, "--stats", tmp_path / "." / "x.png"], capsys, "-o and --stats both write")
    one_error(["render", *TINY, "-o", ""], capsys, "-o needs a file name")
    report = tmp_path / "report"
    one_error(["audit", *TINY, "--json", report, "--report", report], capsys, "--json and --report both write")
    one_error(["audit", *TINY, "--json", report / "audit.json", "--report", report], capsys, "audit.json")
    assert not same.exists() and not report.exists()


def test_a_resumed_bench_names_the_lines_it_measures_again(tmp_path, monkeypatch, capsys):
    """Before: unreadable lines of results.jsonl were dropped (and a torn tail cut off) without
    a word, the run exiting 0."""
    from engine.bench import runner

    def stop(todo, source=None):
        raise PacketrtError("stopped before any work")

    monkeypatch.setattr(runner, "preflight", stop)
    (tmp_path / "results.jsonl").write_text('{garbage\n[1, 2]\n{"id": "x", "seconds": "x"}\n{"id": "tor')
    code, lines = run(["bench", SMOKE, "--out", tmp_path, "--resume"], capsys)
    assert code == 2 and lines[-1] == "packetrt: error: stopped before any work"
    warning = [line for line in lines if "warning" in line]
    assert len(warning) == 1 and "3 unreadable line(s) skipped (line 1, 2, 3)" in warning[0], lines
    assert "a torn last line of 11 bytes cut off" in warning[0]  # {"id": "tor


@pytest.mark.parametrize("text, fragment", [("", "not an OFF file: it is empty"),
                                            ("PLY\n3 1 0\n", "expected the word OFF first, got 'PLY'"),
                                            ("OFF\n3 x 0\n", "expected three counts"),
                                            ("OFF\n99999999999 1 0\n0 0 0\n", "declares 99,999,999,999 vertices")])
def test_a_bad_off_header_says_what_was_expected(tmp_path, capsys, text, fragment):
    """Before: numpy's words ("not enough values to unpack", "cannot reshape array of size 3")."""
    one_error(["render", "--scene", obj(tmp_path, text, "m.off"), *TINY, "-o", tmp_path / "x.png"], capsys,
              "m.off", fragment)


@pytest.mark.parametrize("line, fragment", [("vn nan 0 1", ":4: normal 'vn nan 0 1'"),
                                            ("vt nan 0", ":4: texture coordinate 'vt nan 0'"),
                                            ("vn 0 1", ":4: normal 'vn 0 1' has fewer than 3")])
def test_every_obj_number_is_checked_used_or_not(tmp_path, capsys, line, fragment):
    """Before: a NaN normal, or a NaN texture coordinate no face used, rendered with exit 0."""
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\n" + line + "\nf 1 2 3\n"
    one_error(["render", "--scene", obj(tmp_path, text), *TINY, "-o", tmp_path / "x.png"], capsys, "m.obj", fragment)


@pytest.mark.parametrize("body, fragment", [("s 0 0 0 -1\n", ":4: 's' radius must be >= 0, got -1"),
                                            ("c 0 0 0 1 0 1 0 -0.5\n", ":4: 'c' radii must be >= 0")])
def test_negative_radii_in_an_aff_are_one_line(tmp_path, capsys, body, fragment):
    one_error(["render", "--scene", obj(tmp_path, AFF_HEAD + body, "s.aff"), *TINY, "-o", tmp_path / "x.png"],
              capsys, fragment)


def test_a_damaged_frame_image_is_rendered_again_on_resume(tmp_path, capsys):
    """Before: --resume over a truncated frame PNG failed at the end with Pillow's "image file is
    truncated", naming no file."""
    scene = obj(tmp_path, AFF_HEAD + "a 0 1 2\nk m { transl 2 0 0 0 0 0 0 0 1 1 0 0 0 0 0 }\nx m { s 0 0 0 1 }\n", "moving.aff")
    out = tmp_path / "anim"
    argv = ["animate", "--scene", scene, *TINY, "-o", out]
    assert run(argv, capsys)[0] == 0
    frame = sorted(out.glob("frame_*.png"))[1]
    frame.write_bytes(frame.read_bytes()[:100])
    code, _ = run(argv + ["--resume", "--stats", tmp_path / "s.json"], capsys)
    assert code == 0
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["frames_rendered"] == 1 and stats["frames_resumed"] == 1


@pytest.mark.parametrize("argv, fragment", [
    (["render", *TINY, "-o", "x.jpg"], "-o writes a PNG image; give a name ending in .png"),
    (["render", *TINY, "--traversal", "=single"], "no ray kind before '='"),
    (["audit", *TINY, "--tiles", "3"], "--tiles and --workers split the audit over a --scheduler"),
    (["bench", SMOKE, "--workers", "2"], "--workers sizes the local Dask cluster of --scheduler"),
    (["animate", *TINY, "--time", "0.5"], "--time (one moment) is for render"),
])
def test_options_that_would_be_ignored_or_misread_are_one_line(tmp_path, capsys, monkeypatch, argv, fragment):
    """Before: each was accepted with exit 0 -- a PNG written as x.jpg, '=single' taken for every
    kind, --tiles / --workers / --time silently ignored."""
    monkeypatch.chdir(tmp_path)
    one_error(argv, capsys, fragment)
    assert not (tmp_path / "x.jpg").exists()


@pytest.mark.parametrize("table, fragment", [('path = ""', "path is empty"),
                                             ('name = "whitted"\npath = "m.obj"', "name (a catalog scene) or path"),
                                             ('path = "folder"', "is a folder, not a file")])
def test_a_scene_table_that_names_no_one_scene_is_one_line(tmp_path, capsys, table, fragment):
    """Before: path = "" rendered the default scene, name and path both let the path win, and
    a folder was said not to exist."""
    (tmp_path / "folder").mkdir()
    config = obj(tmp_path, f"[scene]\n{table}\n", "c.toml")
    one_error(["render", config, *TINY, "-o", tmp_path / "x.png"], capsys, fragment)


def test_a_config_with_a_byte_order_mark_is_read(tmp_path, capsys):
    """Before: "not valid TOML: Invalid statement (at line 1, column 1)" for a BOM an editor wrote."""
    config = tmp_path / "c.toml"
    config.write_bytes("\ufeff[render]\nwidth = 16\nheight = 16\nmax_depth = 1\n".encode("utf-8"))
    code, _ = run(["render", config, "-o", tmp_path / "x.png"], capsys)
    assert code == 0 and (tmp_path / "x.png").is_file()


@pytest.mark.parametrize("traversal, fragment", [
    ('[{label = "a\\nb", primary = "single"}]', "printable characters without '|'"),
    ('[{label = "a|b", primary = "single"}]', "printable characters without '|'"),
    ('[{label = "a", primary = "single"}, {label = "a", primary = "ranged"}]', "label 'a' is already that of"),
])
def test_bench_labels_name_one_row_each(tmp_path, capsys, traversal, fragment):
    """Before: a label with a newline or '|' broke summary.md's table, and two variants labelled
    alike gave rows nobody could tell apart."""
    text = MATRIX.format(name="t", res="16").replace('traversal = ["single"]', f"traversal = {traversal}")
    one_error(["bench", obj(tmp_path, text, "m.toml"), "--out", tmp_path / "o"], capsys, "m.toml", fragment)


def test_an_ascii_ply_cut_short_says_so(tmp_path, capsys):
    """Before: trimesh read the file as one without faces: "the file holds no triangles"."""
    header = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    one_error(["render", "--scene", obj(tmp_path, header + "0 0 0\n1 0 0\n", "m.ply"), *TINY, "-o",
               tmp_path / "x.png"], capsys, "m.ply: the header declares element vertex 3, face 1 (4 lines), "
                                            "but the file holds 2 lines after it")
    code, _ = run(["render", "--scene", obj(tmp_path, header + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "m.ply"), *TINY,
                   "-o", tmp_path / "x.png"], capsys)
    assert code == 0


# Session 37's second sweep: the other matrix kinds, and Configs built by hand ------------------
DYNAMIC = 'kind = "dynamic"\nframes = 2\nresolution = 16\n[[scene]]\n{scene}\n[[variant]]\nlabel = "a"\n{variant}\n'


@pytest.mark.parametrize("scene, variant, fragment", [
    ('name = "bart-museum"\nparams = 5', "", "params: must be a table of the scene's parameters"),
    ('name = "bart-museum"\nrecursion = []', "", "recursion: unknown preset []"),
    ('name = "whitted"\nrecursion = "kitchen-paper"', "", "preset 'kitchen-paper' sets how many lights"),
    ('name = "nosuch"', "", "unknown scene 'nosuch'"),
    ('name = "bart-museum"\nparams = { lights = 99 }\nrecursion = "shadows"', "", "lights = 99"),
    ('name = "bart-museum"', 'compare_fresh = "yes"', "compare_fresh: must be true or false"),
    ('name = "bart-museum"', '[[variant]]\nlabel = "b"', "measures the same as scene[0] variant[0]"),
])
def test_a_dynamic_matrix_is_checked_whole_before_any_cell(tmp_path, capsys, scene, variant, fragment):
    """Before: tracebacks (params = 5, recursion = []), a scene the preset's light count does not
    fit, a bad scene or light count found only when its cell came up (after the cells before it
    ran), the same cell measured twice under one id."""
    if "lights = 99" in scene:
        needs_shared_scenes()  # the light count is the loader's to check: it opens the file
    matrix = obj(tmp_path, DYNAMIC.format(scene=scene, variant=variant), "d.toml")
    one_error(["bench", matrix, "--out", tmp_path / "o"], capsys, "d.toml", fragment)
    assert not (tmp_path / "o").exists()


def test_a_dynamic_resolution_of_one_side_is_square():
    """Before: resolution = [16] ended in "not enough values to unpack"."""
    from engine.bench.dynamic import load_dynamic

    data = {"kind": "dynamic", "resolution": [16], "scene": [{"name": "bart-museum"}],
            "variant": [{"label": "a"}]}
    config = load_dynamic(data, "d.toml")[1][0][3]
    assert (config.render.width, config.render.height) == (16, 16)


@pytest.mark.parametrize("text, fragment", [
    ('scene = 5\n[[variant]]\nlabel = "a"\ntraversal = "bvh"\n', "needs one or more [[scene]] tables"),
    ('[[scene]]\nname = "whitted"\nrecursion = "shadows"\nrays = 5\n[[variant]]\nlabel = "a"\ntraversal = "bvh"\n',
     "rays: must be a list of ray sets"),
    ('[[scene]]\nname = "whitted"\nrecursion = "shadows"\n[[variant]]\ntraversal = "bvh"\n', "needs label and traversal"),
    ('[[scene]]\npath = "x.obj"\n[[variant]]\nlabel = "a"\ntraversal = "bvh"\n', "unknown key(s) ['path']"),
    ('[[scene]]\nname = "whitted"\nrecursion = "shadows"\n[[variant]]\nlabel = "a"\ntraversal = "ranged2"\n',
     "'ranged2' has no CUDA version"),
    ('[[scene]]\nname = "whitted"\nrecursion = "nope"\n[[variant]]\nlabel = "a"\ntraversal = "bvh"\n',
     "unknown preset 'nope'"),
])
def test_a_gpu_matrix_is_checked_whole_before_the_gpu_is_asked_for(text, fragment):
    """Before: scene = 5 or rays = 5 were "'int' object is not iterable", a variant without a
    label a KeyError, a path scene a KeyError, and unknown names were found when frames began."""
    import tomllib

    from engine.bench.gpu import check_matrix

    with pytest.raises(ConfigError, match=re.escape(fragment)):
        check_matrix({"kind": "gpu", **tomllib.loads(text)}, "g.toml")


@pytest.mark.parametrize("text, argv, fragment", [
    ('kind = "Trimesh"\n', [], "kind must be one of gpu, dynamic, trimesh"),
    ('kind = "trimesh"\nname = "../x"\n[[mesh]]\nscene = "whitted"\n', [], "name: must be 1-100 letters"),
    ('kind = "trimesh"\nthreads = 100000\n[[mesh]]\nscene = "whitted"\n', [], "threads must be in 0..1024"),
    ('kind = "trimesh"\n[[mesh]]\nscene = "whitted"\n', ["--resume"], "--resume does not apply"),
    ('kind = "dynamic"\nname = "a/b"\n', [], "name: must be 1-100 letters"),
    ('kind = "dynamic"\n', ["--repeat", "3"], "a dynamic matrix sets its own repetitions"),
])
def test_every_matrix_kind_checks_its_name_threads_and_options(tmp_path, capsys, text, argv, fragment):
    """Before: a trimesh or dynamic name could climb out of out/, threads = 100000 was recorded
    as used, and --resume / --repeat were ignored by the runners that do not take them."""
    one_error(["bench", obj(tmp_path, text, "m.toml"), "--out", tmp_path / "o", *argv], capsys, fragment)


def test_a_trimesh_run_keeps_the_results_it_would_replace(tmp_path, capsys, monkeypatch):
    """Before: another run's results.jsonl in --out was overwritten."""
    from engine.bench import trimesh_queries

    monkeypatch.setattr(trimesh_queries, "run", lambda spec, out, progress=None: [])
    out = tmp_path / "o"
    out.mkdir()
    (out / "results.jsonl").write_text('{"id": "earlier"}\n')
    code, lines = run(["bench", obj(tmp_path, 'kind = "trimesh"\n[[mesh]]\nscene = "whitted"\n', "m.toml"),
                       "--out", out], capsys)
    assert code == 0 and any("earlier results moved to" in line for line in lines), lines
    assert (out / "results.jsonl.prev").read_text() == '{"id": "earlier"}\n'


@pytest.mark.parametrize("change, fragment", [
    (lambda c: {"render": None}, "Config.render must be of type RenderConfig"),
    (lambda c: {"traversal": "single"}, "Config.traversal must be of type PerKind"),
    (lambda c: {"options": {"a": 1}}, "Config.options must be of type tuple"),
    (lambda c: {"render": replace(c.render, packet=8.0)}, "render.packet must be one of"),
    (lambda c: {"render": replace(c.render, width=16.0)}, "render.width must be"),
])
def test_a_config_built_by_hand_is_checked_for_types(change, fragment):
    """Before: RenderConfig(packet=8.0) reached numba (a TypingError of many lines) and
    render=None an AttributeError, from RayTracer.render and the renderers alike."""
    import trimesh
    from engine import RayTracer
    from engine.render.config import Config

    base = Config()
    with pytest.raises((ValueError, TypeError), match=re.escape(fragment)) as info:
        RayTracer(trimesh.creation.box()).render(replace(base, **change(base)))
    assert isinstance(info.value, PacketrtError)


def test_numpy_integers_in_a_config_become_plain_ints():
    """Before: width=np.int32(16) rendered, and then its --stats dict could not be written as JSON."""
    import trimesh
    from engine import RayTracer
    from engine.render.config import Config

    base = Config()
    _, stats = RayTracer(trimesh.creation.box()).render(
        replace(base, render=replace(base.render, width=np.int32(16), height=np.int64(16), max_depth=1)))
    json.dumps(stats)


@pytest.mark.parametrize("call, fragment", [
    (lambda i: i.intersects_id([[0, 0, 5]], [[0, 0, -1]], multiple_hits="no"), "multiple_hits must be True or False"),
    (lambda i: i.intersects_id([[0, 0, 5]], [[0, 0, -1]], multiple_hits=np.array([True])), "multiple_hits must be"),
    (lambda i: i.intersects_id([[0, 0, 5]], [[0, 0, -1]], return_locations="no"), "return_locations must be"),
    (lambda i: i.contains_points(np.zeros((3, 0))), "points must have shape (n, 3), got (3, 0)"),
])
def test_intersector_flags_and_points_are_what_they_say(call, fragment):
    """Before: multiple_hits="no" returned every hit (a string is true), an array flag was numpy's
    "truth value is ambiguous", and contains_points of a (3, 0) array answered 0 points for 3."""
    import trimesh
    from engine import RayMeshIntersector
    from engine.query.errors import QueryInputError

    with pytest.raises(QueryInputError, match=re.escape(fragment)):
        call(RayMeshIntersector(trimesh.creation.box()))
    answers = RayMeshIntersector(trimesh.creation.box()).intersects_id([[0, 0, 5]], [[0, 0, -1]], multiple_hits=0)
    assert [a.tolist() for a in answers] == [[4], [0]]


def test_ray_tracer_render_arguments_are_what_they_say():
    import trimesh
    from engine import RayTracer
    from engine.api import ApiArgumentError

    tracer = RayTracer(trimesh.creation.box())
    with pytest.raises(ApiArgumentError, match="config path is empty"):
        tracer.render("")
    with pytest.raises(ApiArgumentError, match="counters must be True or False"):
        tracer.render({"render": {"width": 8, "height": 8}}, counters="no")
    with pytest.raises(ApiArgumentError, match="multiple_hits must be True or False"):
        tracer.intersects_location([[0, 0, 5]], [[0, 0, -1]], multiple_hits="no")



@pytest.mark.parametrize("argv, fragment", [(["--exit-after", "nan"], "--exit-after must be a number of seconds"),
                                            (["--exit-after", "inf"], "--exit-after must be a number of seconds"),
                                            (["--status-file", "."], "--status-file '.' is a folder")])
def test_view_test_options_are_checked_before_the_window(tmp_path, capsys, monkeypatch, argv, fragment):
    """Before: --exit-after nan or inf never closed the window, and a --status-file that could not
    be written was reported after every frame while the viewer ran on."""
    monkeypatch.chdir(tmp_path)
    one_error(["view", *TINY, *argv], capsys, fragment)


@pytest.mark.parametrize("entry, fragment", [("file", "(a file, not a folder)"), ("nowhere", "(no such folder)")])
def test_a_scene_path_entry_that_is_no_folder_is_named(tmp_path, capsys, monkeypatch, entry, fragment):
    """Before: only "looked in X", whether X was a folder without the files, a file or nothing."""
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("PACKETRT_SCENE_PATH", str(tmp_path / entry))
    one_error(["render", "--scene", "bunny", *TINY, "-o", tmp_path / "x.png"], capsys, fragment)


def test_a_scene_too_large_names_its_geometry_not_its_light(tmp_path, capsys):
    """Before: a mesh 1e30 across failed on the position of the light placed for it."""
    mesh = obj(tmp_path, "v -5e29 0 0\nv 5e29 0 0\nv 0 5e29 0\nf 1 2 3\n")
    one_error(["render", "--scene", mesh, *TINY, "-o", tmp_path / "x.png"], capsys, "the geometry reaches 5e+29")


@pytest.mark.parametrize("text, fragment", [
    ('[options.pinhole]\na = 1\n', "'pinhole' is a frustum builder, and frustum builders take no options"),
    ('[traversal]\nprimary = "auto"\n[options.auto]\nmin_live = 2\n', "options.auto.min_live is a fraction"),
])
def test_plugin_options_name_what_takes_them(tmp_path, capsys, text, fragment):
    """Before: [options.pinhole] said "unknown traversal 'pinhole'", and min_live = 2 (documented
    as a fraction of lanes) was taken."""
    one_error(["render", obj(tmp_path, text, "c.toml"), *TINY, "-o", tmp_path / "x.png"], capsys, fragment)


def test_scenes_lists_a_found_file_that_cannot_be_loaded_as_such(tmp_path, capsys, monkeypatch):
    """Before: `packetrt scenes` said "found" for garbage at a scene's file name; the load error
    was in --json only."""
    (tmp_path / "stanford-bunny").mkdir()
    (tmp_path / "stanford-bunny" / "bun_zipper.ply").write_bytes(b"not a ply at all")
    monkeypatch.setenv("PACKETRT_SCENE_PATH", str(tmp_path))
    assert main(["scenes"]) == 0
    bunny = [line for line in capsys.readouterr().out.splitlines() if line.startswith("bunny ")]
    assert len(bunny) == 1 and "found, but cannot be loaded" in bunny[0] and "bun_zipper.ply" in bunny[0]


@pytest.mark.parametrize("value", ["-1", "1.0", "10001", "x"])
def test_the_kitchens_light_count_has_one_message(tmp_path, capsys, value):
    """Before: -1 and 10001 read "a number in [0, 10000]", 1.0 passed that check and was refused by
    the loader as "all" or an integer >= 0 -- three answers to one question."""
    pytest.importorskip("trimesh")
    one_error(["render", "--scene", "bart-kitchen", "--param", f"lights={value}", *TINY, "-o", tmp_path / "x.png"],
              capsys, "parameter lights must be 'all' or an integer in 0..10000")


@pytest.mark.parametrize("offset", [0.0, 500.0, 1e4, 1e6])
def test_rays_at_a_mesh_far_from_the_origin_hit_it(offset):
    """Before: a mesh more than 1,000 sizes from the origin was re-centred when built, and every
    query traced the caller's rays against the moved triangles: every ray missed, with every
    traversal (Embree's too, built over the same moved triangles)."""
    import trimesh
    from engine import RayMeshIntersector, RayTracer

    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.apply_translation([offset, 0.0, 0.0])
    rng = np.random.default_rng(3)
    aim = rng.normal(size=(200, 3)) * 0.3
    origins = np.array([offset, 0.0, 0.0]) + np.array([0.0, 0.0, 4.0]) + rng.normal(size=(200, 3)) * 0.2
    directions = (np.array([offset, 0.0, 0.0]) + aim) - origins
    expected = RayMeshIntersector(mesh).intersects_first(origins, directions)
    assert (expected >= 0).sum() > 150
    for traversal in ("partition", "single", "embree"):
        tracer = RayTracer(mesh, traversal=traversal)
        assert (tracer.intersects_first(origins, directions) == expected).mean() > 0.99, traversal
        assert tracer.intersects_any(origins, directions).tolist() == (expected >= 0).tolist()
    tracer = RayTracer(mesh)
    locations, index_ray, _ = tracer.intersects_location(origins, directions)
    theirs, their_rays, _ = RayMeshIntersector(mesh).intersects_location(origins, directions, multiple_hits=False)
    assert index_ray.tolist() == their_rays.tolist()
    # RayTracer's corners are float32 where its scene holds them: at 500 (not re-centred) a few
    # float32 steps of 500; re-centred, those of the mesh's own size.
    held_at = abs(offset - tracer.scene.origin[0]) + 2.0
    assert np.abs(locations - theirs).max() < 1e-5 + 16 * float(np.spacing(np.float32(held_at)))


@pytest.mark.parametrize("name, value, fragment", [("NUMBA_NUM_THREADS", "0", "NUMBA_NUM_THREADS='0'"),
                                                   ("NUMBA_NUM_THREADS", "100000", "in 1..1024"),
                                                   ("NUMBA_THREADING_LAYER", "bogus", "must be one of default")])
def test_numbas_environment_is_one_line_before_numba_loads(tmp_path, name, value, fragment):
    """Before: NUMBA_NUM_THREADS=0 or a bogus threading layer was numba's traceback at `import
    numba`, before the command could speak, and NUMBA_NUM_THREADS=100000 crashed (SIGSEGV)."""
    env = {**os.environ, name: value}
    done = subprocess.run([sys.executable, "-m", "engine.launch", "render", *TINY, "-o", str(tmp_path / "x.png")],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    lines = done.stderr.splitlines()
    assert done.returncode == 2 and len(lines) == 1 and fragment in lines[0], done.stderr
    assert lines[0].startswith("packetrt: error: environment variable ")
    assert not (tmp_path / "x.png").exists()


# -- options that were taken and then ignored (session 38) -------------------------------

def test_render_audit_refuses_repeat_and_its_stats_say_they_were_not_counted(tmp_path, capsys):
    """``render --audit --repeat 3`` rendered one frame and dropped --repeat; its --stats said its
    zero counters came from "a separate counting pass"."""
    code, err = run(["render", *TINY, "--audit", "--repeat", "3", "-o", tmp_path / "a.png"], capsys)
    assert code == 2 and len(err) == 1 and "--repeat 3" in err[0] and not (tmp_path / "a.png").exists()
    stats = tmp_path / "a.json"
    assert main(["render", *TINY, "--audit", "-o", str(tmp_path / "a.png"), "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert data["audited"] is True and data["counters_from"].startswith("none: an audited frame")
    assert main(["render", *TINY, "-o", str(tmp_path / "b.png"), "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert data["audited"] is False and data["counters_from"].startswith("a separate counting pass")


def test_audit_over_a_scheduler_refuses_two_oracles_before_any_work(tmp_path, capsys):
    code, err = run(["audit", *TINY, "--scheduler", "tcp://127.0.0.1:9", "--oracle", "both"], capsys)
    assert code == 2 and len(err) == 1 and "--oracle both" in err[0]


@pytest.mark.parametrize("matrix, option", [
    ("gpu.toml", ["--scheduler"]), ("gpu.toml", ["--resume"]), ("bart-dynamic.toml", ["--workers", "2"]),
    ("trimesh.toml", ["--steady", "1.1"]), ("bart-dynamic.toml", ["--retries", "1"]),
])
def test_matrices_not_of_cells_refuse_the_cell_runners_options(tmp_path, capsys, matrix, option):
    """They ran and ignored --scheduler, --workers, --steady and --retries (gpu also --resume)."""
    code, err = run(["bench", ROOT / "benchmarks" / matrix, "--out", tmp_path / "o", *option], capsys)
    assert code == 2 and len(err) == 1 and option[0] in err[0] and "a matrix of cells" not in err[0]
    assert not (tmp_path / "o").exists()


def test_a_dynamic_matrix_refuses_a_lights_parameter_its_preset_overrides(capsys):
    """kitchen-paper shades with one light; params = {lights = 3} was replaced by 1 unsaid."""
    from engine.bench.dynamic import load_dynamic

    data = {"kind": "dynamic", "name": "t", "frames": 2, "resolution": 16,
            "scene": [{"name": "bart-kitchen", "recursion": "kitchen-paper", "params": {"lights": 3}}],
            "variant": [{"accel": "refit"}]}
    with pytest.raises(ConfigError, match=r"lights = 3 clashes with preset 'kitchen-paper'"):
        load_dynamic(data, "m.toml")
    data["scene"][0]["params"] = {"lights": 1}           # the preset's own count: fine
    data["variant"][0]["accel"] = "sometimes"           # ... and a variant without a label is named by its settings
    with pytest.raises(ConfigError, match=r"variant 'accel=sometimes'"):
        load_dynamic(data, "m.toml")


@pytest.mark.parametrize("command", [
    ["render", "--scene", "no-such-scene", "-o", "{new}/deeper/x.png"],
    ["render", "--scene", "no-such-scene", "-o", "{new}/x.png", "--stats", "{new}/s/x.json"],
    ["audit", "--scene", "no-such-scene", "--report", "{new}/report"],
    ["audit", "--scene", "no-such-scene", "--json", "{new}/a.json"],
    ["show", "--scene", "no-such-scene", "-o", "{new}/x.png"],
])
def test_a_failed_command_leaves_no_folder_it_made_for_its_outputs(tmp_path, capsys, command):
    new = tmp_path / "new"
    assert main([part.format(new=new) for part in command]) == 2
    assert "unknown scene" in capsys.readouterr().err
    assert not new.exists()
    # A folder that was there stays, with what it held.
    new.mkdir()
    (new / "mine.txt").write_text("mine")
    assert main([part.format(new=new) for part in command]) == 2
    assert sorted(p.name for p in new.iterdir()) == ["mine.txt"]


@pytest.mark.parametrize("name", ["", " "])
def test_an_empty_report_folder_name_is_refused(tmp_path, capsys, name, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["audit", "--size", "16x16", "--report", name]) == 2
    assert capsys.readouterr().err.strip() == "packetrt: error: --report needs a folder name, got an empty one"
    assert list(tmp_path.iterdir()) == []
