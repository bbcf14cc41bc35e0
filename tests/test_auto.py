"""The ``auto`` traversal: its measures are what they say, it picks Ranged for a coherent camera
packet and Partition for a scattered one, a packet it gives to a strategy is walked exactly as
that strategy walks it (same answers and same counters), its choices are counted per batch in
the stats, options override the fitted thresholds and bad ones are refused, and the fit picks
the thresholds that minimise the summed cell times."""
from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from engine.core.errors import ConfigError
from engine.core.types import Frusta, empty_hits, new_stats
from engine.packet.auto_limits import fitted_limits, limits_array
from engine.packet.choose import (LIMIT_NAMES, MAJORITY_SAMPLED_PACKETS, SAMPLED_LANES, SAMPLED_PACKETS,
                                  measure_packets, sampled_packet)
from engine.packet.layout import make_batch
from engine.packet.plugin import walk_batch
from engine.packet.walk import choose_batch
from engine.packet.strategies import AUTO, CHOSEN_NAMES, MASKED, PARTITION, RANGED
from engine.render.plugins import make_frustum, make_traversal
from packet_raysets import scene_rays
from scenes.whitted import whitted_scene

FRUSTUM_FOR = {"primary": "pinhole", "shadow": "pointlight", "reflection": "general", "refraction": "general"}


@pytest.fixture(scope="module")
def rayset():
    return scene_rays(whitted_scene([], {"subdivisions": 1}, 0.0), 48, 48)


def one_packet(org, dirs, tmax, n=16):
    """A batch of one n x n packet (org, dirs f[n*n,3], tmax f[n*n]) in screen order."""
    m = n * n
    pixel = np.arange(m, dtype=np.int32)
    return make_batch("primary", org, dirs, np.zeros(m), tmax, pixel, np.ones((m, 3)), n, n, n)


def measured(bvh, rays, packets):
    k = len(packets.offsets) - 1
    live, footprint = np.zeros(k), np.zeros(k)
    measure_packets(bvh.bmin, bvh.bmax, rays.org, rays.dir, rays.tmin, rays.tmax,
                    np.ascontiguousarray(packets.offsets, np.int32), live, footprint)
    return live, footprint


def camera_packet(rs, half_angle, reach, n=16):
    """n x n rays from one eye at the scene box's centre, directions on a cone of the given half
    angle around +z (the corners exactly on it), segments of length ``reach``."""
    centre = (rs.bounds[0] + rs.bounds[1]) / 2
    s = np.linspace(-1.0, 1.0, n)
    x, y = np.meshgrid(s, s)
    # Corner rays (|x| = |y| = 1) lie on the cone: tan(half_angle) = sqrt(2) * a.
    a = math.tan(half_angle) / math.sqrt(2)
    dirs = np.stack([a * x.ravel(), a * y.ravel(), np.ones(n * n)], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return one_packet(np.tile(centre, (n * n, 1)), dirs, np.full(n * n, reach))


def scattered_packet(rs, seed=3, n=16):
    """n x n rays from points all over the scene box in directions all over the sphere."""
    rng = np.random.default_rng(seed)
    lo, hi = rs.bounds
    org = lo + rng.random((n * n, 3)) * (hi - lo)
    dirs = rng.normal(size=(n * n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return one_packet(org, dirs, np.full(n * n, np.inf))


def numpy_measures(bvh, rays, start, stop, every_lane=False):
    """(live, footprint) of rays start .. stop by the definition in ``engine.packet.choose``:
    on SAMPLED_LANES lanes evenly spaced from the first to the last (``every_lane``: on all)."""
    diagonal = float(np.linalg.norm(bvh.bmax[0].astype(np.float64) - bvh.bmin[0]))
    width = diagonal / math.sqrt((bvh.bmin.shape[0] + 1) / 2)
    n = stop - start
    if n <= SAMPLED_LANES or every_lane:
        lanes = np.arange(start, stop)
    else:
        lanes = start + (np.arange(SAMPLED_LANES) * (n - 1)) // (SAMPLED_LANES - 1)
    tmin, tmax = rays.tmin[lanes], rays.tmax[lanes]
    live = tmin <= tmax
    org = rays.org[lanes][live].astype(np.float64)
    d = rays.dir[lanes][live].astype(np.float64)
    norm = np.linalg.norm(d, axis=1)
    unit = d / norm[:, None]
    reach = np.minimum((tmax[live] - tmin[live]) * norm, diagonal).mean()
    origins = np.linalg.norm(org.max(axis=0) - org.min(axis=0))
    directions = np.linalg.norm(unit.max(axis=0) - unit.min(axis=0))
    return live.mean(), (origins + directions * reach) / width, width


def test_measures_of_a_camera_packet_are_its_cone(rayset):
    diagonal = float(np.linalg.norm(rayset.bvh.bmax[0] - rayset.bvh.bmin[0]))
    half = math.radians(2.0)
    for reach in (0.5 * diagonal, np.inf):
        rays, packets = camera_packet(rayset, half, reach)
        live, footprint = measured(rayset.bvh, rays, packets)
        expected_live, expected, width = numpy_measures(rayset.bvh, rays, 0, rays.org.shape[0])
        assert live[0] == expected_live == 1.0
        assert footprint[0] == pytest.approx(expected, rel=1e-5)
        # One origin: the directions' box spans the cone's chord (2 sin of the half-angle) and
        # a little more (its depth), over the reach (an infinite segment counts as the diagonal).
        chord = footprint[0] * width / min(reach, diagonal)
        assert 2 * math.sin(half) - 1e-6 <= chord <= 2 * math.sin(half) + (1 - math.cos(half)) + 1e-6


def test_the_sampled_diagonal_of_a_camera_packet_measures_the_whole_packet(rayset):
    # The sample of a 16 x 16 packet is its diagonal: its x and y extremes are the packet's, and
    # only the directions' z extent (the cone's depth, the centre ray) is a little short.
    for half in (math.radians(0.5), math.radians(2.0), math.radians(10.0)):
        rays, packets = camera_packet(rayset, half, np.inf)
        sampled = measured(rayset.bvh, rays, packets)[1][0]
        every = numpy_measures(rayset.bvh, rays, 0, rays.org.shape[0], every_lane=True)[1]
        assert sampled == pytest.approx(every, rel=2e-3)
        assert sampled <= every * (1 + 1e-6)


def test_directions_of_any_length_measure_as_their_unit_vectors(rayset):
    """Unit directions (the renderer's) skip the normalisation; longer ones, and a zero or NaN
    one (not measured), take it: the measures are the same."""
    rays, packets = scattered_packet(rayset)
    unit = measured(rayset.bvh, rays, packets)
    longer = rays._replace(dir=(rays.dir * np.float32(3.0)).astype(np.float32),
                           tmax=(rays.tmax / np.float32(3.0)).astype(np.float32))
    assert measured(rayset.bvh, longer, packets)[1][0] == pytest.approx(unit[1][0], rel=1e-5)
    bad = rays.dir.copy()
    bad[0] = 0.0
    bad[17] = np.nan  # lanes 0 and 17 are sampled (the diagonal of a 16 x 16 packet)
    live, footprint = measured(rayset.bvh, rays._replace(dir=bad), packets)
    assert live[0] == 14 / 16 and np.isfinite(footprint[0])


def test_dead_lanes_lower_the_live_fraction_and_are_not_measured(rayset):
    rays, packets = scattered_packet(rayset)
    tmax = rays.tmax.copy()
    tmax[::2] = -1.0  # half the lanes dead
    rays = rays._replace(tmax=tmax)
    live, footprint = measured(rayset.bvh, rays, packets)
    expected_live, expected, _ = numpy_measures(rayset.bvh, rays, 0, rays.org.shape[0])
    assert live[0] == expected_live == 0.5
    assert footprint[0] == pytest.approx(expected, rel=1e-5)
    rays = rays._replace(tmax=np.full_like(tmax, -1.0))
    assert measured(rayset.bvh, rays, packets)[0][0] == 0.0


def test_fitted_chooser_picks_ranged_for_a_camera_packet_and_partition_for_a_scattered_one(rayset):
    auto = make_traversal("auto")
    frustum = make_frustum("general")
    rays, packets = camera_packet(rayset, math.radians(1.0), np.inf)
    frusta = frustum.build(rays, packets, rayset.bounds)
    assert frusta.valid.all()
    assert auto.choose(rayset.bvh, rays, packets, frusta).tolist() == [RANGED]
    rays, packets = scattered_packet(rayset)
    frusta = frustum.build(rays, packets, rayset.bounds)
    assert not frusta.valid.any()  # directions of every sign: no frustum, the fitted fallback
    assert auto.choose(rayset.bvh, rays, packets, frusta).tolist() == [
        CHOSEN_NAMES.index(fitted_limits()["invalid_frustum"])]
    forced = Frusta(frusta.planes, np.ones_like(frusta.valid))  # had it a frustum: by its footprint
    assert auto.choose(rayset.bvh, rays, packets, forced).tolist() == [PARTITION]


def test_options_override_the_fitted_thresholds(rayset):
    rays, packets = camera_packet(rayset, math.radians(1.0), np.inf)
    valid = Frusta(np.zeros((1, 4, 4), np.float32), np.ones(1, np.bool_))
    invalid = Frusta(np.zeros((1, 4, 4), np.float32), np.zeros(1, np.bool_))
    never = make_traversal("auto", {"ranged_max_footprint": -1.0})
    assert never.choose(rayset.bvh, rays, packets, valid).tolist() == [PARTITION]
    masked = make_traversal("auto", {"masked_max_footprint": 10.0})
    assert masked.choose(rayset.bvh, rays, packets, valid).tolist() == [MASKED]
    for name in CHOSEN_NAMES:
        plugin = make_traversal("auto", {"invalid_frustum": name})
        assert plugin.choose(rayset.bvh, rays, packets, invalid).tolist() == [CHOSEN_NAMES.index(name)]
    assert make_traversal("auto").limits == fitted_limits()


@pytest.mark.parametrize("options,message", [({"ranged": 1.0}, "unknown key"),
                                             ({"min_live": "half"}, "must be a number"),
                                             ({"invalid_frustum": "simd"}, "must be one of"),
                                             ({"split_min_packets": -1}, "integer >= 0"),
                                             ({"split_min_packets": 1.5}, "integer >= 0")])
def test_bad_options_are_one_line_errors(options, message):
    with pytest.raises(ConfigError, match=message):
        make_traversal("auto", options)


def test_limits_file_names_every_limit():
    limits = fitted_limits()
    assert set(limits) == set(LIMIT_NAMES)
    limits_array(limits)  # valid values


FORCE = {"masked": {"masked_max_footprint": math.inf, "min_live": 0.0, "invalid_frustum": "masked"},
         "ranged": {"ranged_max_footprint": math.inf, "masked_max_footprint": -1.0, "min_live": 0.0,
                    "invalid_frustum": "ranged"},
         "partition": {"ranged_max_footprint": -1.0, "masked_max_footprint": -1.0, "invalid_frustum": "partition"}}


@pytest.mark.parametrize("kind", sorted(FRUSTUM_FOR))
@pytest.mark.parametrize("name", CHOSEN_NAMES)
def test_a_packet_given_to_a_strategy_is_walked_exactly_as_that_strategy_walks_it(rayset, kind, name):
    """auto forced to one strategy gives that traversal's answers and the same counters: its
    copy of the walk is the strategy's walk."""
    rays, packets = rayset.rays[kind].batch(rayset.width, rayset.height, 8)
    frusta = make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rayset.bounds)
    results = []
    for plugin in (make_traversal("auto", FORCE[name]), make_traversal(name)):
        stats = new_stats(numba.get_num_threads())
        hits = empty_hits(rays.org.shape[0])
        plugin.intersect(rayset.bvh, rayset.tris, rays, packets, frusta, hits, stats)
        occluded = np.zeros(rays.org.shape[0], np.bool_)
        plugin.occluded(rayset.bvh, rayset.tris, rays, packets, frusta, occluded, stats)
        results.append((hits, occluded, stats))
    (hits, occluded, stats), (ref_hits, ref_occluded, ref_stats) = results
    for field in ("prim", "t", "u", "v"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(ref_hits, field))
    np.testing.assert_array_equal(occluded, ref_occluded)
    np.testing.assert_array_equal(stats.counters.sum(axis=0), ref_stats.counters.sum(axis=0))
    n_packets = len(packets.offsets) - 1
    assert stats.extra["auto"]["packets"] == {n: (2 * n_packets if n == name else 0) for n in CHOSEN_NAMES}


#: Packets of the batches the sample tests use: 4x4 gives the 48x48 ray set 144 packets, more
#: than SAMPLED_PACKETS, so that some packets are left out of the sample.
SAMPLE_TEST_PACKET = 4


def sampled_packets(n_packets, per_packet=True):
    """The packets ``engine.packet.choose.batch_choice`` asks the rule for, by its doc: more in a
    batch that may be split packet by packet (``per_packet``) than in one that goes whole."""
    n = min(n_packets, SAMPLED_PACKETS if per_packet else MAJORITY_SAMPLED_PACKETS)
    return sorted({sampled_packet(j, n, n_packets) for j in range(n)})


@pytest.mark.parametrize("n_packets", [1, 5, 63, 64, 65, 1000, 4096])
def test_the_sample_takes_one_packet_in_each_equal_run_of_the_batch(n_packets):
    n = min(n_packets, SAMPLED_PACKETS)
    sample = [sampled_packet(j, n, n_packets) for j in range(n)]
    for j, k in enumerate(sample):
        assert j * n_packets // n <= k < (j + 1) * n_packets // n
    assert len(set(sample)) == n


def test_the_sample_of_an_image_batch_spreads_over_its_columns():
    """A 1024x1024 frame in 16x16 packets: 64 tiles a row, 4,096 packets, row by row. The first
    packet of every run (the sample until session 32) was a tile of the left column each time,
    and that column decided the batch."""
    columns = {sampled_packet(j, SAMPLED_PACKETS, 4096) % 64 for j in range(SAMPLED_PACKETS)}
    assert len(columns) >= SAMPLED_PACKETS // 2
    rows = [sampled_packet(j, SAMPLED_PACKETS, 4096) // 64 for j in range(SAMPLED_PACKETS)]
    assert rows == sorted(rows) and rows[-1] - rows[0] >= 60


def test_a_batch_is_not_decided_by_one_column_of_its_tiles(rayset):
    """The primary batch's packets in two columns of tiles are Masked by the rule, the rest
    Ranged: the sample's majority is Ranged, as the batch's is."""
    rays, packets = rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)
    per_row = rayset.width // SAMPLE_TEST_PACKET
    n_packets = len(packets.offsets) - 1
    assert per_row >= 8 and n_packets > SAMPLED_PACKETS
    odd = [k for k in range(n_packets) if k % per_row in (0, per_row // 2)]
    rays, packets, frusta, options = batch_with_odd_packets(rayset, odd)
    chosen = make_traversal("auto", {**options, "split_min_packets": n_packets + 1}).choose(
        rayset.bvh, rays, packets, frusta)
    assert (chosen == RANGED).all()


def batch_with_odd_packets(rayset, odd):
    """The primary batch of SAMPLE_TEST_PACKET-square packets (more than SAMPLED_PACKETS of them)
    with pinhole frusta, the packets ``odd`` without one; and
    an auto plugin's options under which a packet is Ranged with a frustum and Masked without."""
    rays, packets = rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)
    frusta = make_frustum("pinhole").build(rays, packets, rayset.bounds)
    valid = frusta.valid.copy()
    assert valid.all()
    valid[odd] = False
    options = {"ranged_max_footprint": math.inf, "masked_max_footprint": -1.0, "min_live": 0.0,
               "invalid_frustum": "masked"}
    return rays, packets, Frusta(frusta.planes, valid), options


@pytest.mark.parametrize("per", ["batch", "packet"])
@pytest.mark.parametrize("split", [False, True])
def test_a_batch_is_walked_by_its_samples_majority_or_packet_by_packet(rayset, per, split):
    """Every packet is Ranged by the rule but for a few Masked ones. A sample that agrees (the
    Masked packets outside it) gives Ranged to every packet. A split sample (one of them inside
    it): a batch of fewer than ``split_min_packets`` packets goes whole to the sample's majority
    (Ranged), a batch of as many is chosen packet by packet. All answer as Ranged does."""
    n_packets = len(rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)[1].offsets) - 1
    sampled = sampled_packets(n_packets, per == "packet")
    outside = sorted(set(range(n_packets)) - set(sampled))
    assert n_packets > SAMPLED_PACKETS and len(outside) >= 2
    odd = [outside[0], outside[-1]] + ([sampled[len(sampled) // 2]] if split else [])
    rays, packets, frusta, options = batch_with_odd_packets(rayset, odd)
    plugin = make_traversal("auto", {**options, "split_min_packets": n_packets + (per == "batch"),
                                     "split_min_share": 0.0})  # any share split (the share rule: below)
    expected = np.full(n_packets, RANGED, np.int8)
    if split and per == "packet":
        expected[odd] = MASKED
    np.testing.assert_array_equal(plugin.choose(rayset.bvh, rays, packets, frusta), expected)
    stats = new_stats(numba.get_num_threads())
    hits, ref = empty_hits(rays.org.shape[0]), empty_hits(rays.org.shape[0])
    plugin.intersect(rayset.bvh, rayset.tris, rays, packets, frusta, hits, stats)
    assert stats.extra["auto"]["per_batch"] == [{name: int((expected == i).sum()) for i, name in
                                                 enumerate(CHOSEN_NAMES)}]
    make_traversal("ranged").intersect(rayset.bvh, rayset.tris, rays, packets, frusta, ref, None)
    for field in ("prim", "t", "u", "v"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(ref, field))


def test_a_tie_in_the_sample_goes_to_the_lower_strategy_number(rayset):
    n_packets = len(rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)[1].offsets) - 1
    sampled = sampled_packets(n_packets, per_packet=False)  # a batch under split_min_packets
    rays, packets, frusta, options = batch_with_odd_packets(rayset, sampled[::2])
    assert 2 * len(sampled[::2]) == len(sampled)
    assert (make_traversal("auto", options).choose(rayset.bvh, rays, packets, frusta) == MASKED).all()


def test_packets_left_out_of_a_walk_are_left_out_of_its_sample(rayset):
    """A shadow-order trial walks some packets only (``only``): a sampled packet outside them
    does not split the sample, and gets no choice."""
    n_packets = len(rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)[1].offsets) - 1
    odd = sampled_packets(n_packets)[3]
    rays, packets, frusta, options = batch_with_odd_packets(rayset, [odd])
    limits = make_traversal("auto", options)._limits
    offsets = np.ascontiguousarray(packets.offsets, np.int32)
    only = np.zeros(n_packets, np.int8)
    only[odd] = -1
    choices = np.empty(n_packets, np.int8)
    counts, whole = choose_batch(rayset.bvh.bmin, rayset.bvh.bmax, rays.org, rays.dir, rays.tmin, rays.tmax,
                                 offsets, frusta.valid, limits, choices, only, per_packet=True)
    assert whole == RANGED
    assert choices[odd] == -1 and (np.delete(choices, odd) == RANGED).all()
    assert counts[RANGED] == n_packets - 1 and counts.sum() == n_packets - 1
    counts, whole = choose_batch(rayset.bvh.bmin, rayset.bvh.bmax, rays.org, rays.dir, rays.tmin, rays.tmax,
                                 offsets, frusta.valid, limits, choices, per_packet=True)
    assert whole == -1 and choices[odd] == MASKED and counts[MASKED] == 1


@pytest.mark.parametrize("kind", sorted(FRUSTUM_FOR))
def test_choices_are_recorded_per_packet_and_counted_per_batch(rayset, kind):
    """The walk's per-packet choices are the chooser's, and --stats counts them per batch."""
    rays, packets = rayset.rays[kind].batch(rayset.width, rayset.height, 8)
    frusta = make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rayset.bounds)
    # Thresholds at the batch's median footprint: both strategies get packets.
    footprint = measured(rayset.bvh, rays, packets)[1]
    plugin = make_traversal("auto", {"ranged_max_footprint": float(np.median(footprint)), "min_live": 0.0,
                                     "invalid_frustum": "partition", "split_min_packets": 0})
    expected = np.where(frusta.valid & (footprint <= np.median(footprint)), RANGED, PARTITION).astype(np.int8)
    np.testing.assert_array_equal(plugin.choose(rayset.bvh, rays, packets, frusta), expected)
    if frusta.valid.all():
        assert set(expected.tolist()) == {RANGED, PARTITION}
    choices = np.full(len(expected), -1, np.int8)
    hits = empty_hits(rays.org.shape[0])
    walk_batch(AUTO, rayset.bvh, rayset.tris, rays, packets, frusta, False, hits.t, hits.prim, hits.u, hits.v,
               limits=plugin._limits, choices=choices, per_packet=True)
    np.testing.assert_array_equal(choices, expected)
    stats = new_stats(numba.get_num_threads())
    for _ in range(2):
        plugin.intersect(rayset.bvh, rayset.tris, rays, packets, frusta, empty_hits(rays.org.shape[0]), stats)
    per = {name: int((expected == i).sum()) for i, name in enumerate(CHOSEN_NAMES)}
    assert stats.extra["auto"]["per_batch"] == [per, per]
    assert stats.extra["auto"]["packets"] == {name: 2 * n for name, n in per.items()}


def test_the_fit_picks_the_thresholds_that_minimise_the_summed_time():
    """Synthetic cells: Ranged is faster below footprint bin 5 with live >= 0.75, Partition
    elsewhere, Masked never; frustum-less cells are fastest by Partition."""
    from engine.bench.auto_fit import LIVE_EDGES, fit_limits

    f_edges = np.linspace(0.01, 0.3, 12)
    fb, lb, valid, seconds = [], [], [], []
    for f in range(len(f_edges) + 1):
        for live in range(len(LIVE_EDGES)):
            for ok in (True, False):
                ranged_wins = f <= 5 and live >= 3 and ok
                fb.append(f), lb.append(live), valid.append(ok)
                seconds.append([3.0, 1.0 if ranged_wins else 2.0, 1.5 if ranged_wins else 1.0])
    cells = {"fb": np.array(fb), "lb": np.array(lb), "valid": np.array(valid), "seconds": np.array(seconds)}
    limits, total, _ = fit_limits(cells, f_edges)
    assert limits == {"ranged_max_footprint": float(f_edges[5]), "masked_max_footprint": -1.0,
                      "min_live": LIVE_EDGES[3], "invalid_frustum": "partition"}
    assert total == pytest.approx(cells["seconds"].min(axis=1).sum())


def test_the_worst_row_fit_protects_the_row_the_summed_time_sacrifices():
    """Two rows of cells, footprint bins 0..3: a long row (spd-rings-like) where Partition wins
    from bin 1 up by a lot, and a short row (kitchen-like) where Ranged wins in every bin. The
    summed time puts the Ranged limit at bin 0 (the long row's gain outweighs the short row's
    loss: 1.375x its Ranged time); the worst-row objective moves it to bin 1, where the worse
    of the two rows is 1.25x (the short one) and the long one 1.14x."""
    from engine.bench.auto_fit import LIVE_EDGES, fit_limits, row_ratios, rule_choice

    f_edges = np.array([1.0, 2.0, 3.0])
    full = len(LIVE_EDGES) - 1
    group, fb, seconds = [], [], []
    for f in range(4):  # the long row: Ranged 10 s a cell, Partition 10 in bin 0, then 6
        group.append(("long", 16, "shadow")), fb.append(f), seconds.append([99.0, 10.0, 10.0 if f == 0 else 6.0])
    for f in range(4):  # the short row: Ranged 1 s, Partition 1.5 s in every bin
        group.append(("short", 16, "shadow")), fb.append(f), seconds.append([99.0, 1.0, 1.5])
    cells = {"group": group, "fb": np.array(fb), "lb": np.full(8, full), "valid": np.ones(8, bool),
             "seconds": np.array(seconds)}
    by_total, total, index = fit_limits(cells, f_edges)  # the default: the summed time
    assert by_total["ranged_max_footprint"] == 1.0  # Ranged for bin 0 only: the short row 1.375x
    assert row_ratios(cells, rule_choice(cells["fb"], cells["lb"], cells["valid"], *index)).max() == pytest.approx(1.375)
    by_row, total_by_row, index = fit_limits(cells, f_edges, "worst-row")
    ratios = row_ratios(cells, rule_choice(cells["fb"], cells["lb"], cells["valid"], *index))
    assert by_row["ranged_max_footprint"] == 2.0 and ratios.max() == pytest.approx(1.25)
    assert ratios.min() == pytest.approx(32 / 28) and total_by_row > total
    with pytest.raises(ValueError, match="objective"):
        fit_limits(cells, f_edges, "fastest")


def test_rows_carry_their_resolution_only_when_a_fit_has_several():
    from engine.bench.auto_fit import row_label

    assert row_label("erw6", 256, [256]) == "erw6"
    assert row_label("erw6", 1024, [256, 1024]) == "erw6 1024x1024"


@pytest.mark.parametrize("packet", [4, 16])
@pytest.mark.parametrize("split_min_packets", [None, 0])
def test_a_whitted_frame_by_auto_audits_clean_against_embree(tmp_path, packet, split_min_packets):
    """Every ray of a whole Whitted frame (camera, shadow, reflection and refraction rays of the
    default scene) walked by ``auto`` is checked against Embree: no mismatch. With the default
    ``split_min_packets`` these small batches are walked whole; with 0 every batch whose sample
    is split is chosen packet by packet."""
    import json

    from engine.cli import main

    report = tmp_path / "audit.json"
    config = []
    if split_min_packets is not None:
        config = [str(tmp_path / "auto.toml")]
        (tmp_path / "auto.toml").write_text(f"[options.auto]\nsplit_min_packets = {split_min_packets}\n")
    assert main(["audit", *config, "--size", "64x64", "--traversal", "auto", "--packet", str(packet),
                 "--json", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["mismatches"] == [] and data["agreement"] == 1.0
    assert all(data["by_kind"][kind]["checked"] > 0 for kind in ("primary", "shadow", "reflection", "refraction"))


def test_the_fit_draws_auto_against_ranged_and_partition_row_by_row(tmp_path):
    from PIL import Image

    from engine.bench.auto_fit import figure

    def timing_of(n_rows):
        kinds = ("primary", "shadow", "reflection", "refraction")
        return {("erw6", 8 * (1 + i // 4), kinds[i % 4]): {"ranged": 1.0, "partition": 1.2,
                                                          "auto": 0.97 if i % 2 else 1.08}
                for i in range(n_rows)}

    few = figure(timing_of(2), {("erw6", 8, "primary"): {"ranged": 3, "partition": 1}}, tmp_path / "few.png")
    many = figure(timing_of(8), {}, tmp_path / "many.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["few.png", "many.png"]  # no temporary left
    with Image.open(few) as a, Image.open(many) as b:
        assert a.format == b.format == "PNG"
        assert b.height > a.height  # a bar per row


def test_paired_ratios_give_the_median_and_the_sign_tests_interval():
    """Ratios of times taken in the same repetitions: the median, and for n = 41 the 14th and 28th
    smallest ratios as the 95% interval; a row is faster or slower only when the whole interval
    is on one side of 1."""
    from engine.bench.auto_fit import paired_ratio, verdict

    rng = np.random.default_rng(3)
    ratios = rng.permutation(np.arange(1, 42) / 21.0)
    best = rng.uniform(1e-3, 2e-3, 41)
    median, low, high = paired_ratio(ratios * best, best)
    assert median == pytest.approx(1.0) and low == pytest.approx(14 / 21) and high == pytest.approx(28 / 21)
    assert verdict(low, high) == "same"
    assert verdict(*paired_ratio(0.9 * best, best)[1:]) == "faster"
    assert verdict(*paired_ratio(1.1 * best, best)[1:]) == "slower"
    # A drift shared by both sides of each repetition cancels.
    drift = np.linspace(1.0, 2.0, 41)
    assert paired_ratio(0.95 * best * drift, best * drift)[2] < 1.0


def test_fit_auto_measures_a_thresholds_file_or_names_what_is_wrong_with_it(tmp_path, capsys):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from fit_auto import main, read_limits

    shipped = Path(__file__).resolve().parents[1] / "engine/packet/auto_thresholds.json"
    assert read_limits(str(shipped)) == json.loads(shipped.read_text())["limits"]
    bad = tmp_path / "bad.json"
    bad_value = json.dumps({"limits": {**json.loads(shipped.read_text())["limits"], "ranged_max_footprint": "abc"}})
    for text in ("{", '{"limits": {"min_live": 0.9}}', "[]", bad_value):
        bad.write_text(text)
        assert main(["--limits", str(bad), "--measure-repeat", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"fit_auto: --limits {bad}") and "\n" not in err
    # A folder given as an output file is refused before the fit (no probe file in the project).
    for option in (["--size", "256,x"], ["--size", "8"], ["--packets", "16,"], ["--thresholds", str(tmp_path)],
                   ["--thresholds", str(tmp_path / "t.json"), "--report", str(tmp_path)]):
        assert main([*option, "--measure-repeat", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("fit_auto: ") and "\n" not in err


def test_the_report_gives_each_row_its_paired_interval_and_counts_the_verdicts():
    from engine.bench.auto_fit import LIVE_EDGES, report

    cells = {"group": [("erw6", 8, "primary"), ("erw6", 8, "shadow")], "fb": np.array([0, 1]),
             "lb": np.array([len(LIVE_EDGES) - 1] * 2), "valid": np.array([True, True]),
             "seconds": np.array([[3.0, 1.0, 2.0], [3.0, 2.0, 1.0]])}
    timing = {("erw6", 8, "primary"): {"ranged": 1e-3, "partition": 2e-3, "auto": 0.9e-3, "auto/packet": 1e-3,
                                       "auto/trials": 1e-3,
                                       "paired": {"auto": (0.9, 0.85, 0.95), "auto/packet": (1.0, 0.9, 1.1),
                                                  "auto/trials": (1.0, 0.97, 1.02)}},
              ("erw6", 8, "shadow"): {"ranged": 2e-3, "partition": 1e-3, "auto": 1.2e-3, "auto/packet": 1e-3,
                                      "auto/trials": 1.3e-3,
                                      "paired": {"auto": (1.2, 1.1, 1.3), "auto/packet": (1.0, 0.9, 1.1),
                                                 "auto/trials": (1.3, 1.25, 1.4)}}}
    limits = {"ranged_max_footprint": 0.5, "masked_max_footprint": -1.0, "min_live": LIVE_EDGES[-1],
              "invalid_frustum": "partition"}
    args = {"date": "today", "scenes": ["erw6"], "sizes": [64], "packets": [8], "repeat": 1, "threads": 2,
            "measure_repeat": 3, "command": "fit", "machine": "here", "fitted": False}
    trial = {"kind": "shadow", "packets": 4096, "group": "partition", "larger": False, "tried_packets": 170,
             "own_seconds": 2e-3, "own_packets": 85, "other_seconds": 1e-3, "other_packets": 85, "walked_by": "ranged"}
    counts = {("erw6", 8, "shadow"): {"masked": 0, "ranged": 4096, "partition": 0, "trials": [trial]},
              ("erw6", 8, "primary"): {"masked": 0, "ranged": 1024, "partition": 0}}
    text = report(args, limits, 2.0, cells, np.array([0.5]), timing, counts, 1.0)
    # The primary row was walked entirely by Ranged, its better strategy: its verdict is no choice's.
    # The shadow row, all Ranged too, is not: Partition was its better strategy.
    assert "1 were walked entirely by the better strategy" in text and \
           "faster in 1, the same in 0, slower in 0." in text
    assert "| erw6 | 8 | shadow | 4096 | partition | no | 2.00 (85) | 1.00 (85) | ranged |" in text  # the trials' table
    assert "given with `--limits`" in text
    assert "| 0.900 [0.850, 0.950] | faster |" in text and "| 1.200 [1.100, 1.300] | slower |" in text
    assert "rows, auto: faster than both in 1, the same as the better within the noise in 0, slower than the " \
           "better in 1" in text
    # auto with trials, paired against the same better strategy, has its own column and count.
    assert "| 1.30 | 1.300 [1.250, 1.400] | slower |" in text
    assert "auto with trials: faster than both in 0, the same as the better within the noise in 1, " \
           "slower than the better in 1" in text


@pytest.mark.parametrize("share,in_sample,split", [(0.0, 1, True), (0.015, 1, True), (0.02, 1, False),
                                                    (0.25, 1, False), (0.02, 2, False)])
def test_a_split_with_too_few_packets_of_the_minority_is_walked_whole(rayset, share, in_sample, split):
    """3 of the 144 packets (2.1%) are Masked by the rule, the others Ranged, and the sample is
    split (1 of its 64 packets Masked, 1.6%): the batch is chosen packet by packet and keeps its
    split only when both shares reach ``split_min_share``; otherwise every packet goes to Ranged,
    with no per-packet pass when the sample's share is already short. With 2 sampled packets the
    only Masked ones (3.1% of the sample, 1.4% of the packets), a 2% share passes the sample but
    not the per-packet count: whole. The answers are Ranged's either way."""
    n_packets = len(rayset.rays["primary"].batch(rayset.width, rayset.height, SAMPLE_TEST_PACKET)[1].offsets) - 1
    sampled = sampled_packets(n_packets)
    outside = sorted(set(range(n_packets)) - set(sampled))
    odd = [outside[0], outside[-1], sampled[len(sampled) // 2]] if in_sample == 1 else sampled[10:12]
    rays, packets, frusta, options = batch_with_odd_packets(rayset, odd)
    plugin = make_traversal("auto", {**options, "split_min_packets": 0, "split_min_share": share})
    expected = np.full(n_packets, RANGED, np.int8)
    if split:
        expected[odd] = MASKED
    np.testing.assert_array_equal(plugin.choose(rayset.bvh, rays, packets, frusta), expected)
    stats = new_stats(numba.get_num_threads())
    hits, ref = empty_hits(rays.org.shape[0]), empty_hits(rays.org.shape[0])
    plugin.intersect(rayset.bvh, rayset.tris, rays, packets, frusta, hits, stats)
    assert stats.extra["auto"]["packets"]["masked"] == (len(odd) if split else 0)
    make_traversal("ranged").intersect(rayset.bvh, rayset.tris, rays, packets, frusta, ref, None)
    for field in ("prim", "t", "u", "v"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(ref, field))


def test_split_min_share_is_checked():
    with pytest.raises(ValueError, match="split_min_share must be a number in 0..0.5"):
        make_traversal("auto", {"split_min_share": 0.7})
