"""The numba frame pipeline against the numpy loop it replaced.

Camera batches and child batches must come out in exactly the layout ``make_batch`` gives
(packet composition decides traversal order and so ties; the image's float sums depend on the
order of a pixel's contributions), and whole images must be bit-identical to the numpy
reference (``tests/numpy_whitted.py``) on scenes with shadows, textures, mirrors and glass.
"""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from engine.core.scratch import Scratch
from engine.core.types import Packets, RayBatch, copied_batch
from engine.packet.compact import compact_into_packets
from engine.packet.layout import make_batch
from engine.render.camera import camera_batch, camera_rays
from engine.render.config import from_dict
from engine.render import whitted
from engine.render.whitted import WhittedRenderer
from scenes.catalog import load_named
from numpy_whitted import render_reference
from engine.core.types import RAY_KINDS

LIVE_FIELDS = ("org", "dir", "inv_dir", "tmin", "tmax", "pixel", "weight")


@pytest.fixture(scope="module")
def scene_named():
    """``load_named`` once per scene for this file (building a scene costs more than rendering
    it at these sizes): renderers and the numpy reference only read a Scene."""
    loaded = {}

    def load(name):
        if name not in loaded:
            loaded[name] = load_named(name)
        return loaded[name]

    return load


def assert_same_layout(got, want):
    """Two (RayBatch, Packets): equal packets and lanes (a dead lane's origin is free)."""
    (rays, packets), (ref, ref_packets) = got, want
    assert np.array_equal(packets.offsets, ref_packets.offsets)
    live = ref.pixel >= 0
    assert np.array_equal(rays.pixel >= 0, live)
    for name in LIVE_FIELDS:
        a, b = getattr(rays, name), getattr(ref, name)
        assert a.dtype == b.dtype and np.array_equal(a[live], b[live]), name
        if name != "org":
            assert np.array_equal(a[~live], b[~live]), name


@pytest.mark.parametrize("width,height,n", [(37, 21, 2), (37, 21, 4), (64, 48, 8), (64, 48, 16), (20, 33, 32)])
def test_camera_batch_is_make_batch_of_camera_rays(scene_named, width, height, n):
    scene = scene_named("whitted")
    org, d = camera_rays(scene, width, height)
    count = width * height
    want = make_batch("primary", org, d, np.zeros(count), np.full(count, np.inf), np.arange(count, dtype=np.int32),
                      np.ones((count, 3)), width, height, n)
    assert_same_layout(camera_batch(scene, width, height, n), want)


def _parent(rng, width, height, n, count):
    """A parent batch in packet order with repeated pixels (several rays per pixel)."""
    pixel = rng.integers(0, width * height, count).astype(np.int32)
    d = rng.normal(size=(count, 3)).astype(np.float32)
    d[rng.random(count) < 0.05, 1] = 0  # zero components: the inverse must match too
    return make_batch("reflection", rng.normal(size=(count, 3)), d, np.zeros(count), np.full(count, np.inf), pixel,
                      rng.random((count, 3)), width, height, n)


def assert_compaction_is_a_stable_sort(rng, width, height, n, counts, share):
    """compact_into_packets == make_batch of the flagged lanes of the sources (one parent batch
    of counts[s] rays each, lanes flagged with probability ``share``), concatenated, and every
    child names the parent lane it came from."""
    sources = []
    for count in counts:
        rays, packets = _parent(rng, width, height, n, count)
        count = rays.pixel.shape[0]
        flag = (rng.random(count) < share) & (rays.pixel >= 0)
        sources.append((packets.offsets, rays.pixel, flag, rng.normal(size=(count, 3)).astype(np.float32),
                        rays.dir, (rng.random(count) * 9).astype(np.float32), rays.weight))
    columns = [tuple(s[i] for s in sources) for i in range(7)]
    offsets, org, d, inv, tmin, tmax, pixel, weight, source, lane = compact_into_packets(n, width, height, *columns)
    pick = lambda i: np.concatenate([s[i][s[2]] for s in sources])  # noqa: E731
    want = make_batch("reflection", pick(3), pick(4), np.zeros(len(pick(1))), pick(5), pick(1), pick(6),
                      width, height, n)
    got = (RayBatch(org, d, inv, tmin, tmax, pixel, weight, "reflection"), Packets(offsets, n, width, height))
    assert_same_layout(got, want)
    live = pixel >= 0
    for s, (_, src_pixel, flag, src_org, *_rest) in enumerate(sources):
        mine = live & (source == s)
        assert flag[lane[mine]].all() and mine.sum() == flag.sum()
        assert np.array_equal(org[mine], src_org[lane[mine]]) and np.array_equal(pixel[mine], src_pixel[lane[mine]])
    assert (lane[~live] == -1).all() and (source[~live] == -1).all()


@pytest.mark.parametrize("n_sources", [1, 2, 4])
@pytest.mark.parametrize("n", [2, 8, 16])
def test_children_stay_in_their_tile_in_the_order_of_a_stable_sort(n_sources, n):
    rng = np.random.default_rng(n_sources * 100 + n)
    assert_compaction_is_a_stable_sort(rng, 45, 38, n, [900 + 300 * s for s in range(n_sources)], 0.6)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), width=st.integers(1, 300), height=st.integers(1, 120),
       n=st.sampled_from([2, 4, 8, 16, 32]), counts=st.lists(st.integers(0, 1500), min_size=1, max_size=4),
       share=st.sampled_from([0.0, 0.05, 0.5, 1.0]))
def test_compaction_of_any_image_packet_size_and_sparsity_is_a_stable_sort(seed, width, height, n, counts, share):
    """Planning merges the sources' packets in parallel over ranges of the image's tiles (each
    range finds its first packet per source by binary search): images from one tile to thousands,
    sources without packets, nearly empty ones and full ones, every packet size."""
    assert_compaction_is_a_stable_sort(np.random.default_rng(seed), width, height, n, counts, share)


def test_no_flagged_lane_gives_an_empty_batch():
    rng = np.random.default_rng(3)
    rays, packets = _parent(rng, 16, 16, 4, 50)
    none = np.zeros(rays.pixel.shape[0], np.bool_)
    out = compact_into_packets(4, 16, 16, (packets.offsets,), (rays.pixel,), (none,), (rays.org,), (rays.dir,),
                               (rays.tmax,), (rays.weight,))
    assert out[0].tolist() == [0] and out[1].shape == (0, 3)


def _columns(rng, width, height, n, counts, share):
    """Compaction sources: one parent batch per entry of ``counts`` (rays), each lane flagged
    with probability ``share``."""
    sources = []
    for count in counts:
        rays, packets = _parent(rng, width, height, n, count)
        flag = (rng.random(rays.pixel.shape[0]) < share) & (rays.pixel >= 0)
        sources.append((packets.offsets, rays.pixel, flag, rays.org, rays.dir, rays.tmax, rays.weight))
    return [tuple(s[i] for s in sources) for i in range(7)]


@pytest.mark.parametrize("n", [2, 16])
def test_compaction_into_reused_buffers_equals_compaction_into_fresh_arrays(n):
    """The renderer's Scratch hands back the last call's buffers (the plan's per-tile arrays
    too): a dense compaction, then sparse ones of other source counts, then a dense one again
    must each equal the same compaction into new arrays."""
    rng = np.random.default_rng(7 + n)
    scratch = Scratch()
    width, height = 61, 43
    for counts, share in (((2500, 1800), 0.9), ((40,), 0.5), ((30, 25, 60, 12), 0.3), ((9,), 1.0),
                          ((2600, 2000), 0.8)):
        columns = _columns(rng, width, height, n, counts, share)
        fresh = compact_into_packets(n, width, height, *columns)
        reused = compact_into_packets(n, width, height, *columns, allocate=scratch.allocator("kind"))
        live = fresh[6] >= 0
        assert np.array_equal(fresh[0], reused[0])
        for a, b in zip(fresh[1:], reused[1:]):
            assert np.array_equal(a[live], b[live])


def test_parent_packets_out_of_tile_order_are_refused():
    """Planning merges the sources' packets by tile, which needs them in tile order (as
    ``make_batch`` and the compaction make them); a batch whose packets are not is an error,
    not a silently wrong merge."""
    rng = np.random.default_rng(11)
    rays, packets = _parent(rng, 32, 32, 4, 600)
    offsets = packets.offsets
    assert offsets.shape[0] > 3
    # The first two packets swapped: their lanes moved, the offsets rebuilt.
    first, second = np.arange(offsets[0], offsets[1]), np.arange(offsets[1], offsets[2])
    order = np.r_[second, first, np.arange(offsets[2], offsets[-1])]
    swapped = offsets.copy()
    swapped[1] = offsets[0] + len(second)
    flag = rays.pixel[order] >= 0
    with pytest.raises(ValueError, match="tile order"):
        compact_into_packets(4, 32, 32, (swapped,), (rays.pixel[order],), (flag,), (rays.org[order],),
                             (rays.dir[order],), (rays.tmax[order],), (rays.weight[order],))


def _config(traversal, **render):
    return from_dict({"render": {"threads": 2, **render}, "traversal": dict.fromkeys(RAY_KINDS, traversal)})


@pytest.mark.parametrize("packet,traversal", [(4, "masked"), (16, "partition"), (2, "simd"), (8, "embree")])
def test_whitted_scene_image_is_bit_identical_to_the_numpy_loop(scene_named, packet, traversal):
    config = _config(traversal, width=53, height=41, packet=packet)
    renderer = WhittedRenderer(scene_named("whitted"), config)
    image = renderer.render().image
    assert np.array_equal(image, render_reference(renderer, 53, 41))


@pytest.mark.parametrize("name", ["bart-kitchen", "cornell-box", "bunny"])
def test_real_scene_images_are_bit_identical_to_the_numpy_loop(shared_scenes, scene_named, name):
    """Textures, interpolated normals, glass with total internal reflection (the kitchen)."""
    scene = scene_named(name)
    config = _config("ranged", width=96, height=80, packet=8, max_depth=4, max_reflection_depth=1)
    renderer = WhittedRenderer(scene, config)
    result = renderer.render()
    assert result.rays["shadow"] > 0
    if name == "bart-kitchen":
        assert result.rays["reflection"] > 0 and result.rays["refraction"] > 0
    assert np.array_equal(result.image, render_reference(renderer, 96, 80))


def test_frames_reuse_their_arrays_without_changing_the_image(scene_named):
    """The renderer keeps per-lane arrays between frames: a later frame (of another size in
    between) gives the same image and leaves an earlier result's image alone."""
    renderer = WhittedRenderer(scene_named("whitted"), _config("partition", width=40, height=36, packet=8))
    first = renderer.render()
    kept = first.image.copy()
    renderer.render(size=(72, 50))  # grows every buffer
    again = renderer.render()
    assert np.array_equal(again.image, kept) and np.array_equal(first.image, kept)
    assert renderer.scratch.nbytes() > 0


@pytest.mark.parametrize("traversal,packet", [("partition", 8), ("simd", 2), ("embree", 8)])
def test_shadow_rays_walked_in_their_lanes_give_the_compacted_image(monkeypatch, scene_named, traversal, packet):
    """Shadow rays walked in their parent batch's own lanes (forced here for every light) give
    the image of the same rays compacted into packets (never in place), bit for bit, through a
    packet walk, the 2x2 SIMD baseline and Embree (kernels this file compiles anyway: the
    ray-space hierarchy would add 15 s of compiling to a cold run); in place, the shadow batch is
    the parent's lanes and packets, its unlit lanes dead, every lane a finite ray."""
    images = {}
    for in_place in (True, False):
        monkeypatch.setattr(whitted, "IN_PLACE_SHADOWS", 0.0 if in_place else 2.0)
        seen = []
        renderer = WhittedRenderer(scene_named("whitted"), _config(traversal, width=45, height=38, packet=packet),
                                   observer=lambda kind, query, rays, packets, answer: seen.append(
                                       (kind, query, *copied_batch(rays, packets), packets)))
        images[in_place] = renderer.render().image
        shadows = 0
        for parent, shadow in zip(seen, seen[1:]):
            if shadow[0] != "shadow" or parent[0] == "shadow":
                continue
            shadows += 1
            assert (shadow[4] is parent[4]) == in_place  # the parent's own Packets
            rays = shadow[2]
            live = rays.tmin <= rays.tmax
            assert np.isfinite(rays.org).all() and np.isfinite(rays.inv_dir).all()
            if in_place:
                assert rays.org.shape == parent[2].org.shape and not live.all()
            else:
                assert live[rays.pixel >= 0].all()  # compacted: only padding is dead
        assert shadows > 0
    assert np.array_equal(images[True], images[False])


def test_the_gpu_image_checks_recorder_keeps_only_cast_rays(monkeypatch, scene_named):
    """``engine.bench.gpu_pixels.PixelRecorder`` lists a pixel's rays to explain a GPU/CPU image
    difference: the dead lanes of a shadow batch walked in place are no rays of that pixel."""
    from engine.bench.gpu_pixels import PixelRecorder

    monkeypatch.setattr(whitted, "IN_PLACE_SHADOWS", 0.0)
    recorder, live = PixelRecorder(), []

    def observe(kind, query, rays, packets, answer):
        recorder(kind, query, rays, packets, answer)
        if kind == "shadow":
            live.append(int(np.count_nonzero(rays.tmin <= rays.tmax)))

    renderer = WhittedRenderer(scene_named("whitted"), _config("partition", width=40, height=32, packet=8),
                               observer=observe)
    result = renderer.render()
    recorded = sum(len(record[0]) for record in recorder.batches["shadow"])
    assert recorded == sum(live) == result.rays["shadow"] > 0


def test_shadow_rays_in_place_or_compacted_give_the_same_image(monkeypatch, scene_named):
    """A light's shadow rays are walked in their parent batch's lanes when enough of them are
    lit (``IN_PLACE_SHADOWS``), else compacted into packets of their own: either way the image
    is the same, bit for bit."""
    config = _config("partition", width=61, height=47, packet=8)
    images = []
    for fraction in (0.0, 1.01):  # every batch in place; every batch compacted
        monkeypatch.setattr(whitted, "IN_PLACE_SHADOWS", fraction)
        images.append(WhittedRenderer(scene_named("whitted"), config).render().image)
    assert np.array_equal(images[0], images[1])


@pytest.mark.parametrize("name, can_spawn", [("cornell-box", False), ("erw6", False), ("whitted", True)])
def test_scenes_that_cannot_cast_children_skip_the_spawn_step_with_the_same_image(scene_named, name, can_spawn):
    """Without a reflecting or transmitting material no hit casts a child ray, so the renderer
    skips the spawn step (``MaterialTable.can_spawn``); the image is the one the full step gives."""
    if name == "cornell-box":  # read from the shared scene folder; the others are procedural
        from conftest import needs_shared_scenes
        needs_shared_scenes()
    config = _config("partition", width=48, height=40, packet=8)
    renderer = WhittedRenderer(scene_named(name), config)
    assert renderer.materials.can_spawn is can_spawn
    skipped = renderer.render().image
    renderer.materials.can_spawn = True
    assert np.array_equal(renderer.render().image, skipped)


def test_the_warm_up_compiles_both_shadow_paths_and_leaves_the_first_frame_to_decide(monkeypatch, scene_named):
    """``warm_up`` is what ``packetrt render`` reports as compile time apart from the frames: it
    must reach the in-place and the compacted shadow paths (a real frame's batches may take
    either), run a shadow-order trial, and then forget what that trial learnt."""
    calls = {"in place": 0, "compacted": 0}
    real_in_place, real_compacted = whitted.add_light_in_place, whitted.add_light

    def in_place(*args):
        calls["in place"] += 1
        return real_in_place(*args)

    def compacted(*args):
        calls["compacted"] += 1
        return real_compacted(*args)

    monkeypatch.setattr(whitted, "add_light_in_place", in_place)
    monkeypatch.setattr(whitted, "add_light", compacted)
    renderer = WhittedRenderer(scene_named("whitted"), _config("partition", width=200, height=150, packet=16))
    trials = []
    real_add_trial = renderer.shadow_order.add_trial
    renderer.shadow_order.add_trial = lambda *args: (trials.append(args), real_add_trial(*args))
    renderer.warm_up()
    assert calls["in place"] > 0 and calls["compacted"] > 0, calls
    assert any(trial for _, _, trial in trials)  # some batch had the packets of a trial
    assert renderer.in_place_shadows == whitted.IN_PLACE_SHADOWS
    assert renderer.shadow_order.trials == {} and renderer.shadow_order.wants_trial(0, "primary")
