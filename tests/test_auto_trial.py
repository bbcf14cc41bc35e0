"""``auto``'s timed trials (``engine.packet.auto_trial``): every packet walked once, the rest of a
group given to the side that took less time, the verdict kept for the same batch, and the
answers always the plain traversals'."""
from __future__ import annotations

import numba
import numpy as np
import pytest

from engine.core.types import Frusta, empty_hits, new_stats
from engine.packet.auto_trial import (MARGIN, PASS_SIDES, SPLIT_MARGIN, TRIAL_MIN_PACKETS, TRIAL_PERIOD,
                                      TRIAL_RUN, TrialBook, trial_labels, tried_walk, winner)
from engine.packet.strategies import PARTITION, RANGED
from engine.render.plugins import make_frustum, make_traversal
from packet_raysets import scene_rays
from scenes.whitted import whitted_scene


class FakeClock:
    """A clock for ``TrialBook``: the k-th timed pass lasts durations[k] (start and stop calls
    alternate); any call past the list fails the test."""

    def __init__(self, durations):
        self.durations = list(durations)
        self.now = 0.0
        self.calls = 0

    def __call__(self):
        if self.calls % 2 == 1:
            self.now += self.durations[self.calls // 2]
        self.calls += 1
        return self.now


def test_a_groups_packets_are_dealt_to_the_four_passes_and_the_rest_in_runs():
    """Runs of TRIAL_RUN consecutive packets of the group, so a pass's packets spread over every
    deck (thread) and bring their own answer pages, not packets of one residue."""
    choices = np.array([PARTITION] * 7 + [RANGED] * 600 + [PARTITION] * 50, np.int8)
    labels = trial_labels(choices, RANGED)
    members = np.flatnonzero(choices == RANGED)
    assert (labels[choices != RANGED] == -1).all()
    expected = [min((r // TRIAL_RUN) % TRIAL_PERIOD, 4) for r in range(members.size)]
    np.testing.assert_array_equal(labels[members], expected)
    for trial_pass in range(4):  # each pass holds whole runs, dealt to every deck the group reaches
        ranks = np.flatnonzero(labels[members] == trial_pass)
        assert set(members[ranks] % 8) == set(range(8))


def test_the_larger_group_changes_by_the_margin_and_the_smaller_keeps_a_split_by_more():
    assert winner(RANGED, 1.0, (1 - MARGIN) * 0.999, larger=True) == PARTITION
    assert winner(RANGED, 1.0, 1 - MARGIN, larger=True) == RANGED
    assert winner(PARTITION, 0.5, 1.0, larger=True) == PARTITION
    # The smaller group keeps its own strategy (and the batch its split) only by SPLIT_MARGIN.
    assert winner(PARTITION, (1 - SPLIT_MARGIN) * 0.999, 1.0, larger=False) == PARTITION
    assert winner(PARTITION, (1 - SPLIT_MARGIN) * 1.001, 1.0, larger=False) == RANGED


def record_walks():
    walks = []

    def walk(strategy, chosen):
        walks.append((strategy, np.flatnonzero(chosen == strategy)))
    return walks, walk


def test_a_trial_walks_every_packet_once_and_gives_the_rest_to_the_faster_side():
    """Ranged's group: its own passes take 10, the other's 1, so its rest goes to Partition;
    Partition's group: its own passes take 1, so it keeps its strategy. The same batch again is
    walked by those verdicts, without a pass timed."""
    n = 4 * TRIAL_MIN_PACKETS
    rule = np.where(np.arange(n) % 3 == 0, PARTITION, RANGED).astype(np.int8)
    slow_own = [10.0 if side == 0 else 1.0 for side in PASS_SIDES]
    fast_own = [1.0 if side == 0 else 10.0 for side in PASS_SIDES]
    book = TrialBook(FakeClock(slow_own + fast_own))
    signature = book.signature("shadow", n, 64 * n)
    walks, walk = record_walks()
    choices = rule.copy()
    tried_walk(walk, choices, book, signature)
    walked = np.concatenate([packets for _, packets in walks])
    assert np.array_equal(np.sort(walked), np.arange(n)), "every packet walked exactly once"
    by = np.full(n, -1)
    for strategy, packets in walks:
        by[packets] = strategy
    np.testing.assert_array_equal(choices, by)  # choices say who walked each packet
    passes = [s for s, _ in walks[:4]]
    assert passes == [RANGED, PARTITION, PARTITION, RANGED]
    labels = trial_labels(rule, RANGED)
    assert (by[labels == 4] == PARTITION).all()
    assert (by[(labels == 0) | (labels == 3)] == RANGED).all()
    assert (by[trial_labels(rule, PARTITION) == 4] == PARTITION).all()
    assert book.verdicts(signature) == {RANGED: PARTITION, PARTITION: PARTITION}
    trials = book.trials_of(signature)
    assert [(t["group"], t["larger"], t["walked_by"]) for t in trials] == [("ranged", True, "partition"),
                                                                              ("partition", False, "partition")]
    assert trials[0]["own_seconds"] == 20.0 and trials[0]["own_packets"] == np.count_nonzero((labels == 0) | (labels == 3))

    walks, walk = record_walks()
    again = rule.copy()
    tried_walk(walk, again, book, signature)  # the fake clock has no durations left: no timing
    assert walks and all(s == PARTITION for s, _ in walks) and (again == PARTITION).all()


def test_a_group_too_small_to_try_keeps_the_rules_choice_and_is_not_tried_again():
    n = TRIAL_MIN_PACKETS + 30
    rule = np.full(n, RANGED, np.int8)
    rule[:20] = PARTITION
    book = TrialBook(FakeClock([10.0 if s == 0 else 1.0 for s in PASS_SIDES]))
    signature = book.signature("reflection", n, 16 * n)
    walks, walk = record_walks()
    choices = rule.copy()
    tried_walk(walk, choices, book, signature)
    assert (choices[:20] == PARTITION).all() and (choices[trial_labels(rule, RANGED) == 4] == PARTITION).all()
    assert book.verdicts(signature) == {RANGED: PARTITION}
    walks, walk = record_walks()
    again = rule.copy()
    tried_walk(walk, again, book, signature)
    assert (again[:20] == PARTITION).all() and (again[20:] == PARTITION).all()


@pytest.fixture(scope="module")
def alternating_batch():
    """Camera rays in 4x4 packets, packets 4i + 2 and 4i + 3 without a frustum, and auto options
    under which a packet with a frustum is Ranged and one without Partition: two interleaved
    groups of at least TRIAL_MIN_PACKETS packets each, both in the rule's sample."""
    rs = scene_rays(whitted_scene([], {"subdivisions": 1}, 0.0), 96, 96)
    rays, packets = rs.rays["primary"].batch(rs.width, rs.height, 4)
    frusta = make_frustum("pinhole").build(rays, packets, rs.bounds)
    valid = frusta.valid.copy()
    valid[np.arange(valid.size) % 4 >= 2] = False
    n_packets = len(packets.offsets) - 1
    assert n_packets // 2 >= TRIAL_MIN_PACKETS
    options = {"ranged_max_footprint": np.inf, "masked_max_footprint": -1.0, "min_live": 0.0,
               "invalid_frustum": "partition", "split_min_packets": 0}
    return rs, rays, packets, Frusta(frusta.planes, valid), options


@pytest.mark.parametrize("query", ["intersect", "occluded"])
def test_tried_batches_answer_as_the_plain_traversals_and_report_their_trials(alternating_batch, query):
    """The first walk (timed, no counters: as a render's frames) tries both groups; the second,
    counting (as the ``--stats`` pass), walks them by the verdicts and reports the trials."""
    rs, rays, packets, frusta, options = alternating_batch
    plugin = make_traversal("auto", {**options, "trials": True})
    # Ranged's group looks slow, Partition's fast: Ranged's rest goes to Partition.
    plugin.book = TrialBook(FakeClock([10.0 if s == 0 else 1.0 for s in PASS_SIDES]
                                      + [1.0 if s == 0 else 10.0 for s in PASS_SIDES]))
    n = rays.org.shape[0]
    n_packets = len(packets.offsets) - 1
    reference = make_traversal("partition")
    for stats in (None, new_stats(numba.get_num_threads())):
        if query == "intersect":
            hits, ref = empty_hits(n), empty_hits(n)
            plugin.intersect(rs.bvh, rs.tris, rays, packets, frusta, hits, stats)
            reference.intersect(rs.bvh, rs.tris, rays, packets, frusta, ref, None)
            for field in ("prim", "t", "u", "v"):
                np.testing.assert_array_equal(getattr(hits, field), getattr(ref, field))
        else:
            got, ref = np.zeros(n, np.bool_), np.zeros(n, np.bool_)
            plugin.occluded(rs.bvh, rs.tris, rays, packets, frusta, got, stats)
            reference.occluded(rs.bvh, rs.tris, rays, packets, frusta, ref, None)
            np.testing.assert_array_equal(got, ref)
    assert plugin.book.clock.calls == 16  # two groups, four timed passes each, on the first walk only
    signature = plugin.book.signature("primary", n_packets, n)
    assert plugin.book.verdicts(signature) == {RANGED: PARTITION, PARTITION: PARTITION}
    assert stats.extra["auto"]["per_batch"] == [{"masked": 0, "ranged": 0, "partition": n_packets}]
    trials = stats.extra["auto"]["trials"]
    assert [(t["group"], t["walked_by"]) for t in trials] == [("ranged", "partition"), ("partition", "partition")]
    for t, group in zip(trials, (RANGED, PARTITION)):
        labels = trial_labels(np.where(frusta.valid, RANGED, PARTITION).astype(np.int8),
                              group)
        assert t["tried_packets"] == np.count_nonzero((labels >= 0) & (labels < 4))
    assert plugin.choose(rs.bvh, rays, packets, frusta).tolist() == [PARTITION] * n_packets


def test_trials_are_off_unless_asked_for_and_are_checked():
    assert make_traversal("auto", {}).book is None and make_traversal("auto", {"trials": True}).book is not None
    with pytest.raises(ValueError, match="trials must be true or false"):
        make_traversal("auto", {"trials": "yes"})


def test_a_book_forgets_its_oldest_batches_first():
    from engine.packet.auto_trial import BOOK_CAPACITY
    book = TrialBook()
    for k in range(BOOK_CAPACITY + 5):
        book.open(book.signature("shadow", k, k))
    assert book.verdicts(book.signature("shadow", 0, 0)) is None
    assert book.verdicts(book.signature("shadow", BOOK_CAPACITY + 4, BOOK_CAPACITY + 4)) == {}
