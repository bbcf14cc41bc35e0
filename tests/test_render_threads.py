"""Renderers and the benchmark runner hold their thread count for their own work only.

``[render] threads`` used to be set process-wide when a ``WhittedRenderer`` was made
(``numba.set_num_threads`` in its constructor), so every numba kernel the caller ran after it,
another renderer's included, ran at that count. Now the renderer's methods, the animation
renderer's and a benchmark cell run inside ``engine.core.threads`` and give the caller's count
back."""
from dataclasses import replace

import numba
import pytest

import engine.bench.runner as runner
from engine.bench.machine import machine_info
from engine.bench.matrix import load_matrix
from engine.render.animation import AnimationRenderer
from engine.render.config import Config, with_overrides
from engine.render.whitted import WhittedRenderer
from scenes.catalog import load_named
from tests.test_bench import SMOKE

pytestmark = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")


def callers_count_other_than(threads):
    """Sets numba's count to one the render does not use (``threads``: the render's, 0 = all)
    and returns it, so a count the render left behind shows."""
    mine = 1 if threads == 0 else numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(mine)
    return mine


@pytest.fixture(autouse=True)
def restore_count():
    before = numba.get_num_threads()
    yield
    numba.set_num_threads(before)


def config(threads):
    return with_overrides(Config(), size=(32, 24), depth=2, threads=threads)  # the default traversals


class CountSeen:
    """Observer: numba's thread count at every traced batch."""

    def __init__(self):
        self.seen = set()

    def __call__(self, *args, **kwargs):
        self.seen.add(numba.get_num_threads())


@pytest.mark.parametrize("threads", [0, 1])
def test_whitted_renderer_traces_at_its_count_and_leaves_the_callers(threads):
    callers_count = callers_count_other_than(threads)
    seen = CountSeen()
    renderer = WhittedRenderer(load_named("whitted"), config(threads), observer=seen)
    assert numba.get_num_threads() == callers_count  # making it sets nothing
    renderer.warm_up()
    assert numba.get_num_threads() == callers_count
    renderer.with_counters(renderer.render())
    assert numba.get_num_threads() == callers_count
    renderer.set_scene(load_named("whitted"))
    assert numba.get_num_threads() == callers_count
    assert seen.seen == {threads or numba.config.NUMBA_NUM_THREADS}
    assert renderer.threads == (threads or numba.config.NUMBA_NUM_THREADS)


class StillPath:
    """An animation path whose scene never moves (all ``AnimationRenderer`` reads of a path:
    its range, which the warm-up places the scene at both ends of, and ``scene_at``)."""

    start, end = 0.0, 1.0

    def scene_at(self, time):
        return load_named("whitted")


def test_animation_frames_run_at_their_count_and_leave_the_callers():
    callers_count = callers_count_other_than(1)
    seen = CountSeen()
    animator = AnimationRenderer(StillPath(), config(1), observer_for=lambda scene, bvh: seen)
    animator.warm_up(0.0)
    assert numba.get_num_threads() == callers_count
    frame = animator.frame(0, 0.0)
    assert numba.get_num_threads() == callers_count
    animator.compare_with_fresh_tree(frame, repeat=1)
    animator.render_with_fresh_tree(lambda scene, bvh: seen)
    assert numba.get_num_threads() == callers_count
    assert seen.seen == {1}


def test_a_benchmark_cell_measures_at_its_count_and_leaves_the_callers(monkeypatch):
    callers_count = callers_count_other_than(1)
    replayed_at = []
    real = runner.timed_replays

    def timed_replays(*args, **kwargs):
        replayed_at.append(numba.get_num_threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(runner, "timed_replays", timed_replays)
    cell = replace(load_matrix(str(SMOKE)).cells[0], threads=1)
    yardstick = runner.EmbreeYardstick()
    try:
        record = runner.run_cell(cell, 1, runner.SceneCache(), yardstick, machine_info(), "smoke")
    finally:
        yardstick.close()
    assert numba.get_num_threads() == callers_count
    assert replayed_at and set(replayed_at) == {1}
    assert record["threads"] == 1


def test_stats_record_the_threads_the_kernels_ran_on(tmp_path):
    """Before: with NUMBA_NUM_THREADS=1 and threads = 2 the --stats document said only 2 (the
    config's), though every kernel ran on one thread."""
    import json
    import subprocess
    import sys

    stats = tmp_path / "s.json"
    env = {**__import__("os").environ, "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "engine.cli", "render", "--size", "16x16", "--depth", "1",
                           "--threads", "2", "--stats", str(stats), "-o", str(tmp_path / "x.png")],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr
    document = json.loads(stats.read_text())
    assert document["threads"] == 1 and document["config"]["render"]["threads"] == 2
