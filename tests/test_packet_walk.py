"""The one packet walk (``engine.packet.walk``): every packet traversal plugin names its strategy,
a record of the walk leaves the answers and counters alone and holds exactly the visits the
kernel counts, records are refused where they cannot be kept, and every packet kernel is loaded
from numba's disk cache by a second process."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from engine.render.plugins import make_frustum, make_traversal
from engine.core.types import COUNTER_NODES, Frusta, empty_hits, new_stats
from engine.debug.packet_trace import packet_alone
from engine.packet.plugin import PacketTraversal, walk_batch
from engine.packet.record import DEPTH, kept_visits, new_record
from engine.packet.strategies import STRATEGIES
from packet_raysets import scene_rays
from scenes.whitted import whitted_scene

ROOT = Path(__file__).resolve().parents[1]
FRUSTUM_FOR = {"primary": "pinhole", "shadow": "pointlight", "reflection": "general", "refraction": "general"}


@pytest.fixture(scope="module")
def rayset():
    return scene_rays(whitted_scene([], {"subdivisions": 1}, 0.0), 32, 32)


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_each_packet_traversal_walks_by_its_strategy(name):
    plugin = make_traversal(name)
    assert isinstance(plugin, PacketTraversal)
    assert plugin.strategy == STRATEGIES[name]


def walk_one(rs, strategy, rays, packets, frusta, any_hit, counters=None, record=None):
    answers = empty_hits(rays.org.shape[0])
    walk_batch(strategy, rs.bvh, rs.tris, rays, packets, frusta, any_hit,
               answers.t, answers.prim, answers.u, answers.v, counters, record)
    return answers


def packet_frustum(frusta, k):
    """Packet k's frustum as the Frusta of a batch of one packet."""
    return Frusta(np.ascontiguousarray(frusta.planes[k:k + 1]), np.ascontiguousarray(frusta.valid[k:k + 1]))


@pytest.mark.parametrize("name", sorted(STRATEGIES))
@pytest.mark.parametrize("kind", sorted(FRUSTUM_FOR))
def test_a_record_changes_nothing_and_holds_every_counted_visit(rayset, name, kind):
    """Recorded or not, a packet gets the same answers and counters; the record's visits per
    depth are the pops the kernel counts."""
    rays, packets = rayset.rays[kind].batch(rayset.width, rayset.height, 8)
    frusta = make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rayset.bounds)
    any_hit = kind == "shadow"
    n_packets = len(packets.offsets) - 1
    recorded_some = False
    for k in range(0, n_packets, max(1, n_packets // 5)):
        alone = (*packet_alone(rays, packets, k), packet_frustum(frusta, k))
        plain_counters = new_stats(numba.get_num_threads()).counters
        plain = walk_one(rayset, STRATEGIES[name], *alone, any_hit, plain_counters)
        counters = new_stats(numba.get_num_threads()).counters
        record = new_record(50000)
        recorded = walk_one(rayset, STRATEGIES[name], *alone, any_hit, counters, record)
        for field in ("t", "prim", "u", "v"):
            np.testing.assert_array_equal(getattr(recorded, field), getattr(plain, field))
        np.testing.assert_array_equal(counters, plain_counters)
        visits = kept_visits(record)
        pops = np.bincount(visits[:, DEPTH], minlength=counters.shape[2])
        np.testing.assert_array_equal(pops, counters[:, COUNTER_NODES].sum(axis=0))
        recorded_some |= len(visits) > 0
    assert recorded_some


def test_a_record_is_kept_for_one_packet_with_room_for_its_visits(rayset):
    rays, packets = rayset.rays["primary"].batch(rayset.width, rayset.height, 8)
    with pytest.raises(ValueError, match="one packet at a time"):
        walk_one(rayset, STRATEGIES["partition"], rays, packets, None, False, record=new_record(100))
    k = (len(packets.offsets) - 1) // 2
    alone = (*packet_alone(rays, packets, k), None)
    record = new_record(1)
    walk_one(rayset, STRATEGIES["partition"], *alone, False, record=record)
    assert record.count[0] > 1
    with pytest.raises(ValueError, match="holds 1 visits"):
        kept_visits(record)


CACHE_SCRIPT = """
import sys
import numba, numpy as np
sys.path.insert(0, "tests")
from packet_raysets import scene_rays
from scenes.whitted import whitted_scene
from engine.render.plugins import make_frustum, make_traversal
from engine.core.types import empty_hits, new_stats
from engine.debug.packet_trace import trace_packet
from engine.render.tracer import Tracer

rs = scene_rays(whitted_scene([], {"subdivisions": 1}, 0.0), 16, 16)
for kind, frustum in %r.items():
    rays, packets = rs.rays[kind].batch(rs.width, rs.height, 4)
    frusta = make_frustum(frustum).build(rays, packets, rs.bounds)
    # auto choosing packet by packet as well: these small batches it would walk whole.
    for plugin in [make_traversal(name) for name in %r] + [make_traversal("auto", {"split_min_packets": 0})]:
        for stats in (None, new_stats(numba.get_num_threads())):
            plugin.intersect(rs.bvh, rs.tris, rays, packets, frusta, empty_hits(rays.org.shape[0]), stats)
            plugin.occluded(rs.bvh, rs.tris, rays, packets, frusta, np.zeros(rays.org.shape[0], np.bool_), stats)
        tracer = Tracer(rs.bvh, rs.tris, rs.bounds, {kind: plugin}, {kind: make_frustum(frustum)})
        trace_packet(tracer, kind, rays, packets, 0, kind == "shadow")
"""


def test_a_second_process_loads_every_packet_kernel_from_the_cache():
    """Run every strategy (plain, counting, recording) and frustum builder in two fresh
    processes: the second compiles nothing (NUMBA_DEBUG_CACHE reports no save) and loads the
    walk and the frustum kernel."""
    env = {**os.environ, "NUMBA_DEBUG_CACHE": "1"}
    script = CACHE_SCRIPT % (FRUSTUM_FOR, sorted(STRATEGIES))
    runs = [subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True, text=True,
                           timeout=600) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    second = runs[1].stdout.splitlines()
    assert not [line for line in second if "data saved" in line]
    loaded = [line for line in second if "data loaded" in line]
    for kernel in ("walk.walk_masked", "walk.walk_ranged", "walk.walk_partition", "walk.walk_simd",
                   "walk.choose_packets", "choose.batch_choice", "frustum_builders.build_frusta"):
        assert [line for line in loaded if f"{kernel}-" in line], kernel
