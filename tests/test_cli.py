"""The command line: outputs and their schemas, and one-line errors (exit 2) for user mistakes."""
import json
import subprocess
import sys

import pytest

from engine.cli import main

BAD_INPUTS = [
    (["render", "--traversal", "nope"], "unknown traversal 'nope'; registered traversals: "),
    (["render", "--frustum", "shadow=nope"], "unknown frustum 'nope'"),
    (["render", "--traversal", "sideways=single"], "unknown ray kind 'sideways'"),
    (["render", "--size", "0x10"], "render.width must be in 1..16384"),
    (["render", "--size", "20000x20000"], "render.width must be in 1..16384"),
    (["render", "--size", "16000x16000"], "more than this machine's"),
    (["render", "--size", "wide"], "--size must look like 512x512"),
    (["render", "--packet", "6"], "render.packet must be one of 2, 4, 8, 16, 32"),
    (["render", "--scene", "no-such-scene"], "unknown scene 'no-such-scene'; catalog scenes:"),
    (["render", "--scene", "/nonexistent/model.obj"], "does not exist"),
    (["render", "--scene", "whitted", "--param", "colour=3"], "has no parameter(s) ['colour']"),
    (["render", "/nonexistent/config.toml"], "config file '/nonexistent/config.toml' does not exist"),
]


@pytest.mark.parametrize("argv,message", BAD_INPUTS)
def test_user_mistakes_give_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("content,message", [
    ("[render]\nwidht = 3\n", "unknown key 'widht'; allowed: width, height"),
    ("[render]\nwidth = 'big'\n", "width must be int"),
    ("[colour]\nx = 1\n", "unknown section(s) ['colour']"),
    ("[traversal]\nprimary = 'warp'\n", "unknown traversal 'warp'"),
    ("[render\n", "not valid TOML"),
])
def test_bad_config_files(tmp_path, content, message, capsys):
    path = tmp_path / "c.toml"
    path.write_text(content)
    assert main(["render", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err


@pytest.mark.parametrize("content,message", [
    ("v 0 0 0\nv 1 0 0\nf 1 2 x\n", "bad.obj:3: bad face index 'x'"),
    ("v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n", "bad.obj:2: vertex 'v 1 nan 0' is not finite"),
    ("v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n", "is not finite"),
    ("v 0 0\nf 1 2 3\n", "bad.obj:1: vertex 'v 0 0' has fewer than 3 coordinates"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "bad.obj:4: face index 9 out of range"),
])
def test_malformed_obj_names_file_and_line(tmp_path, content, message, capsys):
    path = tmp_path / "bad.obj"
    path.write_text(content)
    assert main(["render", "--scene", str(path), "-o", str(tmp_path / "x.png")]) == 2
    assert message in capsys.readouterr().err


def test_nan_vertices_in_a_ply_are_rejected(tmp_path, capsys):
    path = tmp_path / "nan.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n")
    assert main(["render", "--scene", str(path), "-o", str(tmp_path / "x.png")]) == 2
    assert "vertex 1 is not finite" in capsys.readouterr().err


def test_render_writes_png_and_stats(tmp_path, capsys):
    out, stats = tmp_path / "a.png", tmp_path / "a.json"
    assert main(["render", "--size", "64x48", "--traversal", "single", "--frustum", "none",
                 "-o", str(out), "--stats", str(stats)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(stats.read_text())
    assert {"scene", "triangles", "width", "height", "config", "seconds", "rays", "mrays_per_s",
            "counters"} <= set(data)
    assert set(data["seconds"]) >= {"bvh", "trace", "shade", "total"}
    assert set(data["seconds"]["trace"]) == {"primary", "shadow", "reflection", "refraction"}
    assert data["rays"]["primary"] == 64 * 48 and data["mrays_per_s"]["primary"] > 0
    assert data["counters"]["ray_aabb"]["primary"] > 0 and data["counters"]["ray_tri"]["shadow"] > 0
    assert data["frames"]["n"] == 1 and data["frames"]["seconds"] == [data["seconds"]["total"]]
    assert data["seconds"]["compile"] >= 0


def test_repeat_renders_more_frames_and_prints_fps_with_compile_apart(tmp_path, capsys):
    out, stats = tmp_path / "a.png", tmp_path / "a.json"
    assert main(["render", "--size", "32x32", "--repeat", "2", "-o", str(out), "--stats", str(stats)]) == 0
    line = capsys.readouterr().out
    assert "FPS (median of 3 frames; compile " in line and "s apart)" in line
    frames = json.loads(stats.read_text())["frames"]
    assert frames["n"] == 3 and len(frames["seconds"]) == 3 and all(s > 0 for s in frames["seconds"])
    assert frames["median"] == sorted(frames["seconds"])[1] and abs(frames["fps"] * frames["median"] - 1) < 1e-9


@pytest.mark.parametrize("bad", ["-1", "lots", "1001"])
def test_bad_repeat_is_one_line_and_exit_2(tmp_path, capsys, bad):
    with pytest.raises(SystemExit) as info:
        main(["render", "--repeat", bad, "-o", str(tmp_path / "a.png")])
    assert info.value.code == 2 and "--repeat" in capsys.readouterr().err


def test_audit_json_schema_and_exit_code(tmp_path, capsys):
    report = tmp_path / "audit.json"
    assert main(["audit", "--size", "48x48", "--traversal", "single", "--frustum", "none",
                 "--json", str(report), "--report", str(tmp_path / "rep")]) == 0
    data = json.loads(report.read_text())
    assert set(data["oracle"]) >= {"name", "version", "robust"}
    assert data["rays_checked"] == sum(k["checked"] for k in data["by_kind"].values())
    for row in data["by_kind"].values():
        assert set(row) == {"checked", "agree", "ties", "mismatches"}
    assert data["agreement"] == 1.0 and data["mismatches"] == []
    assert (tmp_path / "rep" / "mismatches.png").is_file()


def test_plugins_and_scenes_json(capsys):
    assert main(["plugins", "--json"]) == 0
    plugins = json.loads(capsys.readouterr().out)
    names = {p["name"] for p in plugins["traversals"]}
    assert {"single", "embree"} <= names and "none" in {p["name"] for p in plugins["frusta"]}
    # Whole sentences: the first docstring line alone cut the general frustum's in two.
    for row in plugins["traversals"] + plugins["frusta"]:
        assert row["doc"].endswith((".", ")")) and "\n" not in row["doc"], row
    assert main(["scenes", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)["scenes"]}
    assert rows["whitted"]["triangles"] == 3072 and rows["whitted"]["files_found"]


def test_console_script_prints_no_traceback():
    run = subprocess.run([sys.executable, "-m", "engine.cli", "render", "--packet", "3"],
                         capture_output=True, text=True)
    assert run.returncode == 2
    assert run.stderr.strip().startswith("packetrt: error: render.packet") and "Traceback" not in run.stderr


def test_outputs_replace_their_target_whole_and_leave_nothing_behind(tmp_path, monkeypatch):
    """A failed write keeps the old file and no temporary; a good one replaces it."""
    from engine.core import atomic

    target = tmp_path / "out" / "stats.json"
    atomic.write_text(target, "old\n")
    with pytest.raises(RuntimeError):
        with atomic.replacing(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "old\n" and sorted(p.name for p in target.parent.iterdir()) == ["stats.json"]
    assert main(["render", "--size", "16x16", "-o", str(tmp_path / "out" / "a.png"), "--stats", str(target)]) == 0
    assert json.loads(target.read_text())["width"] == 16
    assert sorted(p.name for p in target.parent.iterdir()) == ["a.png", "stats.json"]


def test_the_gpus_small_grid_warning_is_not_printed_by_commands(capsys):
    """numba-cuda warns at every launch of fewer than 128 blocks (a frame's scans and upper
    hierarchy levels are small by nature); a command keeps them off the terminal, other
    performance warnings still show."""
    import warnings

    from numba.core.errors import NumbaPerformanceWarning

    assert main(["plugins"]) == 0
    with warnings.catch_warnings(record=True) as seen:
        warnings.warn(NumbaPerformanceWarning("Grid size 3 will likely result in GPU under-utilization due to "
                                              "low occupancy."))
        warnings.warn(NumbaPerformanceWarning("some other performance note"))
    assert [str(w.message) for w in seen] == ["some other performance note"]


def test_version_names_the_package(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.startswith("packetrt ")
