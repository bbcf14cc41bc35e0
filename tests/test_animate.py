"""Animation paths: the scene placed per frame equals a fresh load, the BVH kept current by
rebuild / refit / auto, and ``packetrt animate`` (frames equal ``render --time``, audits,
statistics, resume, and one-line errors)."""
from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest
from PIL import Image

from engine.cli import main
from engine.core.bvh import BOX_PAD_SCALE, build_bvh
from engine.core.bvh_refit import refit_bvh, refit_levels, sah_cost
from engine.render.accel import BVHKeeper
from scenes.aff_animation import AffAnimation, load_aff

# A floor, a box that slides and turns (x mover), a blended triangle (tpa) and a moving camera,
# over an animation range of 0..2 s.
SCENE = """
    v from 0 3 8 at 0 0 0 up 0 1 0 angle 45
    b 0.1 0.1 0.2
    l 2 6 4
    a 0 2 5
    fm 0.1 0.1 0.1  0.6 0.6 0.6  0.3 0.3 0.3  20 0 1
    p 4  -5 0 -5  -5 0 5  5 0 5  5 0 -5
    fm 0.1 0 0  0.8 0.2 0.2  0.5 0.5 0.5  30 0 1
    x mover
    {
      m
       vertices 8
         -1 0 -1   1 0 -1   1 2 -1   -1 2 -1
         -1 0  1   1 0  1   1 2  1   -1 2  1
       triangles 12
         0 1 2  0 2 3  4 6 5  4 7 6  0 4 5  0 5 1
         3 2 6  3 6 7  0 3 7  0 7 4  1 5 6  1 6 2
    }
    k mover
    {
      transl 3
        0  -2 0 0  0 0 0
        1   0 0 1  0 0 0
        2   2 0 0  0 0 0
      rot 2
        0  0 1 0 0    0 0 0
        2  0 1 0 120  0 0 0
    }
    tpa 2
      0
      2 0.5 -2  0 0 1
      3 0.5 -2  0 0 1
      2 1.5 -2  0 0 1
      2
      2 2.5 -2  0 0 1
      3 2.5 -2  0 0 1
      2 3.5 -2  0 0 1
    k camera
    {
      transl 2
        0  0 3 8  0 0 0
        2  2 3 8  0 0 0
    }
"""


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "moving.aff"
    path.write_text(textwrap.dedent(SCENE))
    return path


def assert_same_scene(a, b):
    for name, x, y in zip(a.triangles._fields, a.triangles, b.triangles):
        assert np.array_equal(x, y), name
    assert a.camera == b.camera
    assert [light.position for light in a.lights] == [light.position for light in b.lights]


# ------------------------------------------------------------------------------- the scene path

def test_scene_at_equals_a_fresh_load_at_every_time(scene_file):
    path = AffAnimation(scene_file)
    assert (path.start, path.end, path.frames, path.animated) == (0.0, 2.0, 5, True)
    for time in (0.0, 1.3, 2.0, 0.4, 5.0, 0.0):          # any order, outside the keys too
        assert_same_scene(path.scene_at(time), load_aff(scene_file, time))
    assert not np.array_equal(path.scene_at(0.0).triangles.v0, path.scene_at(1.0).triangles.v0)


def test_each_frame_keeps_arrays_of_its_own(scene_file):
    """A path reuses its placement buffers and hands later frames' fresh arrays to the scene
    uncopied: no frame may share memory with another, or change when the next is placed."""
    path = AffAnimation(scene_file)
    frames = [path.scene_at(t) for t in (0.0, 0.7, 1.3, 2.0)]
    kept = [[np.array(a) for a in f.triangles] for f in frames]
    for t in (0.2, 1.9):
        path.scene_at(t)
    for i, f in enumerate(frames):
        for name, now, then in zip(f.triangles._fields, f.triangles, kept[i]):
            assert np.array_equal(now, then), (i, name)
        for g in frames[i + 1:]:
            for x, y in zip(f.triangles, g.triangles):
                assert x.size == 0 or not np.shares_memory(x, y)
    # the moving rows of the path's own buffers are not any frame's arrays either
    for buffer in (path.moving._placed, path.moving._placed_normals):
        assert not any(np.shares_memory(buffer, a) for f in frames for a in f.triangles)


def test_builder_keeps_owned_triangles_and_skips_checked_materials():
    from engine.core.errors import SceneError
    from engine.core.scene import Material, SceneBuilder, make_triangles

    tris = make_triangles(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64), np.array([[0, 1, 2]]),
                          np.zeros(1, np.int32))
    copied = SceneBuilder("a")
    copied.add_triangles(tris)
    assert not np.shares_memory(copied.build().triangles.v0, tris.v0)
    owned = SceneBuilder("b")
    owned.add_triangles(tris, owned=True)
    assert owned.build().triangles.v0 is tris.v0
    owned.add_triangles(tris, owned=True)         # two parts: concatenated, so copied
    assert not np.shares_memory(owned.build().triangles.v0, tris.v0)
    bad = SceneBuilder("c")
    bad.add_triangles(tris)
    bad.materials = [Material("bad", diffuse=(float("nan"), 0.0, 0.0))]
    with pytest.raises(SceneError, match="material 'bad' diffuse"):
        bad.build()
    assert bad.build(materials_checked=True).materials[0].name == "bad"   # the caller vouches


def test_frames_of_a_bart_path_equal_fresh_loads(shared_scenes):
    from scenes.catalog import ANIMATORS, _resolve, load_named

    for name, times in (("bart-museum", (-1.0, 2.5, 4.9)), ("bart-robots", (0.0, 31.7))):
        entry, params, files = _resolve(name, {})
        path = ANIMATORS["aff"](files, params)
        for time in times:
            assert_same_scene(path.scene_at(time), load_named(name, {}, time))


# ----------------------------------------------------------------------------------- the BVH

def reference_boxes(bvh, tris):
    """Each node's box from scratch in numpy: leaves bound their triangles, inner nodes their
    subtree's triangles, all widened by the builder's pad."""
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1)
    pad = BOX_PAD_SCALE * np.float32(np.abs(corners).max())
    lo, hi = np.empty_like(bvh.bmin), np.empty_like(bvh.bmax)
    for node in range(len(bvh.first) - 1, -1, -1):
        if bvh.count[node]:
            c = corners[bvh.prim[bvh.first[node]:bvh.first[node] + bvh.count[node]]].reshape(-1, 3)
            lo[node], hi[node] = c.min(0), c.max(0)
        else:
            left = bvh.first[node]
            lo[node] = np.minimum(lo[left], lo[left + 1])
            hi[node] = np.maximum(hi[left], hi[left + 1])
    return lo - pad, hi + pad


def test_refit_gives_every_node_the_box_of_its_moved_triangles(scene_file):
    path = AffAnimation(scene_file)
    first = path.scene_at(0.0).triangles
    bvh = build_bvh(first, leaf_size=1)
    for time in (0.7, 2.0):
        moved = path.scene_at(time).triangles
        refit = refit_bvh(bvh, moved)
        lo, hi = reference_boxes(bvh, moved)
        np.testing.assert_array_equal(refit.bmin, lo)
        np.testing.assert_array_equal(refit.bmax, hi)
        for name in ("first", "count", "prim"):
            np.testing.assert_array_equal(getattr(refit, name), getattr(bvh, name))
    # The same tree refitted to its own triangles is the tree the builder made.
    again = refit_bvh(bvh, first, refit_levels(bvh.first, bvh.count))
    np.testing.assert_array_equal(again.bmin, bvh.bmin)
    np.testing.assert_array_equal(again.bmax, bvh.bmax)
    with pytest.raises(ValueError, match="refit needs"):
        refit_bvh(bvh, first._replace(v0=first.v0[:-1]))


def test_keeper_policies(scene_file):
    path = AffAnimation(scene_file)
    frames = [path.scene_at(t).triangles for t in (0.0, 0.5, 1.0, 1.5, 2.0)]
    ran = {}
    for policy in ("rebuild", "refit"):
        keeper = BVHKeeper(policy, leaf_size=1)
        ran[policy] = [keeper.update(tris)[1]["policy"] for tris in frames]
    assert ran["rebuild"] == ["rebuild"] * 5
    assert ran["refit"] == ["rebuild"] + ["refit"] * 4
    # auto: the box slides away from where the tree was built; a tight threshold rebuilds,
    # and a rebuild resets the ratio to 1.
    keeper = BVHKeeper("auto", leaf_size=1, degrade=1.0001)
    records = [keeper.update(tris)[1] for tris in frames]
    assert records[0]["policy"] == "rebuild"
    assert any(r["policy"] == "rebuild" for r in records[1:])
    assert all(r["sah_ratio"] == 1.0 for r in records if r["policy"] == "rebuild")
    loose = BVHKeeper("auto", leaf_size=1, degrade=100.0)
    assert [loose.update(tris)[1]["policy"] for tris in frames] == ["rebuild"] + ["refit"] * 4
    # auto's budget: while the last build took at most that share of the last frame, rebuild.
    keeper = BVHKeeper("auto", leaf_size=1, degrade=100.0, budget=0.05)
    first = keeper.update(frames[0])[1]
    assert first["reason"] == "first"
    cheap = keeper.update(frames[1], last_frame_seconds=keeper.build_seconds / 0.05 * 2)[1]
    dear = keeper.update(frames[2], last_frame_seconds=keeper.build_seconds / 0.05 / 2)[1]
    assert (cheap["policy"], cheap["reason"], dear["policy"], dear["reason"]) == ("rebuild", "cheap", "refit", None)
    refitted = refit_bvh(build_bvh(frames[0], leaf_size=1), frames[-1])
    assert sah_cost(refitted) > sah_cost(build_bvh(frames[-1], leaf_size=1))


# ---------------------------------------------------------------------------- packetrt animate

def animate(tmp_path, scene_file, *extra, folder="frames"):
    out = tmp_path / folder
    code = main(["animate", "--scene", str(scene_file), "--size", "24x24", "--packet", "4", "-o", str(out),
                 "--stats", str(tmp_path / f"{folder}.json"), *extra])
    return code, out


def test_rebuild_frames_equal_render_at_their_time_and_refit_frames_agree(tmp_path, scene_file):
    code, out = animate(tmp_path, scene_file, "--frames", "3", "--accel", "rebuild")
    assert code == 0
    stats = json.loads((tmp_path / "frames.json").read_text())
    frames = stats["path"]["frames"]
    assert [f["time"] for f in frames] == [0.0, 1.0, 2.0]
    for f in frames:
        assert set(f["seconds"]) == {"scene", "accel", "trace", "shade", "total"}
        assert f["accel"]["policy"] == "rebuild" and f["accel"]["sah_cost"] > 0
        png = tmp_path / f"still{f['index']}.png"
        assert main(["render", "--scene", str(scene_file), "--size", "24x24", "--packet", "4",
                     "--time", str(f["time"]), "-o", str(png)]) == 0
        assert png.read_bytes() == (out / f"frame_{f['index']:05d}.png").read_bytes()
    summary = stats["path"]
    assert summary["total_seconds"] == pytest.approx(sum(f["seconds"]["total"] for f in frames))
    assert summary["mean_fps"] == pytest.approx(3 / summary["total_seconds"])
    assert summary["slowest_seconds"] == max(f["seconds"]["total"] for f in frames)
    for name in ("preview.webp", "path.png", "frames.json"):
        assert (out / name).is_file() or name == "preview.webp" and (out / "preview.gif").is_file()
    # A refitted tree finds the same hits (this scene has no ties), so the same images.
    code, refit_out = animate(tmp_path, scene_file, "--frames", "3", "--accel", "refit", folder="refit")
    assert code == 0
    policies = [f["accel"]["policy"] for f in json.loads((tmp_path / "refit.json").read_text())["path"]["frames"]]
    assert policies == ["rebuild", "refit", "refit"]
    for i in range(3):
        assert (refit_out / f"frame_{i:05d}.png").read_bytes() == (out / f"frame_{i:05d}.png").read_bytes()


@pytest.mark.parametrize("policy", ["refit", "auto"])
def test_every_frame_audits_clean_against_embree(tmp_path, scene_file, policy, capsys):
    code, _ = animate(tmp_path, scene_file, "--frames", "4", "--accel", policy, "--audit")
    assert code == 0
    stats = json.loads((tmp_path / "frames.json").read_text())
    assert stats["audit"]["mismatches"] == 0 and stats["audit"]["checked"] > 4 * 24 * 24
    assert all(f["audit"]["mismatches"] == 0 for f in stats["path"]["frames"])
    # Each refitted frame also rendered over a fresh tree: any pixel that differs has a tie.
    refitted = [f for f in stats["path"]["frames"] if f["accel"]["policy"] == "refit"]
    assert refitted or policy == "auto"          # auto rebuilds this small scene's cheap tree
    assert all(f["audit"]["against_fresh_tree"]["unexplained"] == [] for f in refitted)
    assert stats["audit"]["unexplained"] == 0
    out = capsys.readouterr().out
    assert "0 mismatches" in out and "0 differing pixels not explained by a tie" in out


def test_an_interrupted_animation_keeps_whole_frames_and_resumes(tmp_path, scene_file, monkeypatch):
    from engine.render.animation import AnimationRenderer

    code, full = animate(tmp_path, scene_file, "--frames", "4", folder="full")
    real_frame = AnimationRenderer.frame

    def interrupted(self, index, time):
        if index == 2:
            raise KeyboardInterrupt
        return real_frame(self, index, time)

    monkeypatch.setattr(AnimationRenderer, "frame", interrupted)
    code, out = animate(tmp_path, scene_file, "--frames", "4")
    assert code == 130
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_00000.png", "frame_00001.png"]
    assert not list(out.glob(".*tmp*"))
    assert set(json.loads((out / "frames.json").read_text())["frames"]) == {"0", "1"}
    monkeypatch.setattr(AnimationRenderer, "frame", real_frame)
    code, out = animate(tmp_path, scene_file, "--frames", "4", "--resume")
    assert code == 0
    stats = json.loads((tmp_path / "frames.json").read_text())
    assert (stats["frames_rendered"], stats["frames_resumed"]) == (2, 2)
    assert len(stats["path"]["frames"]) == 4
    for i in range(4):
        assert (out / f"frame_{i:05d}.png").read_bytes() == (full / f"frame_{i:05d}.png").read_bytes()


@pytest.mark.parametrize("args, message", [
    (["--frames", "0"], "--frames must be in 1..100,000, got 0"),
    (["--frames", "1000000000"], "--frames must be in 1..100,000"),
    (["--start", "-1"], "--start -1 is outside the animation path"),
    (["--end", "7"], "--end 7 is outside the animation path"),
    (["--start", "1.5", "--end", "0.5"], "is before --start"),
    (["--fps", "0"], "--fps must be a positive number"),
    (["--frames", "3", "--fps", "2"], "not both"),
])
def test_bad_paths_are_one_line_errors(tmp_path, scene_file, capsys, args, message):
    code, out = animate(tmp_path, scene_file, *args)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not list(out.glob("frame_*.png")) if out.exists() else True


def test_static_scenes_unwritable_folders_and_reused_folders_are_one_line_errors(tmp_path, scene_file, capsys):
    assert main(["animate", "--scene", "whitted", "-o", str(tmp_path / "w")]) == 2
    assert "has no animation path to render" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["animate", "--scene", str(scene_file), "-o", str(blocker)]) == 2
    assert "is a file; give a folder" in capsys.readouterr().err
    code, out = animate(tmp_path, scene_file, "--frames", "1")
    assert code == 0
    capsys.readouterr()
    code, out = animate(tmp_path, scene_file, "--frames", "2")
    err = capsys.readouterr().err
    assert code == 2 and "already holds an animation" in err and err.count("\n") == 1
    code, out = animate(tmp_path, scene_file, "--frames", "2", "--resume")
    err = capsys.readouterr().err
    assert code == 2 and "holds frames of a different animation" in err


def test_fps_spaces_frames_in_scene_time(tmp_path, scene_file):
    code, _ = animate(tmp_path, scene_file, "--fps", "2", "--start", "0.5")
    assert code == 0
    times = [f["time"] for f in json.loads((tmp_path / "frames.json").read_text())["path"]["frames"]]
    assert times == [0.5, 1.0, 1.5, 2.0]
    image = Image.open(tmp_path / "frames" / "frame_00000.png")
    assert image.size == (24, 24)


def test_traversals_without_a_scene_tree_build_none_per_frame(tmp_path, scene_file):
    """Embree (its own scene, rebuilt per frame) and the ray-space hierarchy read no BVH of
    ours: their frames record policy "none" and still audit clean."""
    code, _ = animate(tmp_path, scene_file, "--frames", "2", "--traversal", "embree", "--frustum", "none", "--audit")
    assert code == 0
    frames = json.loads((tmp_path / "frames.json").read_text())["path"]["frames"]
    assert [f["accel"]["policy"] for f in frames] == ["none", "none"]
    assert all(f["audit"]["mismatches"] == 0 for f in frames)


def test_dynamic_matrix_runs_every_policy_and_tables_the_path(tmp_path, scene_file):
    matrix = tmp_path / "dyn.toml"
    matrix.write_text(textwrap.dedent(f"""
        kind = "dynamic"
        name = "dyn"
        frames = 3
        resolution = 16
        packet = 4
        [[scene]]
        path = "{scene_file}"
        label = "moving"
        recursion = "shadows"
        [[variant]]
        label = "rebuild"
        accel = "rebuild"
        [[variant]]
        label = "auto"
        accel = "auto"
        budget = 0.0
        [[variant]]
        label = "rs"
        traversal = "rayspace"
        frustum = "none"
    """))
    out = tmp_path / "out"
    assert main(["bench", str(matrix), "--out", str(out)]) == 0
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [r["labels"]["variant"] for r in records] == ["rebuild", "auto", "rs"]
    assert [f["accel"]["policy"] for f in records[2]["path"]["frames"]] == ["none"] * 3
    assert all(len(r["path"]["frames"]) == 3 for r in records)
    table = (out / "dynamic.md").read_text()
    assert table.count("| moving |") == 3 and (out / "dynamic.png").is_file()
    # auto's refitted frames traced again against a fresh tree, right after the frame
    auto_row = next(line for line in table.splitlines() if "| auto |" in line)
    assert auto_row.rstrip(" |").split("|")[-1].strip() != "–"
    refitted = [f for f in records[1]["path"]["frames"] if f["accel"]["policy"] == "refit"]
    assert refitted and all(f["fresh_tree"]["trace_ratio"] > 0 for f in refitted)
    # resume: nothing left to run; without it, the folder is refused
    assert main(["bench", str(matrix), "--out", str(out), "--resume"]) == 0
    assert len((out / "results.jsonl").read_text().splitlines()) == 3
    assert main(["bench", str(matrix), "--out", str(out)]) == 2


def test_a_path_far_from_the_origin_is_re_centred_and_renders_like_one_at_it(tmp_path):
    """The .aff path keeps its first frame's re-centring shift: frames of a scene moved 1e14
    away equal those of the scene at the origin (camera, lights and keys move with it)."""
    shifted = textwrap.dedent(SCENE)
    far = tmp_path / "far.aff"
    # Everything under one static transform that moves it 1e14 along x.
    # The view is not under any transform: it moves by hand.
    far.write_text("xs 1 1 1  0 1 0 0  100000000000000 0 0\n{\n" + shifted.replace("k camera", "k nocamera")
                   .replace("v from 0 3 8 at 0 0 0", "v from 100000000000000 3 8 at 100000000000000 0 0") + "}\n")
    near = tmp_path / "near.aff"
    near.write_text(shifted.replace("k camera", "k nocamera"))
    path = AffAnimation(far)
    scene = path.scene_at(1.0)
    assert scene.origin[0] == pytest.approx(1e14, rel=1e-6)
    images = {}
    for name, file in (("near", near), ("far", far)):
        assert main(["animate", "--scene", str(file), "--size", "24x24", "--frames", "2", "-o",
                     str(tmp_path / name)]) == 0
        images[name] = [np.asarray(Image.open(tmp_path / name / f"frame_{i:05d}.png")) for i in range(2)]
    # At rest (t = 0) the far geometry is exact in float64 and the frames are equal; once the box
    # turns, float64 at 1e14 holds positions to 1/64 of a unit, so edges may move by a pixel.
    np.testing.assert_array_equal(images["far"][0], images["near"][0])
    differing = np.any(images["far"][1] != images["near"][1], axis=-1).mean()
    assert images["far"][1].any() and differing < 0.05, differing


# -- found by a sweep of the animation features (session 38) -----------------------------------
FAR_SCENE = """
    v from 100000.37 3.1 -12.3 at 100000 1 0 up 0 1 0 angle 60 hither 0.1 resolution 64 64
    b 0.2 0.2 0.2
    l 100000 10 -5
    a 0 2 3
    fm 0.1 0.1 0.1 0.8 0.8 0.8 0 0 0 1 0 1
    p 4  99990 0 -5  100010 0 -5  100010 0 20  99990 0 20
    fm 0.1 0.1 0.1 0.8 0.2 0.2 0 0 0 1 0 1
    x mover
    {
      p 3  99997 0.5 2  100003 0.5 2  100000 5 2
    }
    k mover
    {
      transl 3
        0 0 0 0 0 0 0
        1 5 0 0 0 0 0
        2 20.1234567 0.3 0 0 0 0
    }
"""


def test_a_re_centred_path_renders_every_time_as_render_does(tmp_path):
    """A scene far from the origin whose moving part leaves the first frame's bounds: the
    animation kept the first frame's re-centring shift, render --time took its own, and the
    images differed (a pixel at 256x256); now both use the shift at the path's start, also when
    the animation starts later."""
    scene = tmp_path / "far.aff"
    scene.write_text(textwrap.dedent(FAR_SCENE))
    size = ["--size", "256x256"]
    assert main(["animate", "--scene", str(scene), *size, "--frames", "2", "--start", "1", "-o",
                 str(tmp_path / "late")]) == 0
    for t, frame in (("1", "late/frame_00000.png"), ("2", "late/frame_00001.png")):
        assert main(["render", "--scene", str(scene), *size, "--time", t, "-o", str(tmp_path / f"r{t}.png")]) == 0
        assert np.array_equal(np.asarray(Image.open(tmp_path / frame)), np.asarray(Image.open(tmp_path / f"r{t}.png")))


@pytest.mark.parametrize("name", ["frames.json", "path.png", "frame_00001.png", "preview.webp", "preview.gif"])
def test_stats_may_not_name_a_file_animate_writes(tmp_path, scene_file, capsys, name):
    out = tmp_path / "a"
    code = main(["animate", "--scene", str(scene_file), "--size", "16x16", "--frames", "2", "-o", str(out),
                 "--stats", str(out / name)])
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and len(err) == 1 and "one of the files animate writes" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("suffix", ["", "/"])
def test_stats_may_not_name_the_output_folder(tmp_path, scene_file, capsys, suffix):
    """--stats naming the -o folder itself was refused only after every frame had rendered."""
    out = tmp_path / "a"
    code = main(["animate", "--scene", str(scene_file), "--size", "16x16", "--frames", "2", "-o", str(out),
                 "--stats", str(out) + suffix])
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and len(err) == 1 and "is the -o folder itself" in err[0]
    assert not out.exists()


def test_animate_mistakes_found_late_are_one_line_before_the_work(tmp_path, scene_file, capsys, monkeypatch):
    """-o '' wrote into the current folder; --fps 1e308 was an OverflowError traceback; a
    config's [scene] time was dropped unsaid; a failure after the folder was made left it."""
    monkeypatch.chdir(tmp_path)
    common = ["animate", "--scene", str(scene_file), "--size", "16x16"]
    assert main(common + ["-o", ""]) == 2 and not list(tmp_path.glob("frame_*"))
    assert "-o needs a folder name" in capsys.readouterr().err
    assert main(common + ["--fps", "1e308", "-o", "f"]) == 2 and not (tmp_path / "f").exists()
    assert "at most 100,000" in capsys.readouterr().err
    config = tmp_path / "c.toml"
    config.write_text(f"[scene]\npath = {str(scene_file)!r}\ntime = 1.5\n")
    assert main(["animate", str(config), "--size", "16x16", "-o", "g"]) == 2 and not (tmp_path / "g").exists()
    assert "[scene] time = 1.5" in capsys.readouterr().err
    assert main(common + ["--device", "cuda", "-o", "h"]) == 2 and not (tmp_path / "h").exists()


def test_fps_frames_stay_within_the_path():
    """lo + i / fps rounded past the end (50.00000000000001 on bart-robots' 0..50 s at 1.14 fps)."""
    from engine.render.animation import plan_times

    class Path:
        name, start, end, frames = "p", 0.0, 50.0, 51

    times = plan_times(Path(), fps=1.14)
    assert times[-1] <= 50.0 and len(times) == 58


def test_resume_with_audit_refuses_unaudited_frames_and_counts_every_audited_one(tmp_path, scene_file, capsys):
    """A resumed --audit run took an earlier run's unaudited frames and reported the path
    audited; a resumed audited run counted only the frames it rendered itself."""
    out = tmp_path / "r"
    base = ["animate", "--scene", str(scene_file), "--size", "16x16", "--frames", "3", "-o", str(out)]
    assert main(base + ["--end", "1"]) == 0
    assert main(base + ["--end", "1", "--resume", "--audit"]) == 2
    assert "--audit" in capsys.readouterr().err
    audited = tmp_path / "s"
    base = ["animate", "--scene", str(scene_file), "--size", "16x16", "--frames", "3", "-o", str(audited), "--audit"]
    assert main(base + ["--stats", str(tmp_path / "whole.json")]) == 0
    whole = json.loads((tmp_path / "whole.json").read_text())["audit"]
    (audited / "frame_00001.png").unlink()        # one frame to render again
    assert main(base + ["--resume", "--stats", str(tmp_path / "resumed.json")]) == 0
    resumed = json.loads((tmp_path / "resumed.json").read_text())
    assert resumed["frames_rendered"] == 1 and resumed["audit"]["checked"] == whole["checked"] > 0


def test_warm_up_places_the_scene_twice_so_frame_zero_compiles_nothing(scene_file):
    """The per-frame placement of moving rows is a kernel of its own; the warm-up placed the
    scene once (a full build), so it first ran -- and compiled -- in frame 0's timed phase."""
    from engine.render import config as cfg
    from engine.render.animation import AnimationRenderer
    from scenes.catalog import open_path

    config = cfg.from_dict({"scene": {"path": str(scene_file)}, "render": {"width": 16, "height": 16, "packet": 4}})
    path = open_path(config.scene)
    placed = []
    original = path.scene_at
    path.scene_at = lambda t: placed.append(t) or original(t)
    AnimationRenderer(path, config).warm_up(0.0)
    assert len(placed) >= 2 and len(set(placed)) == 2


MIRRORED_SPHERES = """
    v from 0 0 9 at 0 0 0 up 0 1 0 angle 45
    l 0 0 9
    a 0 1 2
    fm 0 0 0 0.1 0.1 0.1 0.1 0.1 0.1 20 0.9 1.5
    xs -1 1 1 0 1 0 0 -2 0 0
    {
      s 0 0 0 1
    }
    x mover
    {
      s 0 0 0 1
    }
    k mover
    {
      scale 2
        0 -1 1 1 0 0 0
        1 -1 1 1 0 0 0
      transl 2
        0 2 0 0 0 0 0
        1 2 0 0 0 0 0
    }
"""


@pytest.mark.parametrize("time", [0.0, 1.0])
def test_mirroring_transforms_keep_front_faces_out(tmp_path, time):
    """A mirroring `xs` (static) or scale key (moving) turned the triangles' winding: their
    geometric normals pointed in, against the sphere's own normals, and a glass sphere refracted
    as if inside out (344 of 4,096 pixels off the unmirrored sphere's image)."""
    scene_file = tmp_path / "mirrored.aff"
    scene_file.write_text(textwrap.dedent(MIRRORED_SPHERES))
    tris = load_aff(scene_file, time).triangles
    assert tris.v0.shape[0] > 100
    assert np.einsum("ij,ij->i", tris.ng, tris.normals[:, 0]).min() > 0.5


def test_a_camera_keyed_to_scale_zero_is_one_line_without_numpy_warnings(tmp_path, capfd):
    """A camera keyframe of scale 0 has no view direction: numpy's divide warnings (four lines
    with source) came before the NaN camera's error."""
    text = textwrap.dedent(SCENE).replace("k camera\n{\n  transl 2", "k camera\n{\n  scale 1\n    0  0 0 0  0 0 0\n  transl 2")
    assert "scale 1" in text
    path = tmp_path / "flat.aff"
    path.write_text(text)
    assert main(["render", "--scene", str(path), "--size", "16x16", "--time", "1", "-o", str(tmp_path / "x.png")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"packetrt: error: {path}: the camera keyframes at time ") and "give no view" in err[0]


def test_dynamic_table_takes_static_fps_from_a_rebuild_of_the_same_frames():
    """A refit row's static FPS came from any rebuild row of the same scene and plugins: a 64x64
    refit showed an 8x8 rebuild cell's static FPS."""
    from engine.bench.dynamic import table

    def record(variant, update, size, frame_seconds):
        frames = [{"seconds": {"trace": frame_seconds, "shade": 0.0, "accel": 0.001}, "accel": {"policy": update}}] * 2
        return {"labels": {"scene": "s", "variant": variant}, "frames": 2, "threads": 2, "machine": {},
                "config": {"accel": {"update": update}, "traversal": "t", "frustum": "f",
                           "render": {"width": size, "height": size}},
                "path": {"frames": frames, "mean_fps": 1.0, "phase_share": {"accel": 0.1, "scene": 0.1},
                         "policies": {update: 2}}}

    rows = [record("small", "rebuild", 8, 0.01), record("big", "rebuild", 64, 0.5), record("refit", "refit", 64, 0.4)]
    lines = {line.split("|")[2].strip(): line.split("|") for line in table(rows).splitlines() if line.startswith("| s |")}
    assert lines["refit"][6].strip() == "2.00"   # the 64x64 rebuild's 1 / 0.5 s, not the 8x8's 100
    assert lines["small"][6].strip() == "100.00"


@pytest.mark.parametrize("override", ["reflective", "refractive"])
def test_overridden_materials_are_the_same_objects_from_frame_to_frame(scene_file, override):
    """Fresh overridden copies every frame made the renderer rebuild its material table
    (textures too) inside each frame's timed scene phase (Museum: 1.5 -> 15-47 ms a frame)."""
    from engine.core.scene import override_materials
    from engine.render import config as cfg
    from scenes.catalog import open_path

    config = cfg.from_dict({"scene": {"path": str(scene_file)}})
    path, plain = open_path(config.scene, override), open_path(config.scene)
    first, second = path.scene_at(0.0), path.scene_at(1.0)
    assert all(a is b for a, b in zip(first.materials, second.materials))
    assert second.materials == override_materials(plain.scene_at(1.0), override).materials
