"""Open3D as the benchmark's second yardstick (engine.bench.open3d_yardstick): its lean driver
answers exactly what the Open3D oracle answers on any segments, its replays are checked against
the reference like every variant (wrong answers are caught, a few disagreeing rays keep the
rate, many drop it), the matrix key is strict, and a missing Open3D stops the run before work."""
import numpy as np
import pytest

import engine.bench.runner as bench
from engine.bench.matrix import parse_matrix
from engine.bench.open3d_yardstick import (OPEN3D_MISMATCH_TOLERANCE, Open3DTraversal, Open3DYardstick,
                                           open3d_rates)
from engine.cli import main
from engine.core.triangle import safe_inverse
from engine.core.types import RAY_KINDS, RayBatch, empty_hits
from scenes.catalog import load_named
from validation.open3d_oracle import Open3DOracle, Open3DUnavailable


@pytest.fixture(scope="module")
def whitted():
    return load_named("whitted")


def segment_batch(tris, n, seed):
    """Rays aimed at random triangles with every kind of segment: unbounded, cut short, starting
    past the origin (tmin > 0), one-point, dead (tmax < tmin) and NaN."""
    rng = np.random.default_rng(seed)
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1).astype(np.float64)
    lo, hi = corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)
    org = rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), size=(n, 3))
    target = corners[rng.integers(0, len(corners), n)].mean(axis=1)
    dirs = (target - org) * rng.uniform(0.2, 5.0, size=(n, 1))
    reach = np.linalg.norm(target - org, axis=1) / np.linalg.norm(dirs, axis=1)  # t at the target
    tmin = np.where(rng.random(n) < 0.3, rng.uniform(0, 1.5, n) * reach, 0)
    tmax = np.where(rng.random(n) < 0.5, tmin + rng.uniform(0, 2.0, n) * reach, np.inf)
    dead = rng.random(n) < 0.05
    tmax[dead] = tmin[dead] - 1
    point = rng.random(n) < 0.03
    tmax[point] = tmin[point]
    tmax[0] = np.nan
    org, dirs = org.astype(np.float32), dirs.astype(np.float32)
    return RayBatch(org, dirs, safe_inverse(dirs), tmin.astype(np.float32), tmax.astype(np.float32),
                    np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), "reflection")


def test_driver_answers_exactly_as_the_oracle(whitted):
    tris = whitted.triangles
    rays = segment_batch(tris, 4000, seed=5)
    driver, oracle = Open3DTraversal(tris, threads=2), Open3DOracle(tris, threads=2)
    hits = empty_hits(4000)
    hits.prim[:] = 77  # stale answers must not survive
    driver.intersect(None, tris, rays, None, None, hits, None)
    theirs = oracle.intersect(rays)
    assert (theirs.prim >= 0).sum() > 1000
    for field in ("t", "prim", "u", "v"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(theirs, field), err_msg=field)
    occluded = np.ones(4000, np.bool_)
    driver.occluded(None, tris, rays, None, None, occluded, None)
    expected = oracle.occluded(rays)
    assert expected.sum() > 500 and (~expected).sum() > 500
    np.testing.assert_array_equal(occluded, expected)
    live = rays.tmin <= rays.tmax
    assert not occluded[~live].any() and (hits.prim[~live] == -1).all()
    with pytest.raises(ValueError):
        driver.occluded(None, tris, rays, None, None, np.zeros(3999, np.bool_), None)


@pytest.fixture(scope="module")
def recorded(whitted):
    """(renderer, recorder, reference answers) of a small Whitted frame with every ray kind."""
    from engine.render.config import Config, RenderConfig
    from engine.render.whitted import WhittedRenderer

    config = Config(render=RenderConfig(width=32, height=32, max_depth=3, packet=8))
    recorder = bench.BatchRecorder()
    renderer = WhittedRenderer(whitted, config, observer=recorder)
    renderer.render()
    renderer.observer = None
    return renderer, recorder, bench.ReferenceAnswers().get(renderer, recorder)


def test_replays_are_checked_and_wrong_answers_caught(recorded):
    renderer, recorder, reference = recorded
    yardstick = Open3DYardstick()
    runs, answers = yardstick.seconds(renderer, recorder, 2, bench.timed_replays)
    assert len(runs) == 2 and all(run[k] > 0 for run in runs for k in RAY_KINDS)
    assert yardstick.seconds(renderer, recorder, 2, bench.timed_replays)[0] is runs  # once per batch set
    tracer = yardstick.tracer(renderer)
    good = bench.check_answers(recorder.batches, answers, reference, tracer, renderer.tris)
    for k in RAY_KINDS:
        assert good[k]["checked"] > 0 and good[k]["mismatches"] == 0, (k, good[k])
    tampered = []
    for (kind, query, rays, packets), answer in zip(recorder.batches, answers):
        if query == "intersect":
            hit = np.flatnonzero(answer.prim >= 0)[:3]
            answer = answer._replace(prim=answer.prim.copy(), t=answer.t.copy())
            answer.prim[hit] = (answer.prim[hit] + 11) % renderer.tris.v0.shape[0]
            answer.t[hit] *= 0.5
        else:
            answer = ~answer & (rays.tmin <= rays.tmax)
        tampered.append(answer)
    bad = bench.check_answers(recorder.batches, tampered, reference, tracer, renderer.tris)
    assert bad["primary"]["mismatches"] == 3 and bad["shadow"]["mismatches"] > 0
    rates = open3d_rates({k: 1.0 for k in (*RAY_KINDS, "all")}, bad)
    assert rates["shadow"] is None and rates["all"] is None  # every shadow answer flipped: dropped
    assert open3d_rates({k: 1.0 for k in (*RAY_KINDS, "all")}, good)["all"] == 1.0
    yardstick.close()


def test_a_few_disagreeing_rays_keep_open3ds_rate_many_drop_it():
    def check(mismatches, checked=100_000):
        row = {"checked": checked, "ties": 0, "mismatches": 0}
        return {"primary": dict(row, mismatches=mismatches), "shadow": row, "reflection": row, "refraction": row}

    rates = {k: 2.0 for k in (*RAY_KINDS, "all")}
    few = int(OPEN3D_MISMATCH_TOLERANCE * 100_000)
    assert open3d_rates(rates, check(few)) == rates
    many = open3d_rates(rates, check(few + 1))
    assert many["primary"] is None and many["all"] is None and many["shadow"] == 2.0
    # Ours and Embree drop a kind on a single mismatch.
    assert bench._checked(rates, check(1))["primary"] is None


MATRIX = """
name = "t"
repeat = 1
{extra}
[axes]
scene = ["whitted"]
traversal = ["single"]
frustum = ["none"]
packet = [8]
recursion = ["primary"]
resolution = [16]
"""


def test_matrix_key_is_strict_and_follows_embree_by_default(tmp_path, capsys):
    import tomllib

    def parsed(extra):
        return parse_matrix(tomllib.loads(MATRIX.format(extra=extra)), "m.toml")

    assert parsed("").cells[0].open3d and parsed("").open3d
    assert not parsed("embree = false").cells[0].open3d
    assert parsed("embree = false\nopen3d = true").cells[0].open3d
    off = parsed("open3d = false")
    assert not off.cells[0].open3d and "open3d" not in off.cells[0].identity()
    assert parsed("").cells[0].key != off.cells[0].key  # a cell measured without Open3D is not done
    path = tmp_path / "bad.toml"
    path.write_text(MATRIX.format(extra='open3d = "yes"'))
    assert main(["bench", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "open3d: must be true or false" in err and err.count("\n") == 1


def test_missing_open3d_stops_the_run_before_any_work(tmp_path, monkeypatch, capsys):
    import validation.open3d_oracle as oracle

    def unavailable():
        raise Open3DUnavailable("the open3d oracle cannot load Open3D: the shared library libusb-1.0.so.0 is missing")

    def refuse(*args, **kwargs):
        raise AssertionError("a cell ran without Open3D")

    monkeypatch.setattr(oracle, "load_open3d", unavailable)
    monkeypatch.setattr(bench, "run_cell", refuse)
    path = tmp_path / "m.toml"
    path.write_text(MATRIX.format(extra=""))
    assert main(["bench", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "libusb-1.0.so.0" in err and "open3d = false" in err and str(path) in err


def test_timed_replays_answer_into_the_same_arrays_each_time(recorded):
    """Replays trace into arrays made once, before the timing (as a frame's renderer keeps its
    answers), and answer what a replay into new arrays answers; stale values are overwritten."""
    renderer, recorder, _ = recorded
    fresh = bench.replay(recorder.batches, renderer.tracer)[1]
    kept = bench.answer_arrays(recorder.batches)
    for answer in kept:  # stale answers that a replay must not leave behind
        if isinstance(answer, np.ndarray):
            answer.fill(True)
        else:
            answer.prim.fill(7)
    _, first = bench.replay(recorder.batches, renderer.tracer, answers=kept)
    _, second = bench.replay(recorder.batches, renderer.tracer, answers=kept)
    for a, b, c, k in zip(fresh, first, second, kept):
        assert b is k and c is k
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            for field in ("t", "prim", "u", "v"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    runs, answers = bench.timed_replays(recorder.batches, renderer.tracer, 2)
    assert len(runs) == 2 and len(answers) == len(recorder.batches)
