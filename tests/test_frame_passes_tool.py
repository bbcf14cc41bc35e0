"""tools/frame_passes.py: every pass is timed and the renderer's kernels are back afterwards."""
from __future__ import annotations

import engine.render.whitted as whitted
from tests.tools_loader import load_tool


def test_the_passes_of_a_small_frame_are_timed_and_restored(tmp_path, capsys):
    tool = load_tool("frame_passes")
    before = {name: getattr(whitted, name) for name in tool.PASSES}
    config = tmp_path / "c.toml"
    config.write_text("[render]\nwidth = 32\nheight = 32\nmax_depth = 2\n")
    assert tool.main([str(config), "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("frame ") and "medians of 2 frames" in out[0]
    timed = {line.split()[0]: float(line.split()[1]) for line in out[1:] if not line.strip().startswith("trace")}
    assert set(timed) == set(tool.PASSES) and timed["shade_surface"] > 0 and timed["camera_batch"] > 0
    assert {name: getattr(whitted, name) for name in tool.PASSES} == before


def test_a_wrong_command_line_prints_the_usage(capsys):
    assert load_tool("frame_passes").main([]) == 2
    assert "frame_passes.py CONFIG.toml" in capsys.readouterr().err


def test_help_and_bad_input_are_answers_not_tracebacks(tmp_path, capsys):
    """--help printed a ConfigError traceback ("config file '--help' does not exist")."""
    tool = load_tool("frame_passes")
    assert tool.main(["--help"]) == 0
    assert "FRAMES" in capsys.readouterr().out
    assert tool.main([str(tmp_path / "none.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none.toml" in err and "does not exist" in err
    assert tool.main([str(tmp_path / "none.toml"), "0"]) == 2
    assert "FRAMES" in capsys.readouterr().err
