"""``engine.bench.paired_frames`` and ``tools/paired_frames.py``: frames of several configurations
interleaved in one process, each later variant's time over the first's per repetition."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))


def test_frames_are_paired_by_repetition_and_reported(tmp_path, capsys):
    from paired_frames import main

    report = tmp_path / "paired.md"
    assert main(["--scene", "whitted", "--recursion", "render-defaults", "--size", "32", "--repeat", "3",
                 "--threads", "1", "--variant", "single/none/4", "--variant", "paper/paper/4",
                 "--report", str(report)]) == 0
    text = report.read_text()
    assert capsys.readouterr().out == text
    assert "| single/none 4x4 |" in text and "| paper/paper 4x4 |" in text
    assert "the first's speed" in text


def test_the_ratios_are_the_later_variants_over_the_first(monkeypatch):
    """With frame times fixed per variant, the paired ratio is exactly their quotient."""
    import engine.render.whitted as whitted
    from engine.bench.paired_frames import paired_frames
    from paired_frames import parse_variant

    class Args:
        scene, recursion, size, threads = "whitted", "render-defaults", 32, 1

    cells = [parse_variant("single/none/4", Args), parse_variant("simd/none/2", Args)]
    seconds = {4: 0.2, 2: 0.5}
    real = whitted.WhittedRenderer.render

    def fixed(self, size=None):
        result = real(self, size)
        result.seconds = {"total": seconds[self.config.render.packet], "trace": {"primary": 0.1}, "shade": 0.05}
        return result

    monkeypatch.setattr(whitted.WhittedRenderer, "render", fixed)
    result = paired_frames(cells, 5, log=lambda m: None)
    assert [len(v["frame"]) for v in result["variants"]] == [5, 5]
    median, low, high = result["ratios"][0]["frame"]
    assert median == low == high == pytest.approx(2.5)
    assert result["ratios"][0]["trace"][0] == pytest.approx(1.0)


@pytest.mark.parametrize("variant", ["single/none", "single/none/5", "nosuch/none/4", "single/nosuch/4"])
def test_a_bad_variant_is_one_line_and_exit_2(variant, capsys):
    from paired_frames import main

    assert main(["--scene", "whitted", "--recursion", "render-defaults", "--size", "32", "--repeat", "1",
                 "--variant", "single/none/4", "--variant", variant]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("paired_frames: ") and "\n" not in err


def test_too_few_variants_or_an_unknown_preset_is_one_line_and_exit_2(capsys):
    from paired_frames import main

    assert main(["--scene", "whitted", "--variant", "single/none/4"]) == 2
    assert main(["--scene", "whitted", "--recursion", "nosuch", "--variant", "single/none/4",
                 "--variant", "single/none/8"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all(line.startswith("paired_frames: ") for line in lines)


def test_a_report_that_cannot_be_written_is_refused_before_any_frame(tmp_path, capsys, monkeypatch):
    import engine.bench.paired_frames as paired
    from paired_frames import main

    monkeypatch.setattr(paired, "paired_frames", lambda *a, **k: (_ for _ in ()).throw(AssertionError("rendered")))
    assert main(["--scene", "whitted", "--recursion", "render-defaults", "--size", "32", "--variant", "single/none/4",
                 "--variant", "single/none/8", "--report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("paired_frames: --report") and "folder" in err and "\n" not in err


TABLE2 = {"name": "t2", "repeat": 1, "embree": False, "plot": ["table2"],
          "axes": {"scene": ["whitted"], "recursion": ["reflection1-shadows"], "resolution": [32]},
          "group": [{"traversal": ["simd"], "frustum": ["none"], "packet": [2]},
                    {"traversal": ["paper"], "frustum": ["paper", "none"], "packet": [16]}]}


def test_a_matrix_with_paired_variants_writes_them_and_table2_shows_them(tmp_path):
    import json

    import engine.bench.runner as bench
    from engine.bench.matrix import parse_matrix

    matrix = parse_matrix({**TABLE2, "paired": {"variants": ["simd/none/2", "paper/paper/16"], "repeat": 2}},
                          "t2.toml")
    assert [(t.label, f.label, n) for t, f, n in matrix.paired] == [("simd", "none", 2), ("paper", "paper", 16)]
    summary = bench.run_matrix(matrix, tmp_path, progress=False)
    assert {"paired.json", "paired.md", "table2.md"} <= {p.name for p in summary["files"]}
    data = json.loads((tmp_path / "paired.json").read_text())
    (group,) = data["groups"]
    assert data["repeat"] == 2 and group["scene"] == "whitted" and group["size"] == "32x32"
    assert [len(v["frame"]) for v in group["variants"]] == [2, 2]
    table = (tmp_path / "table2.md").read_text()
    assert "## Per frame, paired by repetition" in table
    assert "| whitted | reflection1-shadows | 32x32 | paper/paper 16x16 over simd/none 2x2 |" in table
    # A later run of a matrix without [paired] into the same folder leaves no stale pairs behind.
    bench.run_matrix(parse_matrix(TABLE2, "t2.toml"), tmp_path, progress=False)
    assert not (tmp_path / "paired.json").exists()
    assert "paired by repetition" not in (tmp_path / "table2.md").read_text()


@pytest.mark.parametrize("paired, where", [
    ("no", "paired"), ({"variants": ["simd/none/2"]}, "paired.variants"),
    ({"variants": ["simd/none/2", "paper/paper"]}, "paired.variants[1]"),
    ({"variants": ["simd/none/2", "nosuch/paper/16"]}, "paired.variants[1]"),
    ({"variants": ["simd/none/2", "paper/paper/16"], "repeat": 0}, "paired.repeat"),
    ({"variants": ["simd/none/2", "paper/paper/16"], "reps": 3}, "paired.reps")])
def test_a_bad_paired_table_names_its_key(paired, where):
    from engine.bench.matrix import parse_matrix
    from engine.core.errors import ConfigError

    with pytest.raises(ConfigError, match=f"t2.toml: {where.replace('[', '.').replace(']', '.')}"):
        parse_matrix({**TABLE2, "paired": paired}, "t2.toml")
