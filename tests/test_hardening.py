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
from pathlib import Path

import numpy as np
import pytest

from engine.cli import main
from engine.core.errors import ConfigError, ConfigTypeError, PacketrtError, SceneError

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

    def stop(todo):
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
