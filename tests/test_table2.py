"""Table 2 as the paper reports it: the kitchen-paper preset (one light), the bundled matrix's
rows, the scene parameter ``lights`` in a matrix, and the table2 report built from synthetic
records (whole-frame and trace-only FPS, ratios, culling benefit, yardsticks)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from engine.bench.matrix import RECURSION, load_matrix, parse_matrix
from engine.bench.plots import table2, table2_rows
from engine.bench.runner import cell_scene
from engine.core.errors import ConfigError
from engine.core.types import RAY_KINDS

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"


@pytest.fixture
def scene_path(monkeypatch):
    """PACKETRT_SCENE_PATH = the shared scene folder (skip when it is not there)."""
    if not SHARED_SCENES.is_dir():
        pytest.skip(f"shared scene data not found at {SHARED_SCENES}")
    monkeypatch.setenv("PACKETRT_SCENE_PATH", str(SHARED_SCENES))
    return SHARED_SCENES


def one_cell(scene, recursion: str, resolution: int = 16):
    data = {"name": "t", "axes": {"scene": [scene], "recursion": [recursion], "resolution": [resolution],
                                  "traversal": ["paper"], "frustum": ["paper"], "packet": [16]}}
    matrix = parse_matrix(data, "t.toml")
    assert len(matrix.cells) == 1
    return matrix.cells[0]


# -- the preset ---------------------------------------------------------------------------------

def test_kitchen_paper_is_kitchen_full_with_one_light():
    paper, full = RECURSION["kitchen-paper"], RECURSION["kitchen-full"]
    assert (paper.max_depth, paper.max_reflection_depth, paper.lights, paper.override, paper.max_lights) == \
        (4, 1, True, "none", 1)
    assert replace(paper, max_lights=None, doc=full.doc) == full
    assert paper.as_dict()["max_lights"] == 1
    assert "max_lights" not in full.as_dict()   # the other presets' cells keep their ids


def test_kitchen_paper_cell_renders_the_kitchens_first_light_only(scene_path):
    from scenes.catalog import load_named

    base = load_named("bart-kitchen")
    assert len(base.lights) == 6
    paper = one_cell("bart-kitchen", "kitchen-paper")
    assert paper.identity()["recursion"]["max_lights"] == 1
    scene = cell_scene(base, paper)
    assert scene.lights == [base.lights[0]] and len(base.lights) == 6   # the cached scene is untouched
    assert len(cell_scene(base, one_cell("bart-kitchen", "kitchen-full")).lights) == 6
    assert cell_scene(base, one_cell("bart-kitchen", "museum-reflect3")).lights == []
    assert paper.key != one_cell("bart-kitchen", "kitchen-full").key


def test_a_preset_asking_more_lights_than_the_scene_has_names_the_count():
    from scenes.catalog import load_named

    base = replace(load_named("whitted"), lights=[])
    with pytest.raises(ConfigError, match=r"'kitchen-paper' keeps the first 1 point light\(s\), but scene "
                                          r"'whitted' has 0"):
        cell_scene(base, one_cell("whitted", "kitchen-paper"))


def test_kitchen_paper_on_a_one_light_scene_runs(tmp_path):
    """The preset through the runner on a procedural scene: a record with one light and shadow rays."""
    import engine.bench.runner as bench
    from engine.bench import results

    data = {"name": "kp", "repeat": 1, "embree": False, "plot": ["table2"],
            "axes": {"scene": ["whitted"], "recursion": ["kitchen-paper"], "resolution": [16]},
            "group": [{"traversal": ["simd"], "frustum": ["none"], "packet": [2]},
                      {"traversal": ["paper"], "frustum": ["paper", "none"], "packet": [16]}]}
    matrix = parse_matrix(data, "kp.toml")
    bench.run_matrix(matrix, tmp_path, progress=False)
    records, _ = results.read_results(tmp_path / results.RESULTS)
    assert len(records) == 3
    assert all(r["scene"]["lights"] == 1 and r["rays"]["shadow"] > 0 for r in records)
    text = (tmp_path / "table2.md").read_text()
    assert "| whitted | kitchen-paper | 16x16 |" in text and (tmp_path / "table2.png").stat().st_size > 0


# -- the bundled matrix and the scene parameter in matrices ---------------------------------------

def test_table2_matrix_has_the_papers_rows(scene_path):
    matrix = load_matrix(str(ROOT / "benchmarks" / "overbeck-table2.toml"))
    assert "table2" in matrix.plots
    cells = {(c.scene.name, c.recursion, c.traversal.label, c.frustum.label, c.packet, c.width, c.height)
             for c in matrix.cells}
    for scene, recursion in (("bart-kitchen", "kitchen-paper"), ("bart-museum", "museum-reflect3"),
                             ("erw6", "shadows")):
        assert {(scene, recursion, "simd", "none", 2, 1024, 1024), (scene, recursion, "paper", "none", 16, 1024, 1024),
                (scene, recursion, "paper", "paper", 16, 1024, 1024)} <= cells


def test_lights_as_a_scene_parameter_in_a_matrix(scene_path):
    cell = one_cell({"name": "bart-kitchen", "lights": 1}, "kitchen-full")
    assert dict(cell.scene.params) == {"lights": 1}
    with pytest.raises(ConfigError, match=r"axes\.scene\[0\]\.lights: must be str like the default 'all'"):
        one_cell({"name": "bart-kitchen", "lights": 1.5}, "kitchen-full")


# -- the report -----------------------------------------------------------------------------------

MACHINE = {"cpu": "test cpu", "python": "3", "numpy": "1", "numba": "0", "embreex": "2", "embree": "3",
           "git": {"commit": "0123456789abcdef", "dirty": False}}


def record(scene, recursion, traversal, frustum, packet, frame, trace, embree=None, open3d=None, lights=1):
    """A results.jsonl record with what the table2 report reads: frame and trace seconds per frame."""
    per_kind = lambda total: {k: {"median": total / len(RAY_KINDS)} for k in RAY_KINDS}
    return {"labels": {"scene": scene, "recursion": recursion, "resolution": "1024x1024", "traversal": traversal,
                       "frustum": frustum, "packet": packet},
            "scene": {"triangles": 1000, "lights": lights}, "rays": {"all": 123456}, "threads": 2,
            "machine": MACHINE, "matrix": "t",
            "seconds": {"frame": {"median": frame}, "shade": {"median": frame - trace},
                        "trace": per_kind(trace), "replay": per_kind(trace),
                        "embree": None if embree is None else per_kind(embree)},
            "fps": {"frame": 1 / frame, "trace": 1 / trace,
                    "embree_trace": None if embree is None else 1 / embree,
                    **({} if open3d is None else {"open3d_trace": 1 / open3d})}}


def three(scene, recursion, small, plain, culled, embree=0.5, open3d=None):
    """The 2×2 SIMD, 16×16 no culling and 16×16 culling records of one row: (frame, trace) seconds."""
    return [record(scene, recursion, "simd", "none", 2, *small, embree=embree, open3d=open3d),
            record(scene, recursion, "paper", "none", 16, *plain, embree=embree, open3d=open3d),
            record(scene, recursion, "paper", "paper", 16, *culled, embree=embree, open3d=open3d)]


def table_rows(text: str) -> dict:
    """{(scene, configuration): [cells]} of the main table."""
    rows = {}
    for line in text.split("## Where a frame goes")[0].splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and len(cells) > 6 and cells[0] != "scene":
            rows[cells[0], cells[1]] = cells
    return rows


def test_table2_report_gives_whole_frame_and_trace_fps_with_ratios(tmp_path):
    records = (three("bart-kitchen", "kitchen-paper", (2.0, 1.0), (0.5, 0.25), (0.4, 0.2))
               + three("bart-museum", "museum-reflect3", (1.0, 0.5), (0.5, 0.25), (0.25, 0.125), embree=1.0)
               + three("erw6", "shadows", (0.1, 0.05), (0.05, 0.025), (0.04, 0.02)))
    files = table2(records, tmp_path)
    assert [p.name for p in files] == ["table2.md", "table2.png"] and files[1].stat().st_size > 0
    text = files[0].read_text()
    assert "Open3D" not in text
    rows = table_rows(text)
    assert list(rows) == [("bart-kitchen", "kitchen-paper"), ("bart-museum", "museum-reflect3"), ("erw6", "shadows")]
    kitchen = rows["bart-kitchen", "kitchen-paper"]
    # frame FPS 2×2, 16×16 no culling, 16×16, ratio; trace FPS likewise; culling benefit frame / trace;
    # Embree trace FPS and our trace over it.
    assert kitchen[2:6] == ["1024x1024", "1,000", "1", "123,456"]
    assert kitchen[6:10] == ["0.50", "2.00", "2.50", "5.00×"]
    assert kitchen[10:14] == ["1.00", "4.00", "5.00", "5.00×"]
    assert kitchen[14] == "1.25× / 1.25×"
    assert kitchen[15:17] == ["2.00", "2.50×"]
    museum = rows["bart-museum", "museum-reflect3"]
    assert museum[6:10] == ["1.00", "2.00", "4.00", "4.00×"] and museum[15:17] == ["1.00", "8.00×"]
    assert rows["erw6", "shadows"][9] == "2.50×"
    where = text.split("## Where a frame goes")[1]
    assert "| bart-kitchen | kitchen-paper | 2×2 SIMD | 2,000.0 | 1,000.0 | 1,000.0 | 50% |" in where
    assert "| erw6 | shadows | 16×16, culling | 40.0 | 20.0 | 20.0 | 50% |" in where


def test_table2_report_shows_open3d_when_measured_and_tolerates_gaps(tmp_path):
    records = (three("erw6", "shadows", (0.1, 0.05), (0.05, 0.025), (0.04, 0.02), open3d=0.1)
               + [record("bunny-floor", "bunny-floor", "simd", "none", 2, 0.5, 0.25),
                  record("bunny-floor", "bunny-floor", "paper", "paper", 16, 0.25, 0.125)]    # no "no culling"
               + [record("cornell-box", "shadows", "paper", "paper", 16, 0.25, 0.125)])     # no baseline: no row
    text = table2(records, tmp_path)[0].read_text()
    rows = table_rows(text)
    assert list(rows) == [("erw6", "shadows"), ("bunny-floor", "bunny-floor")]
    assert rows["erw6", "shadows"][17:19] == ["10.00", "5.00×"]                   # Open3D trace FPS, ours over it
    bunny = rows["bunny-floor", "bunny-floor"]
    assert bunny[6:10] == ["2.00", "–", "4.00", "2.00×"] and bunny[14] == "– / –" and bunny[17:19] == ["–", "–"]
    assert table2([record("erw6", "shadows", "paper", "paper", 16, 0.25, 0.125)], tmp_path) == []


def test_table2_rows_prefer_simd_and_the_papers_system():
    records = ([record("erw6", "shadows", "masked", "none", 16, 1.0, 1.0),
                record("erw6", "shadows", "single", "none", 4, 1.0, 1.0)]
               + three("erw6", "shadows", (0.1, 0.05), (0.05, 0.025), (0.04, 0.02)))
    (row,) = table2_rows(records)
    assert row["baseline"] == "simd 2×2"
    assert row["records"]["plain"]["labels"]["traversal"] == "paper"
    assert row["frame"]["culled"] == pytest.approx(25.0)


def test_table2_report_adds_auto_beside_the_papers_system_when_measured(tmp_path):
    """A 16×16 `auto` record with frusta gets its frame FPS and its frame and trace ratios to 2×2
    SIMD in three more columns, and a row in "Where a frame goes"; the paper's columns keep the
    paper's system."""
    records = three("bart-kitchen", "kitchen-paper", (2.0, 1.0), (0.5, 0.25), (0.4, 0.2))
    records.append(record("bart-kitchen", "kitchen-paper", "auto", "paper", 16, 0.25, 0.125))
    text = table2(records, tmp_path)[0].read_text()
    kitchen = table_rows(text)["bart-kitchen", "kitchen-paper"]
    assert kitchen[6:10] == ["0.50", "2.00", "2.50", "5.00×"]       # the paper's system, as before
    assert kitchen[17:20] == ["4.00", "8.00×", "8.00×"]             # auto: frame FPS, frame and trace / 2×2
    assert "frame `auto` / 2×2" in text
    where = text.split("## Where a frame goes")[1]
    assert "| bart-kitchen | kitchen-paper | 16×16 `auto`, culling | 250.0 | 125.0 | 125.0 | 50% |" in where
    (row,) = table2_rows(records)
    assert row["records"]["culled"]["labels"]["traversal"] == "paper"
