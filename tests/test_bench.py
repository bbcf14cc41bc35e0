"""The benchmark runner: output files and their schema (never the times), --resume, interrupts,
and bad matrices rejected before any work with the key and the allowed values."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

import engine.bench.runner as bench
from engine.bench.matrix import RECURSION, load_matrix, parse_matrix
from engine.core.errors import ConfigError
from engine.bench.packets_report import COST_TERMS, packet_cells
from engine.bench.results import fastest_host, host_slowdown, host_slowness
from engine.cli import main
from engine.core.types import RAY_KINDS

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "benchmarks" / "smoke.toml"

RECORD_KEYS = {"schema", "id", "matrix", "tags", "labels", "cell", "config", "scene", "repeat", "threads",
               "seconds", "rays", "batches", "packets", "mrays_per_s", "embree_mrays_per_s", "ratio_to_embree", "fps",
               "open3d_mrays_per_s", "ratio_to_open3d", "checks", "counters", "counters_by_depth", "extra", "machine", "started", "wall_seconds", "load",
               "host"}
SUMMARY_KEYS = {"median", "min", "max", "q1", "q3", "runs"}


def lines(path: Path) -> list:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def smoke_dir(tmp_path_factory):
    """benchmarks/smoke.toml run once through the CLI."""
    out = tmp_path_factory.mktemp("bench") / "smoke"
    assert main(["bench", str(SMOKE), "--out", str(out)]) == 0
    return out


def test_smoke_writes_jsonl_csv_and_plots(smoke_dir):
    matrix = load_matrix(str(SMOKE))
    records = lines(smoke_dir / "results.jsonl")
    assert sorted(r["id"] for r in records) == sorted(c.key for c in matrix.cells)
    for r in records:
        assert set(r) == RECORD_KEYS
        assert r["schema"] == 1 and r["matrix"] == "smoke" and r["repeat"] == 2
        s = r["seconds"]
        for name in ("frame", "shade"):
            assert set(s[name]) == SUMMARY_KEYS and len(s[name]["runs"]) == 2
        for part in ("trace", "replay", "embree", "open3d"):
            assert set(s[part]) == set(RAY_KINDS) and all(set(v) == SUMMARY_KEYS for v in s[part].values())
        # The per-ray floor is measured for packet-traversal cells only ("paper" here, not "single").
        if r["labels"]["traversal"] == "paper":
            assert set(s["floor"]) == set(RAY_KINDS) and s["floor"]["primary"]["median"] > 0
        else:
            assert s["floor"] is None
        assert r["packets"]["primary"] == (64 // 8) ** 2
        assert r["rays"]["primary"] == 64 * 64 and r["rays"]["all"] == sum(r["rays"][k] for k in RAY_KINDS)
        assert set(r["mrays_per_s"]) == set(RAY_KINDS) | {"all"}
        assert r["ratio_to_embree"]["primary"] > 0 and r["embree_mrays_per_s"]["all"] > 0
        # Open3D, the second yardstick, traced the same batches (smoke.toml has embree = true,
        # which turns it on by default).
        assert r["cell"]["open3d"] is True and r["fps"]["open3d_trace"] > 0
        assert set(r["open3d_mrays_per_s"]) == set(RAY_KINDS) | {"all"} and r["open3d_mrays_per_s"]["all"] > 0
        assert r["ratio_to_open3d"]["all"] == pytest.approx(r["mrays_per_s"]["all"] / r["open3d_mrays_per_s"]["all"])
        # Every timed variant's answers were checked, ray for ray, and agreed (Open3D too: on
        # this scene it has no reason to disagree on a single ray).
        for variant in ("ours", "embree", "open3d"):
            for k in RAY_KINDS:
                row = r["checks"][variant][k]
                assert row["checked"] == r["rays"][k] and row["mismatches"] == 0, (variant, k, row)
        assert r["counters"]["ray_tri"]["primary"] > 0 and r["counters_by_depth"]["ray_aabb"]["primary"]
        assert r["fps"]["frame"] > 0 and r["fps"]["trace"] > 0
        m = r["machine"]
        assert {"cpu", "cores", "numba_threads", "python", "numpy", "numba", "embreex", "embree", "open3d", "git"} <= set(m)
        assert len(m["git"]["commit"]) == 40 or m["git"]["commit"] == "unknown"
        assert r["config"]["render"]["width"] == 64 and r["cell"]["packet"] == 8
        # The host's speed, probed just before and after the cell on the cell's threads.
        for when in ("before", "after"):
            probe = r["host"][when]
            assert probe["compute_ms"] > 0 and probe["memory_ns"] > 0 and probe["stream_gbps"] > 0
            assert probe["threads"] == r["threads"]
    by_preset = {}
    for r in records:
        by_preset.setdefault(r["labels"]["recursion"], []).append(r)
    # Recursion presets: "shadows" casts shadow rays and nothing secondary; "reflection2" has its
    # lights off (no shadow rays) and reflects.
    assert all(r["rays"]["shadow"] > 0 and r["rays"]["reflection"] == 0 for r in by_preset["shadows"])
    assert all(r["rays"]["shadow"] == 0 and r["rays"]["reflection"] > 0 for r in by_preset["reflection2"])
    # Same rays in every cell of a preset, whatever the traversal: the batches Embree re-traces.
    for rs in by_preset.values():
        assert len({json.dumps(r["rays"], sort_keys=True) for r in rs}) == 1
    with open(smoke_dir / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(records)
    assert {"id", "scene", "traversal", "frustum", "packet", "recursion", "frame_s", "mrays_all", "ratio_all",
            "rays_primary", "trace_s_shadow", "ratio_reflection", "ray_aabb_primary", "commit", "fps_open3d_trace",
            "open3d_mrays_all", "ratio_open3d_all", "open3d_s_shadow", "open3d_mrays_primary", "ratio_open3d_reflection",
            "open3d_mismatches_primary", "host_compute_ms_before", "host_memory_ns_after",
            "host_stream_gbps_after"} <= set(rows[0])
    assert all(float(row["open3d_mrays_all"]) > 0 for row in rows)
    pngs = list(smoke_dir.glob("*.png"))
    assert pngs and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    summary = (smoke_dir / "summary.md").read_text()
    assert "| whitted |" in summary and "| Open3D Mrays/s | ours / Open3D |" in summary
    assert "| CPU share | host slow-down |" in summary
    slowdowns = [float(line.rsplit("|", 2)[1]) for line in summary.splitlines() if line.startswith("| whitted |")]
    assert len(slowdowns) == len(records) and all(x >= 1.0 for x in slowdowns)


def test_host_slowdown_is_each_cell_over_the_fastest():
    def record(before, after):
        return {"host": {"before": {"compute_ms": before}, "after": {"compute_ms": after}}}
    rows = [record(6.0, 6.0), record(5.0, 7.0), record(4.0, 4.0), {"labels": {}}]
    assert host_slowdown(rows) == [1.5, 1.75, 1.0, None]  # the slower probe of each cell
    assert host_slowdown([{"labels": {}}]) == [None]


def test_resume_does_no_work(smoke_dir, tmp_path, monkeypatch):
    out = tmp_path / "again"
    shutil.copytree(smoke_dir, out)
    before = (out / "results.jsonl").read_bytes()

    def refuse(*args, **kwargs):
        raise AssertionError("--resume ran a finished cell")

    monkeypatch.setattr(bench, "run_cell", refuse)
    monkeypatch.setattr(bench, "preflight", refuse)
    assert main(["bench", str(SMOKE), "--out", str(out), "--resume"]) == 0
    assert (out / "results.jsonl").read_bytes() == before
    assert list(out.glob("*.png")) and (out / "results.csv").is_file()


def test_interrupted_run_is_consistent_and_resumes(tmp_path, monkeypatch, capsys):
    out = tmp_path / "interrupted"
    real = bench.run_cell
    calls = []

    def first_then_ctrl_c(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            # What numba raises when Ctrl-C lands inside a compiled call.
            raise SystemError("CPUDispatcher(<function _build>) returned a result with an exception set") \
                from KeyboardInterrupt()
        return real(*args, **kwargs)

    monkeypatch.setattr(bench, "run_cell", first_then_ctrl_c)
    assert main(["bench", str(SMOKE), "--out", str(out)]) == 130
    assert "--resume" in capsys.readouterr().err
    records = lines(out / "results.jsonl")
    assert len(records) == 1
    with open(out / "results.csv") as f:
        assert len(list(csv.DictReader(f))) == 1
    assert (out / "summary.md").is_file()
    # A torn last line (a crash in mid-write) is ignored, then cut off before the next append.
    with open(out / "results.jsonl", "a") as f:
        f.write('{"schema": 1, "id": "0123')
    monkeypatch.setattr(bench, "run_cell", real)
    assert main(["bench", str(SMOKE), "--out", str(out), "--resume"]) == 0
    records = lines(out / "results.jsonl")
    matrix = load_matrix(str(SMOKE))
    assert sorted(r["id"] for r in records) == sorted(c.key for c in matrix.cells)


def test_ctrl_c_before_the_first_cell_leaves_no_folder(tmp_path, monkeypatch, capsys):
    """It left a new folder with an empty results.csv and a summary.md of no rows."""
    out = tmp_path / "new"

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(bench, "run_cell", ctrl_c)
    assert main(["bench", str(SMOKE), "--out", str(out)]) == 130
    assert "before the first cell finished" in capsys.readouterr().err
    assert not out.exists()


VALID = """
name = "t"
repeat = 1
[axes]
scene = ["whitted"]
traversal = ["single"]
frustum = ["none"]
packet = [8]
recursion = ["primary"]
resolution = [16]
"""


def replace_line(key: str, value: str) -> str:
    return "\n".join(f"{key} = {value}" if line.startswith(f"{key} =") else line for line in VALID.splitlines())


BAD_MATRICES = [
    (replace_line("scene", '["nowhere"]'), ["axes.scene[0]", "unknown scene 'nowhere'", "catalog scenes:", "whitted"]),
    (replace_line("traversal", '["warp"]'),
     ["axes.traversal[0]", "unknown traversal 'warp'", "registered traversals:", "partition"]),
    (replace_line("frustum", '[{shadow = "cone"}]'), ["axes.frustum[0].shadow", "unknown frustum 'cone'", "pointlight"]),
    (replace_line("packet", "[]"), ["axes.packet", "axis is empty", "2, 4, 8, 16, 32"]),
    (replace_line("packet", '["16"]'), ["axes.packet[0]", "must be an integer", "2, 4, 8, 16, 32", "'16'"]),
    (replace_line("packet", "[6]"), ["axes.packet[0]", "one of 2, 4, 8, 16, 32"]),
    (replace_line("recursion", '["deep"]'), ["axes.recursion[0]", "unknown recursion preset 'deep'", "reflection2"]),
    (replace_line("recursion", "[2]"), ["axes.recursion[0]", "must be a recursion preset name", "shadows"]),
    (replace_line("resolution", "[16.5]"), ["axes.resolution[0]", "must be N (N x N), [W, H]"]),
    (replace_line("resolution", "[0]"), ["render.width must be in 1..16384"]),
    (replace_line("scene", '[{name = "whitted", colour = 3}]'), ["axes.scene[0]", "no parameter(s) ['colour']", "checks"]),
    (replace_line("scene", '[{name = "whitted", checks = "many"}]'), ["axes.scene[0].checks", "must be int"]),
    (replace_line("repeat", "0"), ["repeat", "1..1000"]),
    (replace_line("repeat", '"five"'), ["repeat", "must be an integer"]),
    (VALID + 'plot = ["mrays"]\n', ["axes.plot", "unknown axis", "top-level keys go before [axes]"]),
    (VALID.replace('repeat = 1', 'repeat = 1\nplot = ["fig9"]'), ["plot[0]", "unknown figure kind 'fig9'", "table2"]),
    (VALID.replace('repeat = 1', 'repeats = 1'), ["repeats", "unknown key", "allowed: name, description, repeat"]),
    (VALID.replace("[axes]", "[axes]\ncolour = [1]"), ["axes.colour", "unknown axis", "scene, traversal"]),
    (VALID.replace('packet = [8]\n', ""), ["axes.packet", "missing axis"]),
    (VALID + "[[group]]\ntag = 'a'\n[[group]]\npacket = [8, 7]\n", ["group[1].packet[1]", "one of 2, 4, 8, 16, 32"]),
    (VALID + "[options.rayspace]\npair_budget = 0\n", ["options.rayspace: pair_budget must be an integer"]),
    ("[axes\n", ["not valid TOML"]),
]


@pytest.mark.parametrize("content,messages", BAD_MATRICES)
def test_bad_matrix_rejected_before_any_work(tmp_path, monkeypatch, capsys, content, messages):
    def refuse(*args, **kwargs):
        raise AssertionError("work started on a bad matrix")

    monkeypatch.setattr(bench, "run_matrix", refuse)
    path = tmp_path / "bad.toml"
    path.write_text(content)
    out = tmp_path / "out"
    assert main(["bench", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("packetrt: error: ") and err.count("\n") == 1 and str(path) in err
    for message in messages:
        assert message in err
    assert not out.exists()


def test_missing_scene_files_are_named_before_work(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PACKETRT_SCENE_PATH", str(tmp_path))
    path = tmp_path / "m.toml"
    path.write_text(replace_line("scene", '[{name = "bunny", lod = 3}]'))
    assert main(["bench", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "missing file(s) stanford-bunny/bun_zipper_res4.ply" in err and str(tmp_path) in err


def test_missing_matrix_file_and_bad_repeat(tmp_path, capsys):
    assert main(["bench", str(tmp_path / "none.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err
    path = tmp_path / "m.toml"
    path.write_text(VALID)
    assert main(["bench", str(path), "--repeat", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--repeat: must be in 1..1000" in capsys.readouterr().err


def test_cells_are_the_union_of_group_products_with_stable_ids():
    data = {"repeat": 1, "axes": {"scene": ["whitted"], "traversal": ["single", "paper"], "frustum": ["none"],
                                  "packet": [8, 16], "recursion": ["primary"], "resolution": [16, [32, 8], "8x4"]},
            "group": [{"tag": "a"}, {"tag": "b", "packet": [8], "resolution": [16]}]}
    matrix = parse_matrix(data, "m.toml")
    assert len(matrix.cells) == 2 * 2 * 3  # group b's cells are all in group a: measured once
    both = [c for c in matrix.cells if c.tags == ("a", "b")]
    assert len(both) == 2 and all(c.packet == 8 and (c.width, c.height) == (16, 16) for c in both)
    assert {(c.width, c.height) for c in matrix.cells} == {(16, 16), (32, 8), (8, 4)}
    paper = next(c for c in matrix.cells if c.traversal.label == "paper")
    assert paper.traversal.per_kind() == {"primary": "ranged", "shadow": "partition", "reflection": "partition",
                                          "refraction": "partition"}
    # Labels and tags are not part of a cell's identity; its configuration is.
    relabelled = parse_matrix({**data, "axes": {**data["axes"], "scene": [{"name": "whitted", "label": "W"}]}}, "x")
    assert {c.key for c in relabelled.cells} == {c.key for c in matrix.cells}
    deeper = parse_matrix({**data, "axes": {**data["axes"], "recursion": ["shadows"]}}, "x")
    assert not {c.key for c in deeper.cells} & {c.key for c in matrix.cells}
    table = parse_matrix({**data, "axes": {**data["axes"], "traversal": [{"label": "mix", "shadow": "single"}]}}, "x")
    assert table.cells[0].traversal.per_kind()["shadow"] == "single"
    assert table.cells[0].traversal.per_kind()["primary"] == "ranged"


def test_a_traversal_entry_carries_options_that_override_the_matrix():
    """One matrix compares option values: an entry's options replace the matrix's for its cells,
    join them for other keys, and make cells of their own; a bad table names its key."""
    data = {"repeat": 1, "options": {"rayspace": {"pair_budget": 5000}},
            "axes": {"scene": ["whitted"], "frustum": ["none"], "packet": [8], "recursion": ["shadows"],
                     "resolution": [16],
                     "traversal": [{"label": "light", "shadow": "rayspace"},
                                   {"label": "pixel", "shadow": "rayspace",
                                    "options": {"rayspace": {"shadow_grid": "pixel"}}}]}}
    cells = {c.traversal.label: c for c in parse_matrix(data, "m.toml").cells}
    assert dict(cells["light"].options) == {"rayspace": (("pair_budget", 5000),)}
    assert dict(cells["pixel"].options) == {"rayspace": (("pair_budget", 5000), ("shadow_grid", "pixel"))}
    assert cells["light"].key != cells["pixel"].key
    assert cells["pixel"].config().options == cells["pixel"].options
    no_entry_options = parse_matrix({**data, "axes": {**data["axes"], "traversal": ["single"]}}, "m.toml")
    assert no_entry_options.cells[0].options == (("rayspace", (("pair_budget", 5000),)),)
    bad = {**data, "axes": {**data["axes"], "traversal": [{"shadow": "rayspace", "options": {"rayspace": 3}}]}}
    with pytest.raises(ConfigError, match=r"m\.toml: axes\.traversal\[0\]\.options"):
        parse_matrix(bad, "m.toml")
    wrong = {**data, "axes": {**data["axes"], "traversal": [{"shadow": "rayspace",
                                                             "options": {"rayspace": {"shadow_grid": "x"}}}]}}
    with pytest.raises(ConfigError, match="shadow_grid must be one of"):
        parse_matrix(wrong, "m.toml")
    frustum = {**data, "axes": {**data["axes"], "frustum": [{"shadow": "none", "options": {}}]}}
    with pytest.raises(ConfigError, match="unknown key"):
        parse_matrix(frustum, "m.toml")


def test_bundled_matrices_parse():
    """Every bundled matrix is valid where its scenes are available (the smoke one always)."""
    from scenes.catalog import entries, find_files

    for path in sorted((ROOT / "benchmarks").glob("*.toml")):
        text = path.read_text()
        if 'kind = "trimesh"' in text:
            continue  # a mesh-query matrix, not renders: tests/test_bench_trimesh.py parses it
        needs = [name for name, entry in entries().items() if f'"{name}"' in text and find_files(entry)[1]]
        if needs and path != SMOKE:
            continue
        if 'kind = "dynamic"' in text:          # whole animation paths: engine.bench.dynamic
            from engine.bench.dynamic import load_dynamic
            from engine.render.config import read_toml

            assert load_dynamic(read_toml(str(path), "matrix"), str(path))[1]
            continue
        if 'kind = "gpu"' in text:              # rays and frames on the GPU: engine.bench.gpu
            from engine.bench.gpu import check_matrix
            from engine.render.config import read_toml

            check_matrix(read_toml(str(path), "matrix"), str(path))
            continue
        matrix = load_matrix(str(path))
        assert matrix.cells and matrix.plots


def test_kitchen_full_limits_reflections_not_refractions():
    """The Table 2 kitchen preset's max_reflection_depth: mirror reflections only off camera hits."""
    from dataclasses import replace

    from engine.render.config import Config, RenderConfig
    from engine.render.whitted import WhittedRenderer
    from scenes.catalog import load_named

    scene = load_named("whitted")  # a mirror sphere and a glass sphere
    preset = RECURSION["kitchen-full"]
    assert (preset.max_depth, preset.max_reflection_depth, preset.lights) == (4, 1, True)
    base = Config(render=RenderConfig(width=32, height=32, max_depth=4, packet=8),
                  traversal=None, frustum=None)
    full = WhittedRenderer(scene, base).render().rays
    limited = WhittedRenderer(scene, replace(base, render=replace(base.render, max_reflection_depth=1))).render().rays
    assert 0 < limited["reflection"] < full["reflection"]
    assert limited["refraction"] == full["refraction"] > 0 or limited["refraction"] > 0
    none = WhittedRenderer(scene, replace(base, render=replace(base.render, max_reflection_depth=0))).render().rays
    assert none["refraction"] > 0 and none["reflection"] < limited["reflection"]


def test_every_plot_kind_draws(tmp_path):
    """A tiny matrix that feeds every figure and table kind."""
    data = {"name": "plots", "repeat": 1, "plot": ["mrays", "fig5", "fig6", "fig7", "table2", "roger", "packets"],
            "axes": {"scene": ["whitted"], "recursion": ["reflection1-shadows"], "resolution": [32],
                     "packet": [16], "frustum": ["none"]},
            "group": [{"traversal": ["simd"], "packet": [2]},
                      {"traversal": ["paper", "ranged", "partition"], "frustum": ["paper", "none"], "packet": [8, 16]},
                      {"tag": "resolution", "traversal": ["rayspace", "single"], "resolution": [16, 32]}]}
    matrix = parse_matrix(data, "plots.toml")
    summary = bench.run_matrix(matrix, tmp_path, progress=False)
    assert summary["ran"] == len(matrix.cells)
    names = {p.name for p in summary["files"]}
    assert {"results.csv", "summary.md", "mrays.png", "fig5.png", "fig6-whitted.png", "fig6-totals.png", "fig7.png",
            "fig7.md", "table2.md", "table2.png", "roger.md", "roger.png", "packets.md", "packets.png"} <= names
    table = (tmp_path / "table2.md").read_text()
    assert "| whitted | reflection1-shadows | 32x32 |" in table and "×" in table
    records = lines(tmp_path / "results.jsonl")
    rayspace = next(r for r in records if r["labels"]["traversal"] == "rayspace")
    assert rayspace["extra"]["reflection"]["rayspace"]["candidates_per_ray"] > 0
    assert "candidates" in (tmp_path / "roger.md").read_text()
    # The packet report: only packet-traversal cells (13 here), per-kind rates, the targets
    # against the 2x2 simd baseline and a cost model fitted on those cells whose walk time
    # (replay - floor) is positive: at 32x32 timing noise can push one below its floor.
    report = (tmp_path / "packets.md").read_text()
    assert "| ranged | on | " in report and "| partition | off | " in report and "| Embree | – | " in report
    assert "over the 2×2 SIMD baseline" in report and "Culling benefit" in report
    (cells,) = packet_cells(records).values()
    assert len(cells) == 13
    usable = [r for r in cells if r["seconds"]["replay"]["primary"]["median"] > r["seconds"]["floor"]["primary"]["median"]]
    # The fit needs twice as many usable cells as terms; on a busy machine fewer may be left.
    fitted = f"| primary | {len(usable)} | " in report
    assert fitted == (len(usable) >= 2 * len(COST_TERMS)) and "rayspace" not in report
    assert "the per-ray floor" in report and "| simd | off | 2 | " in report


@pytest.mark.usefixtures("shared_scenes")
def test_bunny_floor_scene():
    from scenes.catalog import load_named

    scene = load_named("bunny-floor", {"lod": 3})
    assert scene.n_triangles == 948 + 128 and len(scene.lights) == 1
    assert max(scene.materials[1].reflectance) > 0 and max(scene.materials[0].reflectance) == 0


def test_cost_fit_recovers_known_costs_and_never_goes_negative():
    """The packets report's cost model: exact costs come back from noiseless data, and a term
    whose unconstrained fit would be negative is held at zero instead."""
    import numpy as np

    from engine.bench.packets_report import nonnegative_fit

    rng = np.random.default_rng(3)
    a = rng.random((40, 4)) * [1e3, 1e5, 1e6, 1e5]
    costs = np.array([30e-9, 5e-9, 4e-9, 17e-9])
    np.testing.assert_allclose(nonnegative_fit(a / a.max(0), a @ costs) / a.max(0), costs, rtol=1e-9)
    y = a[:, 0] * 1e-8 - a[:, 1] * 1e-10  # the unconstrained fit gives the second term a negative cost
    assert np.linalg.lstsq(a, y, rcond=None)[0][1] < 0
    x = nonnegative_fit(a, y)
    assert (x >= 0).all() and x[1] == 0 and x[0] > 0


def test_wrong_answers_are_caught_and_their_rates_dropped():
    """The runner's answer check can fail: tampered answers count as mismatches, and a kind with
    mismatches loses its rate (and so does "all")."""
    import numpy as np

    from engine.render.config import Config, RenderConfig
    from engine.render.whitted import WhittedRenderer
    from scenes.catalog import load_named

    config = Config(render=RenderConfig(width=32, height=32, max_depth=2, packet=8))
    recorder = bench.BatchRecorder()
    renderer = WhittedRenderer(load_named("whitted"), config, observer=recorder)
    renderer.render()
    renderer.observer = None
    reference = bench.ReferenceAnswers().get(renderer, recorder)
    _, answers = bench.replay(recorder.batches, renderer.tracer)
    good = bench.check_answers(recorder.batches, answers, reference, renderer.tracer, renderer.tris)
    assert all(good[k]["mismatches"] == 0 for k in RAY_KINDS) and good["primary"]["checked"] == 32 * 32
    tampered = []
    for (kind, query, rays, packets), answer in zip(recorder.batches, answers):
        if query == "intersect":
            hit = np.flatnonzero(answer.prim >= 0)[:5]
            answer.prim[hit] = (answer.prim[hit] + 7) % renderer.tris.v0.shape[0]
            answer.t[hit] *= 0.5
        else:
            answer[:] = ~answer & (rays.tmin <= rays.tmax)
        tampered.append(answer)
    bad = bench.check_answers(recorder.batches, tampered, reference, renderer.tracer, renderer.tris)
    assert bad["primary"]["mismatches"] == 5 and bad["shadow"]["mismatches"] > 0
    rates = bench._checked({"primary": 1.0, "shadow": 2.0, "reflection": 3.0, "refraction": 4.0, "all": 5.0}, bad)
    assert rates["primary"] is None and rates["shadow"] is None and rates["all"] is None
    assert bench._checked(dict(rates, primary=1.0, shadow=2.0, all=5.0), good)["all"] == 5.0


def test_the_eta_cost_counts_only_the_lights_a_preset_keeps():
    """``kitchen-paper`` keeps the first light: its shadow rays are one light's, not six."""
    from engine.bench.matrix import parse_matrix
    from engine.bench.runner import _cost

    table = {"name": "eta", "axes": {"scene": ["whitted"], "recursion": ["kitchen-full", "kitchen-paper"],
                                     "traversal": ["partition"], "frustum": ["general"], "packet": [8],
                                     "resolution": [64]}}
    cells = parse_matrix(table, "<eta>").cells
    full, paper = (next(c for c in cells if c.recursion == name) for name in ("kitchen-full", "kitchen-paper"))
    six_lights = (6, 1000)
    # kinds per generation: primary + 6 shadow kinds, against primary + 1.
    assert _cost(full, six_lights, 1) / _cost(paper, six_lights, 1) == 7 / 2
    assert _cost(paper, (1, 1000), 1) == _cost(paper, six_lights, 1)


def test_recorded_batches_are_the_rays_the_frame_cast():
    """The runner replays (ours, the floor, Embree, Open3D) what BatchRecorder kept: it must be
    every batch as it was cast, although the renderer reuses its per-lane arrays within the
    frame (a later shadow batch or generation writes where an earlier one was)."""
    import numpy as np

    from engine.render.config import Config, RenderConfig
    from engine.render.whitted import WhittedRenderer
    from scenes.catalog import load_named

    recorder, cast = bench.BatchRecorder(), []

    def observe(kind, query, rays, packets, answer):
        recorder(kind, query, rays, packets, answer)
        cast.append([np.array(getattr(rays, f)) for f in ("org", "dir", "tmin", "tmax", "pixel")])

    config = Config(render=RenderConfig(width=40, height=32, max_depth=4, packet=8))
    WhittedRenderer(load_named("whitted"), config, observer=observe).render()
    kinds = [batch[0] for batch in recorder.batches]
    assert kinds.count("shadow") > 1 and kinds.count("reflection") > 1  # arrays were reused
    for (kind, _, rays, _), arrays in zip(recorder.batches, cast):
        for name, array in zip(("org", "dir", "tmin", "tmax", "pixel"), arrays):
            assert np.array_equal(getattr(rays, name), array), (kind, name)


def _gpu_result(rays):
    frame = {"scene": "bunny", "recursion": "shadows", "variant": "rayspace", "resolution": [64, 64],
             "median_seconds": 0.0125, "fps": 80.0, "compile_seconds": 1.0}
    return {"device": "Some GPU", "date": "2026-11-26", "labels": ["bvh", "rayspace"], "rays": rays,
            "frames": [frame], "images": [], "audits": [{"scene": "bunny", "variant": "rayspace", "checked": 9,
                                                         "mismatches": 0}]}


def test_gpu_variant_may_name_a_traversal_per_ray_kind():
    """The paper's rayspace system rasterises camera rays: a variant names a device traversal per
    kind, for frames only; a partial table or one with ray sets is refused, naming the key."""
    from engine.bench.gpu import check_matrix, variant_traversals

    scene = [{"name": "cornell-box", "recursion": "render-defaults"}]  # kitchen-paper (the default) limits lights
    per_kind = {"primary": "bvh", "shadow": "rayspace", "reflection": "rayspace", "refraction": "rayspace"}
    check_matrix({"kind": "gpu", "scene": scene, "variant": [{"label": "r", "traversal": per_kind, "rays": False}]},
                 "g.toml")
    assert variant_traversals({"traversal": per_kind}) == per_kind
    assert variant_traversals({"traversal": "bvh"}) == dict.fromkeys(per_kind, "bvh")
    with pytest.raises(ConfigError, match="g.toml: variant 1: a traversal per ray kind times frames only"):
        check_matrix({"kind": "gpu", "scene": scene, "variant": [{"label": "r", "traversal": per_kind}]}, "g.toml")
    with pytest.raises(ConfigError, match="g.toml: variant 1 traversal: a table needs a traversal name for each"):
        check_matrix({"kind": "gpu", "scene": scene, "variant": [{"label": "r", "traversal": {"primary": "bvh"},
                                                                  "rays": False}]}, "g.toml")
    with pytest.raises(ConfigError, match="g.toml: variant 1 traversal: must be a name or a table"):
        check_matrix({"kind": "gpu", "scene": scene, "variant": [{"label": "r", "traversal": 3}]}, "g.toml")


def test_gpu_table_of_frames_only_has_no_ray_table():
    """A gpu matrix whose variants cast no ray sets writes the frame and audit tables only (it
    once wrote a ray table's header with an empty traversal column)."""
    from engine.bench.gpu import table

    text = table(_gpu_result([]))
    assert "| scene | rays |" not in text
    assert "| bunny | shadows | rayspace | 64x64 | 12.50 ms | 80.0 | 1.0 s |" in text
    row = {"scene": "bunny", "rays": "primary", "resolution": 64, "count": 4096,
           "bvh": {"grays_per_s": 2.0, "seconds": 0.001, "kernel_grays_per_s": 2.5,
                   "embree": {"mismatches": 0, "ties": 1}},
           "mitsuba": {"grays_per_s": 1.0, "seconds": 0.002}}
    text = table(_gpu_result([row]))
    assert "| scene | rays | count | bvh | Mitsuba 3 cuda_ad_rgb | ours / Mitsuba |" in text
    assert "| 2.00x |" in text


def test_a_cell_keeps_no_frame_image_alive_while_it_times_the_next(monkeypatch):
    """Each timed render's image must be free before the next render: kept alive (all of a
    cell's frames were), every timed frame's image was fresh memory whose page faults landed in
    the shading passes of a process's first cell only (15-25 ms a 1024x1024 kitchen frame),
    whose later cells reused the memory earlier cells had freed."""
    import gc
    import weakref

    from engine.render.whitted import WhittedRenderer

    real_render = WhittedRenderer.render
    alive, most = [], []

    def render(self, size=None):
        gc.collect()
        most.append(sum(ref() is not None for ref in alive))
        result = real_render(self, size)
        alive.append(weakref.ref(result.image))
        return result

    monkeypatch.setattr(WhittedRenderer, "render", render)
    table = {"name": "alive", "axes": {"scene": ["whitted"], "recursion": ["render-defaults"],
                                       "traversal": ["partition"], "frustum": ["general"], "packet": [8],
                                       "resolution": [32]}}
    cell = parse_matrix(table, "<alive>").cells[0]
    record = bench.measure_cell_afresh(cell, 4, "alive")
    assert record["seconds"]["frame"]["median"] > 0
    # The warm-up render and then four timed renders: none starts with an earlier image alive.
    assert len(most) >= 5 and max(most[1:5]) == 0, most


def _host_record(before, after, label=""):
    return {"label": label, "host": {"before": {"compute_ms": before}, "after": {"compute_ms": after}}}


def test_steadiest_measures_a_cell_again_while_the_host_ran_slow():
    again = iter([_host_record(9.0, 9.5, "second"), _host_record(5.2, 5.3, "third"), _host_record(5.0, 5.0, "4th")])
    record, fastest = bench.steadiest(lambda: next(again), _host_record(8.0, 8.0, "first"), 1.1, 2,
                                      {"compute_ms": 5.0})
    # 8 > 1.1 x 5: measured again; 9.5 is worse (kept the first); 5.3 is within 1.1 x 5: kept, stop.
    assert record["label"] == "third" and record["host"]["measured"] == 3 and fastest == {"compute_ms": 5.0}
    assert next(again)["label"] == "4th"  # no fourth measurement


def test_steadiest_keeps_a_steady_cell_and_stops_after_its_retries():
    calls = []
    five = {"compute_ms": 5.0}
    record, _ = bench.steadiest(lambda: calls.append(1), _host_record(5.4, 5.0, "only"), 1.1, 2, five)
    assert record["label"] == "only" and record["host"]["measured"] == 1 and not calls
    slow = iter([_host_record(9.0, 9.0, "b"), _host_record(8.0, 8.5, "c")])
    record, fastest = bench.steadiest(lambda: next(slow), _host_record(10.0, 10.0, "a"), 1.1, 2, five)
    assert record["label"] == "c" and record["host"]["measured"] == 3 and fastest == five
    # The run's fastest moment is learnt from the probes: a faster probe lowers the bar.
    record, fastest = bench.steadiest(lambda: None, _host_record(4.0, 4.2, "quick"), 1.1, 2, five)
    assert record["label"] == "quick" and fastest == {"compute_ms": 4.0}


def test_host_slowness_takes_the_slowest_measure_of_either_probe():
    fastest = {"compute_ms": 5.0, "memory_ns": 100.0, "stream_gbps": 15.0}
    record = {"host": {"before": {"compute_ms": 5.0, "memory_ns": 130.0, "stream_gbps": 15.0},
                       "after": {"compute_ms": 5.5, "memory_ns": 100.0, "stream_gbps": 10.0}}}
    assert host_slowness(record, fastest) == pytest.approx(1.5)  # the bandwidth after: 15 / 10
    assert fastest_host([record]) == {"compute_ms": 5.0, "memory_ns": 100.0, "stream_gbps": 15.0}
    assert host_slowness({"labels": {}}, fastest) is None


def test_run_matrix_under_steady_records_the_steadiest_measurement(tmp_path, monkeypatch):
    """A fake cell measurement whose host is slow the first time: the matrix keeps the second."""
    matrix = load_matrix(str(SMOKE))
    probes = iter([10.0, 5.0])

    def fake_run(cell, *args, **kwargs):
        load = next(probes, 5.0)
        return {"schema": 1, "id": cell.key, "labels": cell.labels(), "host": {"before": {"compute_ms": load},
                                                                               "after": {"compute_ms": load}}}

    monkeypatch.setattr(bench.host_speed, "measure", lambda: {"compute_ms": 5.0, "memory_ns": 100.0, "threads": 2})
    monkeypatch.setattr(bench, "write_outputs", lambda out, matrix: [])
    matrix.cells = matrix.cells[:2]
    bench.run_matrix(matrix, tmp_path, progress=False, run=fake_run, steady=1.2, retries=3)
    records = lines(tmp_path / "results.jsonl")
    assert [r["host"]["measured"] for r in records] == [2, 1]
    assert [r["host"]["before"]["compute_ms"] for r in records] == [5.0, 5.0]


@pytest.mark.parametrize("flags, message", [(["--steady", "0.9"], "--steady must be a number >= 1"),
                                            (["--steady", "nan"], "--steady must be a number >= 1"),
                                            (["--steady", "1.1", "--retries", "-1"], "--retries must be"),
                                            (["--steady", "1.1", "--scheduler"], "does not combine with --scheduler")])
def test_bad_steady_flags_are_one_line(tmp_path, capsys, flags, message):
    assert main(["bench", str(SMOKE), "--out", str(tmp_path / "x"), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


# -- found by a sweep of the runner (session 38) -------------------------------------------------
def test_two_scenes_under_one_camera_keep_their_own_references_and_yardsticks(tmp_path):
    """The whitted scene at two subdivisions casts the same primary rays: the reference answers
    and yardstick timings were cached by the rays alone, so the second cell's right answers were
    called wrong (737 rays, its rates dropped) and Embree's seconds were the first scene's."""
    data = {"name": "dg", "repeat": 1, "embree": True, "open3d": False,
            "axes": {"scene": [{"name": "whitted", "subdivisions": 1}, {"name": "whitted", "subdivisions": 3}],
                     "traversal": ["ranged"], "frustum": ["none"], "packet": [8], "recursion": ["primary"],
                     "resolution": [48]}}
    bench.run_matrix(parse_matrix(data, "dg.toml"), tmp_path, progress=False)
    first, second = lines(tmp_path / "results.jsonl")
    assert first["scene"]["triangles"] < second["scene"]["triangles"]
    for record in (first, second):
        for who, rows in record["checks"].items():
            assert all(row["mismatches"] == 0 for row in rows.values()), (who, rows)
        assert record["mrays_per_s"]["all"] is not None
    assert first["seconds"]["embree"] != second["seconds"]["embree"]


def test_table2_baseline_is_simd_without_frusta_and_labels_name_one_entry(tmp_path):
    """Table 2 took the first simd 2x2 record, frusta or not, and called it simd 2x2 all the
    same; one label on two groups' different traversals merged their rows."""
    from engine.bench.plots import table2_rows

    def record(traversal, frustum, packet, frame):
        return {"labels": {"scene": "s", "recursion": "r", "resolution": "8x8", "traversal": traversal,
                           "frustum": frustum, "packet": packet},
                "fps": {"frame": frame}, "scene": {"triangles": 1}, "rays": {"all": 1},
                "seconds": {"replay": {k: {"median": 1.0 / frame} for k in RAY_KINDS}, "embree": None}}

    records = [record("simd", "paper", 2, 6.0), record("simd", "none", 2, 1400.0), record("paper", "paper", 16, 2000.0)]
    (row,) = table2_rows(records)
    assert row["records"]["small"]["labels"]["frustum"] == "none" and row["baseline"] == "simd 2×2"
    (row,) = table2_rows([records[0], records[2]])
    assert row["baseline"] == "simd 2×2 with frusta paper"  # said, not hidden
    data = {"name": "lab", "repeat": 1, "axes": {"scene": ["whitted"], "recursion": ["shadows"], "resolution": [16],
                                                 "frustum": ["none"], "packet": [8]},
            "group": [{"traversal": [{"label": "X", "primary": "ranged"}]},
                      {"traversal": [{"label": "X", "primary": "masked"}]}]}
    with pytest.raises(ConfigError, match=r"group\[1\]\.traversal: label 'X' already names another traversal"):
        parse_matrix(data, "lab.toml")


def test_paired_variants_take_the_matrix_options_not_the_first_cells(tmp_path, monkeypatch):
    import engine.bench.paired_frames as paired

    data = {"name": "po", "repeat": 1, "embree": False,
            "axes": {"scene": ["whitted"], "frustum": ["paper"], "packet": [8], "recursion": ["shadows"],
                     "resolution": [16],
                     "traversal": [{"label": "rs-pixel", "shadow": "rayspace",
                                    "options": {"rayspace": {"shadow_grid": "pixel"}}}, "ranged"]},
            "paired": {"variants": ["ranged/paper/8", "rayspace/paper/8"], "repeat": 1}}
    matrix = parse_matrix(data, "po.toml")
    assert matrix.cells[0].options  # the first cell's entry carries its own options
    seen = []
    monkeypatch.setattr(paired, "paired_frames", lambda cells, *a, **k: seen.extend(cells) or (_ for _ in ()).throw(
        KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        paired.run_paired(matrix, tmp_path)
    assert [cell.options for cell in seen] == [(), ()]


def test_an_empty_out_is_an_error_not_the_default_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["bench", str(Path(__file__).parents[1] / "benchmarks" / "smoke.toml"), "--out", ""]) == 2
    assert "--out needs a folder name" in capsys.readouterr().err and not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra, named", [(["--repeat", "3"], "repeat 3"), ([], "'renamed'")])
def test_resume_refuses_records_of_another_matrix_or_repeat(smoke_dir, tmp_path, capsys, extra, named):
    """--resume with a different --repeat, or another matrix's records in --out, counted those
    records as done: the table mixed repeat counts, or kept another matrix's cells."""
    out = tmp_path / "again"
    shutil.copytree(smoke_dir, out)
    before = (out / "results.jsonl").read_bytes()
    matrix = SMOKE
    if not extra:
        matrix = tmp_path / "renamed.toml"
        matrix.write_text(SMOKE.read_text().replace(f'name = "{bench.load_matrix(str(SMOKE)).name}"',
                                                    'name = "renamed"'))
        assert bench.load_matrix(str(matrix)).name == "renamed"
    assert main(["bench", str(matrix), "--out", str(out), "--resume", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("packetrt: error: --resume: ") and named in err
    assert (out / "results.jsonl").read_bytes() == before
