"""``packetrt show``: the packet traces recorded by the traversal kernel agree with the answers
and counters of the real traversals and with the BVH, the picture's geometry is right, the PNG
shows the packet, its frustum and its nodes, and mistakes are one-line errors."""
import copy
import functools
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from engine.cli import main
from engine.render.config import Config, with_overrides
from engine.debug.packet_trace import CULLED, ENTERED, PACKET_WALKS, rayspace_node, trace_packet
from engine.debug.show import (FRUSTUM, NO_PACKET, RAY_HIT, STRATEGY_COLOURS, build_picture, capture_batch,
                               centre_packet, compose, legend_height, node_colours, packet_tiles)
from engine.packet.strategies import CHOSEN_NAMES
from engine.render.plugins import make_traversal
from engine.core.triangle import slab_test
from engine.core.types import COUNTER_NODES, RAY_KINDS, Frusta, Packets, RayBatch, copied_batch, empty_hits, new_stats
from engine.render import whitted
from engine.render.whitted import WhittedRenderer
from scenes.catalog import scene_from_config

ROOT = Path(__file__).resolve().parents[1]


@functools.cache
def load_scene(scene_config, override="none"):
    """``scene_from_config``, loaded once per process (building the default scene costs more
    than rendering it at 64x64): renderers and ``build_picture`` only read a Scene."""
    return scene_from_config(scene_config, override)


@functools.cache
def render_batches(traversal, frustum=None, size=64, packet=8):
    """(renderer, [(kind, query, rays, packets, answer)]) of one render of the default scene,
    each batch copied as it is cast (the renderer reuses its per-lane arrays within a frame).
    Rendered once per set of arguments and shared by the tests that ask for it: they only read
    the batches and trace packets through the renderer's tracer, which keeps no state."""
    config = with_overrides(Config(), traversal=[traversal], frustum=[frustum] if frustum else [],
                            size=(size, size), packet=packet, depth=2)
    scene = load_scene(config.scene)
    seen = []
    renderer = WhittedRenderer(scene, config, observer=lambda kind, query, rays, packets, answer: seen.append(
        (kind, query, *copied_batch(rays, packets), copy.deepcopy(answer))))
    renderer.render()
    renderer.observer = None  # shared: no later render adds to ``seen``
    return renderer, seen


def every_kind(seen):
    """The first batch of each ray kind."""
    first = {}
    for batch in seen:
        first.setdefault(batch[0], batch)
    assert set(first) == {"primary", "shadow", "reflection", "refraction"}
    return first.values()


def node_parents(bvh):
    """i64[N]: each node's parent (-1 for the root)."""
    parent = np.full(bvh.first.shape[0], -1)
    inner = np.flatnonzero(bvh.count == 0)
    parent[bvh.first[inner]] = inner
    parent[bvh.first[inner] + 1] = inner
    return parent


def leaf_of_triangle(bvh):
    """i32[T]: the leaf holding each triangle (every triangle is in exactly one leaf)."""
    leaf_of = np.full(bvh.prim.shape[0], -1, np.int32)
    for leaf in np.flatnonzero(bvh.count > 0):
        leaf_of[bvh.prim[bvh.first[leaf]:bvh.first[leaf] + bvh.count[leaf]]] = leaf
    assert (leaf_of >= 0).all()
    return leaf_of


@pytest.mark.parametrize("walk", PACKET_WALKS + ("single",))
@pytest.mark.parametrize("frustum", [None, "none"])
def test_recorded_walk_gives_the_real_traversals_hits(walk, frustum):
    """The recorded walk's answers are the plugin's on the whole batch, bit for bit, and the leaf
    holding every hit triangle is one the record says the packet entered, with that triangle
    among those tested there."""
    renderer, seen = render_batches(walk, frustum)
    bvh = renderer.bvh
    leaf_of = leaf_of_triangle(bvh)
    for kind, query, rays, packets, answer in every_kind(seen):
        n_packets = len(packets.offsets) - 1
        for k in range(0, n_packets, max(1, n_packets // 6)):
            start, stop = packets.offsets[k], packets.offsets[k + 1]
            trace = trace_packet(renderer.tracer, kind, rays, packets, k, query == "occluded")
            if query == "intersect":
                assert np.array_equal(trace.prim, answer.prim[start:stop]), (kind, k)
                assert np.array_equal(trace.t, answer.t[start:stop]), (kind, k)
                real = answer.prim[start:stop]
            else:
                assert np.array_equal(trace.prim >= 0, answer[start:stop]), (kind, k)
                real = trace.prim
            entered_leaves = {int(n) for n, o in zip(trace.nodes, trace.outcome) if o == ENTERED and bvh.count[n]}
            assert set(trace.leaves) == entered_leaves
            for tri in real[real >= 0]:
                leaf = int(leaf_of[tri])
                assert leaf in entered_leaves, (kind, k, tri)
                assert tri in trace.leaves[leaf]
            assert (trace.alive <= trace.live).all()
            if frustum == "none":
                assert CULLED not in trace.outcome


def test_recorded_walk_descends_the_tree():
    """Every recorded node but the root is a child of a node entered before it, at its parent's
    depth plus one; a culled or missed node has no live lane counted, an entered one some; the
    root counts the live lanes whose segment meets its box (by the scalar ``slab_test``); a
    packet-wise walk visits each node once."""
    renderer, seen = render_batches("partition")
    bvh = renderer.bvh
    parent = node_parents(bvh)
    for walk in PACKET_WALKS:
        tracer = renderer.tracer.with_traversal({kind: make_traversal(walk) for kind in RAY_KINDS})
        for kind, query, rays, packets, answer in every_kind(seen):
            for k in range(0, len(packets.offsets) - 1, 3):
                trace = trace_packet(tracer, kind, rays, packets, k, query == "occluded")
                lo, hi = packets.offsets[k], packets.offsets[k + 1]
                if not (rays.tmin[lo:hi] <= rays.tmax[lo:hi]).any():
                    # A shadow batch walked in its parent's packets (``IN_PLACE_SHADOWS``) has
                    # packets with no lit lane: nothing to walk, nothing recorded.
                    assert len(trace.nodes) == 0, (walk, kind, k)
                    continue
                if trace.outcome[0] != CULLED:
                    at_root = sum(rays.tmin[r] <= rays.tmax[r] and slab_test(
                        *rays.org[r], *rays.inv_dir[r], rays.tmin[r], rays.tmax[r], bvh.bmin, bvh.bmax, 0) < np.inf
                        for r in range(packets.offsets[k], packets.offsets[k + 1]))
                    assert trace.alive[0] == at_root, (walk, kind, k)
                if walk != "simd":
                    assert trace.pops.sum() == len(trace.nodes)
                seen_at = {}
                for i, (node, depth, outcome, alive) in enumerate(zip(trace.nodes.tolist(), trace.depth.tolist(),
                                                                        trace.outcome, trace.alive.tolist())):
                    if node:
                        up = int(parent[node])
                        assert up in seen_at and trace.outcome[seen_at[up]] == ENTERED, (walk, kind, k, node)
                        assert depth == trace.depth[seen_at[up]] + 1
                    else:
                        assert i == 0 and depth == 0
                    assert (alive > 0) == (outcome == ENTERED), (walk, kind, k, node)
                    seen_at[node] = i


def one_packet(rays, packets, frusta, k):
    """Packet k alone: (RayBatch, Packets, Frusta)."""
    start, stop = packets.offsets[k], packets.offsets[k + 1]
    sliced = RayBatch(*(np.ascontiguousarray(getattr(rays, f)[start:stop]) for f in RayBatch._fields[:-1]), rays.kind)
    return (sliced, Packets(np.array([0, stop - start], np.int32), packets.size, packets.width, packets.height),
            Frusta(frusta.planes[k:k + 1].copy(), frusta.valid[k:k + 1].copy()))


@pytest.mark.parametrize("walk", PACKET_WALKS + ("single",))
def test_recorded_walk_pops_the_nodes_the_kernel_counts(walk):
    """The kernels count every stack pop per BVH depth; run on the packet alone, they count
    exactly what the recorder walked: same order, same decisions, same early exits."""
    renderer, seen = render_batches(walk)
    plugin = make_traversal(walk)
    for kind, query, rays, packets, answer in every_kind(seen):
        frusta = renderer.frustum[kind].build(rays, packets, renderer.bounds)
        n_packets = len(packets.offsets) - 1
        for k in range(0, n_packets, max(1, n_packets // 6)):
            trace = trace_packet(renderer.tracer, kind, rays, packets, k, query == "occluded")
            alone, alone_packets, alone_frusta = one_packet(rays, packets, frusta, k)
            stats = new_stats(numba.get_num_threads())
            if query == "intersect":
                plugin.intersect(renderer.bvh, renderer.tris, alone, alone_packets, alone_frusta,
                                 empty_hits(alone.org.shape[0]), stats)
            else:
                plugin.occluded(renderer.bvh, renderer.tris, alone, alone_packets, alone_frusta,
                                np.zeros(alone.org.shape[0], np.bool_), stats)
            counted = stats.counters[:, COUNTER_NODES].sum(axis=0)
            assert np.array_equal(counted, trace.pops), (kind, k)


def test_partition_rays_only_thin_out_going_down():
    """A partition child never has more rays alive than its parent, and the frusta cull nodes."""
    renderer, seen = render_batches("partition")
    bvh = renderer.bvh
    parent = node_parents(bvh)
    culled = 0
    for kind, query, rays, packets, answer in every_kind(seen):
        for k in range(len(packets.offsets) - 1):
            trace = trace_packet(renderer.tracer, kind, rays, packets, k, query == "occluded")
            alive = dict(zip(trace.nodes.tolist(), trace.alive.tolist()))
            for node, count in alive.items():
                if node:
                    assert count <= alive[int(parent[node])]
            culled += trace.outcome.count(CULLED)
    assert culled > 0


def test_rayspace_node_keeps_every_hit_triangle():
    renderer, seen = render_batches("rayspace", packet=8)
    for kind, query, rays, packets, answer in every_kind(seen):
        if query != "intersect":
            continue
        for k in range(0, len(packets.offsets) - 1, 5):
            node = rayspace_node(renderer.tris, rays, packets, k)
            start, stop = packets.offsets[k], packets.offsets[k + 1]
            hit = answer.prim[start:stop]
            assert np.isin(hit[hit >= 0], node.survivors).all()
            assert node.per_level == sorted(node.per_level, reverse=True)
            assert node.level == 3  # 8x8 tiles


def test_frustum_drawing_holds_the_rays():
    """The drawn frustum's corners lie on its planes and every drawn ray lies inside it."""
    config = with_overrides(Config(), size=(64, 64), packet=8, depth=1)
    scene = load_scene(config.scene)
    for kind in ("primary", "reflection"):
        pic = build_picture(scene, config, kind)
        lines = {name: (pts, seg) for name, pts, seg, _, _ in pic.lines}
        corners = lines["frustum"][0]
        rays = lines["rays"][0]
        # Rebuild the planes from the renderer to test against them.
        renderer = WhittedRenderer(scene, config)
        r, packets, *_ = capture_batch(renderer, kind)
        k = centre_packet(r, packets)
        planes = renderer.frustum[kind].build(r, packets, renderer.bounds).planes[k].astype(np.float64)
        scale = np.abs(rays).max()
        side = corners @ planes[:, :3].T + planes[:, 3]
        assert (np.abs(side).min(axis=1) < 1e-3 * scale).all()  # each corner is on a plane
        inside = rays @ planes[:, :3].T + planes[:, 3]
        assert (inside >= -1e-4 * scale).all()


@pytest.mark.parametrize("kind", ["primary", "reflection"])
def test_auto_picture_colours_packets_by_their_strategy(kind):
    """With ``auto`` the frustum and the packet map show the strategy each packet was walked by:
    the map's tiles are those ``auto`` chooses for the batch, the drawn packet's among them."""
    config = with_overrides(Config(), traversal=["auto"], size=(64, 64), packet=8, depth=2)
    scene = load_scene(config.scene)
    renderer = WhittedRenderer(scene, config)
    pic = build_picture(scene, config, kind, renderer=renderer)
    chosen = pic.summary["auto_choice"]
    assert any(line.startswith(f"auto walked this packet by {chosen}") for line in pic.legend)
    assert pic.tiles.shape == (8, 8, 3)
    tx, ty = pic.tile
    assert tuple(pic.tiles[ty, tx]) == STRATEGY_COLOURS[chosen]
    rays, packets, *_ = capture_batch(renderer, kind)
    frusta = renderer.tracer.frusta_for(kind, rays, packets)
    choices = renderer.tracer.traversal[kind].choose(renderer.bvh, rays, packets, frusta)
    placed = packet_tiles(rays, packets)[:, 0] >= 0  # packets with a live ray have a tile
    drawn = [tuple(c) for c in pic.tiles.reshape(-1, 3) if tuple(c) != NO_PACKET]
    names = list(STRATEGY_COLOURS)
    assert sorted(drawn) == sorted(STRATEGY_COLOURS[names[c]] for c in choices[placed])
    frustum = [line for line in pic.lines if line[0] == "frustum"]
    for _, _, _, colours, _ in frustum:
        assert (colours == STRATEGY_COLOURS[chosen]).all()
    assert (STRATEGY_COLOURS[chosen], f"auto: {chosen} (frustum, map)") in pic.keys
    assert names == list(CHOSEN_NAMES)
    image = compose(np.zeros((120, 320, 3), np.uint8), pic)
    assert image.shape == (120 + legend_height(pic), 320, 3)


def test_default_packet_is_near_the_centre():
    config = with_overrides(Config(), size=(64, 64), packet=8, depth=0)
    scene = load_scene(config.scene)
    pic = build_picture(scene, config, "primary")
    assert pic.summary["packet"] in (27, 28, 35, 36)  # the four tiles around the centre of 8x8 tiles


def _colours(image):
    """(colours i64[C,3], pixels i64[C]): the distinct colours of an RGB u8 image and how many
    pixels have each, so that counting the pixels near a colour is per colour, not per pixel."""
    packed = (image[..., 0].astype(np.int64) << 16) | (image[..., 1].astype(np.int64) << 8) | image[..., 2]
    values, pixels = np.unique(packed, return_counts=True)
    return np.stack([values >> 16, (values >> 8) & 255, values & 255], axis=1), pixels


def _colour_pixels(colours, colour, tolerance=40):
    """Pixels (of ``_colours``'s table) within ``tolerance`` of ``colour``, summed over R, G, B."""
    values, pixels = colours
    target = np.array(colour) * 255
    return int(pixels[np.abs(values - target).sum(axis=1) < tolerance].sum())


def test_show_writes_a_png_with_packet_frustum_and_nodes(tmp_path):
    """The real command in a fresh process (Open3D offscreen, no display): the rendering below the
    legend holds the rays' blue, the frustum's magenta and the visited nodes' colours."""
    from PIL import Image

    out = tmp_path / "show.png"
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    args = ["--size", "64x64", "--packet", "8", "--depth", "1"]
    run = subprocess.run([sys.executable, "-m", "engine.cli", "show", *args, "-o", str(out)],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "primary packet" in run.stdout and str(out) in run.stdout
    image = np.asarray(Image.open(out).convert("RGB"))
    assert image.shape == (600, 800, 3)
    config = with_overrides(Config(), size=(64, 64), packet=8, depth=1)
    pic = build_picture(load_scene(config.scene), config, "primary")
    drawing = image[legend_height(pic):]
    colours = _colours(drawing)
    assert _colour_pixels(colours, RAY_HIT) > 30
    assert _colour_pixels(colours, FRUSTUM) > 30
    trace_nodes = [c for name, _, _, c, _ in pic.lines if name == "nodes"][0]
    node_pixels = sum(_colour_pixels(colours, colour, 20) for colour in np.unique(trace_nodes.round(3), axis=0))
    assert node_pixels > 100
    assert (drawing > 250).all(axis=2).mean() > 0.3  # white background: nothing smeared


def test_node_colours_follow_the_live_fraction():
    colours = node_colours([0, 5, 10], 10)
    assert colours.shape == (3, 3)
    assert not np.allclose(colours[0], colours[2])


@pytest.mark.parametrize("argv,message", [
    (["--kind", "sideways"], "--kind must be one of primary, shadow, reflection, refraction"),
    (["--kind", "reflection", "--depth", "0"], "casts no reflection rays (max depth 0 casts camera rays only"),
    # before session 37 the refraction one blamed the materials of a scene with a glass sphere
    (["--kind", "refraction", "--depth", "0"], "casts no refraction rays (max depth 0 casts camera rays only"),
    (["--packet-index", "100000"], "is out of range: the first primary batch has 64 packets (valid 0..63)"),
    (["--picture", "10x10"], "--picture must be between 64x64 and 4096x4096"),
])
def test_show_mistakes_are_one_line_errors(argv, message, capsys, tmp_path):
    code = main(["show", "--size", "64x64", "--packet", "8", "-o", str(tmp_path / "x.png"), *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "x.png").exists()


def test_a_packet_without_a_live_ray_is_a_one_line_error(monkeypatch, capsys, tmp_path):
    """Shadow rays walked in their parent's lanes keep the packets of tiles that cast none: such
    a packet is refused in one line, and the default choice never lands on one."""
    monkeypatch.setattr(whitted, "IN_PLACE_SHADOWS", 0.0)
    config = with_overrides(Config(), size=(64, 64), packet=8, depth=0)
    renderer = WhittedRenderer(load_scene(config.scene), config)
    rays, packets, *_ = capture_batch(renderer, "shadow")
    live = rays.tmin <= rays.tmax
    dead = [k for k in range(len(packets.offsets) - 1) if not live[packets.offsets[k]:packets.offsets[k + 1]].any()]
    assert dead  # the sky above the default scene's floor casts no shadow ray
    code = main(["show", "--size", "64x64", "--packet", "8", "--depth", "0", "--kind", "shadow",
                 "--packet-index", str(dead[0]), "-o", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert code == 2 and "has no live ray" in err and err.count("\n") == 1
    assert not (tmp_path / "x.png").exists()
    assert centre_packet(rays, packets) not in dead


def test_rayspace_picture_has_cone_and_survivors():
    config = with_overrides(Config(), traversal=["rayspace"], size=(64, 64), packet=8, depth=1)
    pic = build_picture(load_scene(config.scene), config, "reflection")
    names = [name for name, *_ in pic.lines]
    assert "cone" in names and "survivors" in names and "rays" in names
    assert 0 < pic.summary["survivors"] <= 3072


def test_captured_batch_survives_the_renderer_reusing_its_arrays():
    """The renderer reuses per-lane arrays: the third generation's reflections land in the
    first one's. The batch ``show`` draws must still be the first, as it was traced."""
    config = with_overrides(Config(), size=(32, 32), depth=4, packet=4)
    config = config.__class__(**{**config.__dict__, "override": "reflective"})
    renderer = WhittedRenderer(load_scene(config.scene, config.override), config)
    first = []

    def copy_first(kind, query, rays, packets, answer):
        if kind == "reflection" and not first:
            first.append((np.array(rays.org), np.array(rays.dir), np.array(answer.t)))

    renderer.observer = copy_first
    renderer.render()                       # renders are deterministic: capture_batch's is the same
    renderer.observer = None
    rays, packets, query, answer, n_batches, _ = capture_batch(renderer, "reflection")
    assert n_batches >= 3
    org, direction, t = first[0]
    np.testing.assert_array_equal(rays.org, org)
    np.testing.assert_array_equal(rays.dir, direction)
    np.testing.assert_array_equal(answer.t, t)


@pytest.mark.parametrize("order", ["surface", "light"])
def test_a_shadow_packet_is_shown_walked_from_the_end_the_render_walked_it(shared_scenes, order):
    """With ``shadow_order = "light"`` the render walks shadow packets far child first; show
    records that walk, not the surface-first one: its node count is the render's own count."""
    from dataclasses import replace
    from engine.debug.packet_trace import packet_alone
    from engine.render.config import validate
    from engine.render.tracer import Tally

    config = with_overrides(Config(), scene="erw6", size=(64, 64))
    config = validate(replace(config, render=replace(config.render, shadow_order=order)))
    renderer = WhittedRenderer(scene_from_config(config.scene, config.override), config)
    captured = capture_batch(renderer, "shadow")
    assert captured.from_end == (order == "light")
    walks_differ = 0
    for k in (3, 5, 9):
        pic = build_picture(renderer.scene, config, "shadow", k, renderer=renderer)
        assert pic.summary["from_light"] == (order == "light")
        alone, alone_packets = packet_alone(captured.rays, captured.packets, k)
        counted = {}
        for from_end in (False, True):
            tally = Tally(count=True)
            renderer.tracer.trace("shadow", "occluded", alone, alone_packets, tally, from_end=from_end)
            counted[from_end] = int(tally.stats["shadow"].counters[:, COUNTER_NODES].sum())
        assert pic.summary["visited"] == counted[order == "light"]
        walks_differ += counted[False] != counted[True]
    assert walks_differ   # the two ends really walk differently on these packets


@pytest.mark.parametrize("traversal", ["single", "wide", "embree"])
def test_no_frustum_is_drawn_for_a_traversal_that_culls_with_none(traversal):
    config = with_overrides(Config(), size=(64, 64), traversal=[traversal])
    pic = build_picture(load_scene(config.scene), config, "primary")
    assert "frustum" not in [name for name, *_ in pic.lines]
    assert not pic.summary["frustum_valid"]
    assert any("culls with none" in line for line in pic.legend)
    assert FRUSTUM not in [colour for colour, _ in pic.keys]


@pytest.mark.parametrize("kind, grid", [("shadow", "light"), ("reflection", "direction")])
def test_a_rayspace_picture_says_when_the_render_grouped_rays_otherwise(kind, grid):
    config = with_overrides(Config(), traversal=["rayspace"], size=(64, 64), packet=8, depth=1)
    pic = build_picture(load_scene(config.scene), config, kind)
    assert any("pixel layout" in line and repr(grid) in line for line in pic.legend)
    primary = build_picture(load_scene(config.scene), config, "primary")
    assert not any("pixel layout" in line for line in primary.legend)
