"""Shadow rays walked from either end (``engine.render.shadow_order``): the far-child-first walk
gives the same occlusion answers with other node visits, every walk counts its visits as the
instrumented kernel does, a trial walks every packet once, ``ShadowOrder`` decides by counted
visits per (light, kind), and renders are the same image whichever end is chosen."""
from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np
import pytest

from engine.core.errors import ConfigError
from engine.core.types import Hits, new_stats, stats_totals
from engine.packet.plugin import live_rays_of, walk_batch
from engine.packet.strategies import STRATEGIES
from engine.render import config as cfg
from engine.render.plugins import make_frustum, make_traversal
from engine.render.shadow_order import MARGIN, TRIAL_RAYS, ShadowOrder
from engine.render.whitted import WhittedRenderer
from packet_raysets import scene_rays
from scenes.catalog import scene_from_config
from scenes.whitted import whitted_scene


@pytest.fixture(scope="module")
def shadows():
    """(SceneRays, RayBatch, Packets, Frusta) of the default scene's shadow rays, 16x16 packets."""
    setup = scene_rays(whitted_scene([], {}, 0.0), 96, 96)
    rays, packets = setup.rays["shadow"].batch(setup.width, setup.height, 16)
    frusta = make_frustum("pointlight").build(rays, packets, setup.bounds)
    return setup, rays, packets, frusta


def walk(strategy, setup, rays, packets, frusta, from_end, counters=None):
    """(hits, visits i64[threads]) of an any-hit walk from the surface or the far end."""
    n = rays.org.shape[0]
    hits = Hits(np.empty(n, np.float32), np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32))
    visits = np.zeros(numba.config.NUMBA_NUM_THREADS, np.int64)
    walk_batch(strategy, setup.bvh, setup.tris, rays, packets, frusta, True, *hits, counters, from_end=from_end,
               visits=visits)
    return hits, visits


@pytest.mark.parametrize("name", ["ranged", "partition", "masked", "simd"])
def test_walking_from_the_far_end_answers_the_same_with_other_visits(shadows, name):
    setup, rays, packets, frusta = shadows
    near_hits, near_visits = walk(STRATEGIES[name], setup, rays, packets, frusta, False)
    far_hits, far_visits = walk(STRATEGIES[name], setup, rays, packets, frusta, True)
    assert np.array_equal(near_hits.prim >= 0, far_hits.prim >= 0)
    assert 0.05 < np.mean(near_hits.prim >= 0) < 0.95  # blocked and free rays both occur
    # The order changed: some blocked ray stopped at another blocker, and the counts moved.
    assert not np.array_equal(near_hits.t, far_hits.t)
    assert near_visits.sum() != far_visits.sum()


def test_walking_from_the_far_end_agrees_with_embree(shadows):
    # Ground truth on the same real shadow rays: every live ray's occlusion agrees with Embree's
    # or is a tie (an occluder grazed at an edge or a segment end), as the audits count them.
    from engine.render.tracer import Tracer
    from validation.compare import compare_occlusion
    from validation.oracle import EmbreeOracle

    setup, rays, packets, frusta = shadows
    oracle = EmbreeOracle(setup.tris)
    reference = oracle.occluded(rays)
    tracer = Tracer(setup.bvh, setup.tris, setup.bounds, {"shadow": make_traversal("partition")},
                    {"shadow": make_frustum("pointlight")})
    for name in ("ranged", "partition", "masked", "simd", "auto"):
        hits, _ = walk(STRATEGIES[name], setup, rays, packets, frusta, True)
        ours = hits.prim >= 0
        closest = tracer.trace("shadow", "intersect", rays, packets)
        comparison = compare_occlusion(rays, ours, reference, setup.tris, closest, oracle.intersect(rays))
        assert not comparison.mismatch.any(), name
        assert comparison.agree.sum() > 0.99 * np.count_nonzero(rays.tmin <= rays.tmax), name


def test_every_walk_counts_the_visits_the_instrumented_walk_counts(shadows):
    setup, rays, packets, frusta = shadows
    for from_end in (False, True):
        stats = new_stats(numba.get_num_threads())
        _, counted = walk(STRATEGIES["partition"], setup, rays, packets, frusta, from_end, stats.counters)
        _, plain = walk(STRATEGIES["partition"], setup, rays, packets, frusta, from_end)
        assert counted.sum() == plain.sum() == stats_totals(stats)["nodes"] > 0


@pytest.mark.parametrize("name", ["partition", "auto"])
def test_a_trial_walks_every_packet_once_from_alternate_ends(shadows, name):
    setup, rays, packets, frusta = shadows
    plugin = make_traversal(name)
    plain = np.zeros(rays.org.shape[0], np.bool_)
    plugin.occluded(setup.bvh, setup.tris, rays, packets, frusta, plain, None)
    tried, trial = np.zeros_like(plain), {}
    stats = new_stats(numba.get_num_threads())
    plugin.occluded(setup.bvh, setup.tris, rays, packets, frusta, tried, stats, False, trial)
    assert np.array_equal(plain, tried)
    # Each end walked half the packets (groups 0 and 3 from the surface, 1 and 2 from the light).
    offsets = np.ascontiguousarray(packets.offsets, np.int32)
    group = np.arange(len(offsets) - 1) % 4
    from_light = np.where((group == 1) | (group == 2), 0, -1).astype(np.int8)
    assert trial["light"][1] == live_rays_of(rays.tmin, rays.tmax, offsets, from_light)
    assert trial["surface"][1] + trial["light"][1] == np.count_nonzero(rays.tmin <= rays.tmax)
    assert trial["surface"][0] + trial["light"][0] == stats_totals(stats)["nodes"] > 0
    if name == "auto":  # every packet's strategy counted once
        assert sum(stats.extra["auto"]["packets"].values()) == len(offsets) - 1


def test_shadow_order_decides_by_visits_per_ray_per_light_and_kind():
    order = ShadowOrder("auto")
    assert order.wants_trial(0, "primary") and not order.from_light(0, "primary")
    half = TRIAL_RAYS // 2
    order.add_trial(0, "primary", {"surface": (100 * half, half), "light": (10 * half, half)})
    assert order.wants_trial(0, "primary")  # not enough rays yet: still the surface
    order.add_trial(0, "primary", {})       # nothing learnt from an empty trial
    order.add_trial(0, "primary", {"surface": (100 * half, half), "light": (10 * half, half)})
    assert not order.wants_trial(0, "primary") and order.from_light(0, "primary")
    # Within the margin the surface stays; each (light, kind) decides alone.
    close = (1.0 - MARGIN / 2) * TRIAL_RAYS
    order.add_trial(0, "reflection", {"surface": (TRIAL_RAYS, TRIAL_RAYS), "light": (close, TRIAL_RAYS)})
    order.add_trial(1, "primary", {"surface": (TRIAL_RAYS, TRIAL_RAYS), "light": (3 * TRIAL_RAYS, TRIAL_RAYS)})
    assert order.chosen() == {"0/primary": "light", "0/reflection": "surface", "1/primary": "surface"}
    assert not order.wants_trial(0, "reflection")


@pytest.mark.parametrize("mode, from_light", [("surface", False), ("light", True)])
def test_fixed_orders_never_try(mode, from_light):
    order = ShadowOrder(mode)
    assert not order.wants_trial(0, "primary") and order.from_light(0, "primary") is from_light
    with pytest.raises(ValueError):
        ShadowOrder("middle")


def test_renders_are_the_same_image_from_either_end_and_auto_chooses_alike_twice():
    config = cfg.Config()
    scene = scene_from_config(config.scene, "none")
    images, chosen = {}, []
    for mode in ("surface", "light", "auto", "auto"):
        renderer = WhittedRenderer(scene, replace(config, render=replace(config.render, shadow_order=mode)))
        result = renderer.render()  # 512x512: enough shadow rays of reflection hits to decide
        images.setdefault(mode, result.image)
        assert np.array_equal(result.image, images["surface"])
        if mode == "auto":
            chosen.append(result.shadow_order)
    # The default scene's reflection and refraction hits cast shadow rays that are cheaper from
    # the light (see the README), and the choice is counted, not timed: the same both times.
    assert chosen[0] == chosen[1]
    assert chosen[0].get("0/reflection") == "light"


def test_config_checks_the_shadow_order(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[render]\nshadow_order = "light"\n')
    assert cfg.load(str(path)).render.shadow_order == "light"
    path.write_text('[render]\nshadow_order = "middle"\n')
    with pytest.raises(ConfigError, match="shadow_order"):
        cfg.load(str(path))


def test_the_benchmark_replays_shadow_batches_from_the_end_the_renderer_walks_them():
    from engine.bench.runner import BatchRecorder, replay

    config = cfg.Config()
    config = replace(config, render=replace(config.render, shadow_order="light", width=128, height=128))
    recorder = BatchRecorder()
    renderer = WhittedRenderer(scene_from_config(config.scene, "none"), config, observer=recorder)
    renderer.render()
    kinds = [batch[0] for batch in recorder.batches]
    assert "shadow" in kinds
    assert recorder.from_end == [kind == "shadow" for kind in kinds]
    seen = []
    tracer = renderer.tracer
    original = tracer.trace

    def trace(*args, **kwargs):
        seen.append(kwargs.get("from_end", False))
        return original(*args, **kwargs)

    tracer.trace = trace
    replay(recorder.batches, tracer, recorder.from_end)
    assert seen == recorder.from_end


def test_stats_count_the_first_frame_whatever_followed_it(tmp_path, capsys):
    """The counting pass replays the first frame from the shadow order it began with: its
    counters and ``extra.shadow_order`` do not depend on --repeat (the trials of later frames
    changed which end the counting pass walked, so the counters moved with --repeat)."""
    import json

    from engine.cli import main

    seen = []
    for repeat in ("0", "1", "2"):
        stats = tmp_path / f"r{repeat}.json"
        assert main(["render", "--size", "256x256", "--repeat", repeat, "--stats", str(stats),
                     "-o", str(tmp_path / "x.png")]) == 0
        doc = json.loads(stats.read_text())
        seen.append((doc["counters"]["ray_aabb"]["shadow"], doc["extra"]["shadow_order"]))
    assert seen[0] == seen[1] == seen[2]
    assert seen[0][1]["0/primary"] in ("surface", "light", "undecided") and len(seen[0][1]) == 3


@pytest.mark.parametrize("mode", ["surface", "light"])
def test_stats_name_a_fixed_end_and_no_end_for_traversals_that_ignore_it(tmp_path, mode):
    for traversal, expected in (("partition", mode), ("embree", None)):
        config = cfg.with_overrides(cfg.Config(), size=(64, 64), traversal=[traversal])
        config = replace(config, render=replace(config.render, shadow_order=mode))
        renderer = WhittedRenderer(scene_from_config(config.scene, config.override), config)
        ends = renderer.render().shadow_order
        if expected is None:
            assert ends == {}
        else:
            assert ends and set(ends.values()) == {expected}
