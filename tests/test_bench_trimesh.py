"""The trimesh benchmark matrix (engine.bench.trimesh_queries): checked before work, and a tiny
run on a procedural scene gives one record per query with agreement counted."""
import json
from pathlib import Path

import pytest

from engine.bench.paired_stats import paired_ratio
from engine.bench.trimesh_queries import _alternating_seconds, _paired_times, parse, run
from engine.core.errors import ConfigError
from engine.render.config import read_toml

ROOT = Path(__file__).resolve().parents[1]


def test_the_bundled_trimesh_matrix_parses():
    spec = parse(read_toml(str(ROOT / "benchmarks" / "trimesh.toml"), "matrix"), "trimesh.toml")
    assert [m["scene"] for m in spec["mesh"]] == ["bunny", "bart-kitchen"]
    assert spec["queries"] == ["first", "any", "all", "contains"] and spec["rays"] >= 100000


def test_a_tiny_matrix_runs_and_counts_agreement(tmp_path):
    spec = parse({"kind": "trimesh", "repeat": 1, "rays": 3000, "all_rays": 500, "points": 500,
                  "render_path": True, "mesh": [{"scene": "whitted", "subdivisions": 2}]}, "tiny.toml")
    records = run(spec, tmp_path, progress=lambda line: None)
    assert [(r["rays"], r["query"]) for r in records] == [
        ("incoherent", "first"), ("incoherent", "any"), ("incoherent", "all"), ("points", "contains"),
        ("primary", "first"), ("primary", "any"), ("primary", "all"),
        ("shuffled", "first"), ("shuffled", "any"), ("shuffled", "all")]
    for r in records:
        assert r["trimesh_mrays"] > 0 and r["packetrt_mrays"] > 0
        assert r["speedup_1thread"] > 0 and r["same_on_1thread"] is True, r
        for key in ("speedup_paired", "speedup_1thread_paired"):
            median, low, high = r[key]
            assert 0 < low <= median <= high, r
        if r["query"] in ("first", "any", "all"):
            assert r["agree"] >= 0.99 * r["n"], r
    assert records[4]["render_path_mrays"] > 0
    # trimesh's contains against itself (it re-casts undecided points at random), contains only.
    assert 0.9 * records[3]["n"] <= records[3]["trimesh_self_agree"] <= records[3]["n"]
    assert all(r["trimesh_self_agree"] is None for r in records if r["query"] != "contains")
    assert records[2]["trimesh_rehits"] >= 0 and records[0]["trimesh_rehits"] is None
    assert all(r["render_path_mrays"] is None for k, r in enumerate(records) if k != 4)
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    assert [json.loads(line)["query"] for line in lines] == [r["query"] for r in records]
    assert "| whitted | primary | first |" in (tmp_path / "results.md").read_text()
    assert "speed-up, 1 thread each" in (tmp_path / "results.md").read_text()
    assert "| speed-up, paired [95%] |" in (tmp_path / "results.md").read_text()
    # Each query's host probes, and the slow-down column they give.
    for r in records:
        assert all(r["host"][when]["compute_ms"] > 0 and r["host"][when]["stream_gbps"] > 0
                   for when in ("before", "after"))
    rows = [line for line in (tmp_path / "results.md").read_text().splitlines() if line.startswith("| whitted |")]
    assert "| host slow-down |" in (tmp_path / "results.md").read_text()
    assert len(rows) == len(records) and all(float(row.rsplit("|", 2)[1]) >= 1.0 for row in rows)



def test_paired_timing_alternates_which_call_goes_first():
    """The API and the render path are timed in alternation, each after its own warm-up, so a
    drift of the host lands on both; the first call's answer comes back."""
    order = []
    first = lambda: order.append("a") or "answer"
    second = lambda: order.append("b")
    seconds_a, answer, seconds_b = _paired_times(first, second, 4)
    timed = order[-8:]
    assert timed == ["a", "b", "b", "a", "a", "b", "b", "a"]
    assert order.index("b") > 0 and answer == "answer" and len(seconds_a) == len(seconds_b) == 4


def test_the_backends_are_timed_in_alternating_rounds():
    """trimesh's and packetrt's timed calls come in blocks that alternate, the side going first
    changing from round to round, every repeat made once; each side's median and last answer
    come back."""
    blocks = []

    def side(name):
        def timed(k):
            blocks.append((name, k))
            return [0.001 * (len(blocks))] * k, name
        return timed

    (t_a, answer_a, calls_a), (t_b, answer_b, calls_b) = _alternating_seconds([side("a"), side("b")], 11, 3)
    assert blocks == [("a", 4), ("b", 4), ("b", 4), ("a", 4), ("a", 3), ("b", 3)]
    assert (answer_a, answer_b) == ("a", "b") and t_a == pytest.approx(0.004) and t_b == pytest.approx(0.003)
    assert calls_a == pytest.approx([0.001] * 4 + [0.004] * 4 + [0.005] * 3) and len(calls_b) == 11
    blocks.clear()
    _alternating_seconds([side("a"), side("b")], 2, 5)  # more rounds than repeats: a call a round
    assert blocks == [("a", 1), ("b", 1), ("b", 1), ("a", 1)]


def test_the_paired_speed_up_divides_the_calls_of_the_same_round():
    """A host that slows down over the rounds slows both calls of a round: the paired speed-up
    stays the true 2x with a tight interval, while calls of different rounds paired scatter
    from 1.2x to 3.4x."""
    drift = [1.0, 1.5, 2.0, 1.2, 1.8, 1.1, 1.9, 1.3, 1.6, 1.4, 1.7]
    theirs = [0.2 * d for d in drift]
    ours = [0.1 * d for d in drift]
    assert paired_ratio(theirs, ours) == pytest.approx((2.0, 2.0, 2.0))
    median, low, high = paired_ratio(theirs, ours[::-1])
    assert low == pytest.approx(1.6) and high == pytest.approx(2.5)  # the 2nd and 10th of 11 (1.18x .. 3.4x)


@pytest.mark.parametrize("data,words", [
    ({"mesh": [{"scene": "bunny"}], "rays": 0}, "rays"),
    ({"mesh": [{"scene": "bunny"}], "rounds": 0}, "rounds"),
    ({"mesh": [{"scene": "bunny"}], "one_thread": "yes"}, "one_thread"),
    ({"mesh": [{"scene": "bunny"}], "queries": ["closest"]}, "closest"),
    ({"mesh": []}, "[[mesh]]"),
    ({"mesh": [{"scene": "bunny"}], "colour": 1}, "colour"),
])
def test_mistakes_in_the_matrix_are_named(data, words):
    with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace("]", r"\]")):
        parse(dict(data, kind="trimesh"), "m.toml")


def test_stepping_rehits_explains_only_hits_within_trimeshs_step():
    """Two coincident faces (opposite windings) and one 0.1 behind: trimesh's stepping may report
    both coincident faces for a grazing ray; that ray counts as a re-hit, while an extra hit
    farther than trimesh's step (a crossing packetrt would have missed) does not."""
    import numpy as np
    import trimesh

    from engine.bench.trimesh_queries import stepping_rehits

    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    vertices = np.concatenate([quad, quad, quad + [0, 0, -0.1]])
    faces = np.array([[0, 1, 2], [4, 6, 5], [8, 9, 10]])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    origins, directions = np.array([[0.3, -0.4, 1.0]] * 3), np.array([[0.0, 0.0, -1.0]] * 3)
    # ray 0: theirs re-found the coincident face (explained); ray 1: theirs found the face 0.1
    # behind that ours missed (not explained); ray 2: ours has the same two crossings plus the
    # coincident face's (fewer on theirs' side: not a re-hit either).
    ours = (np.array([0, 2, 0, 0, 1, 2]), np.array([0, 0, 1, 2, 2, 2]))
    theirs = (np.array([0, 1, 2, 0, 2, 0, 2]), np.array([0, 0, 0, 1, 1, 2, 2]))
    assert stepping_rehits(mesh, ours, theirs, origins, directions) == 1
