"""Timed trials that check ``auto``'s rule on the batches it splits, and remember the verdicts.

The rule (``engine.packet.choose``) gives each packet of a split batch Ranged or Partition from
its live fraction, footprint and frustum. Those measures cannot tell every scene's packets apart:
at 1024x1024 the rule sends some of the kitchen's and the museum's shadow packets to Partition,
which walks them more slowly than Ranged, while spd-rings' packets of the same footprint walk
faster by Partition (``docs/auto-fit-1024.md``); no one threshold serves every row
(``docs/auto-fit-two-sizes.md``). So ``auto`` also measures, on the batches where the rule
disagrees with itself.

When a batch is chosen packet by packet (its sample split, and at least ``split_min_packets``
packets), each of its two groups -- the packets the rule gave Ranged, those it gave Partition --
with at least ``TRIAL_MIN_PACKETS`` packets is tried. The group's packets, in packet order, are
dealt in runs of ``TRIAL_RUN``: of every ``TRIAL_PERIOD`` runs, run 0 and run 3 are walked by the
group's own strategy and runs 1 and 2 by the other one, as four timed parallel passes in the
order own, other, other, own, so that the host's drift and the caches warming over the four
passes fall on both sides alike. Runs of consecutive packets, not single packets: the walk deals
packet k to deck k % decks, so packets of one residue would all go to one thread, and neighbouring
packets share the pages of the answer arrays, whose first touch (a page fault) would all fall on
the first pass. The rest of the group (half of it) is walked by the side whose packets took less
time each. Every packet is walked exactly once, so the answers are the plain traversals' answers
(all strategies find the same hits).

Splitting a batch has a cost of its own that a trial of separate packets does not see: each
strategy's pass walks packets farther apart, which share fewer tree nodes in the caches (the
kitchen's 1024x1024 shadow batch walked 7% slower split than whole by Ranged, although its
Partition packets each walked 8% faster by Partition in the trial). So the larger group needs the
other strategy to be ``MARGIN`` faster to change, and the smaller group keeps its own strategy,
and with it the split, only when that is ``SPLIT_MARGIN`` faster than the larger group's.

The verdicts are kept in a ``TrialBook`` under the batch's signature (ray kind, packet count, ray
count): the same batch of the next frame of a static scene has the same signature, and its
groups are walked by their verdicts at once, with no trial and no extra pass. A batch not seen
before (a new frame of an animation, another resolution) is tried afresh. The book belongs to one
``auto`` plugin instance (one renderer or query), so nothing is shared between renders.

**Off by default** (``[options.auto] trials = true`` turns them on): measured, they make ``auto``
slower. ``tools/fit_auto.py`` at 1024x1024 (16x16 packets, erw6, museum, kitchen, spd-rings, 21
paired repetitions, the shipped thresholds; session 31, ``docs/auto-fit-1024-trials.md``):

- packets dealt one by one (ranks mod 8), no split margin: with trials slower than the better
  strategy in 3 of 16 rows, faster than both in 1; the rule alone slower in 1;
- runs of 16 packets, times per packet, the split margin (as here): with trials slower in 7 rows;
  the rule alone slower in 1 and faster than both in 1 (museum reflections, 0.909 [0.855, 0.982]).

Two reasons, both measured. The first timed pass of a process reads far slower than the same work
later: erw6's 1024x1024 reflection batch, its Ranged group tried by a fresh plugin four times in
one process, read 14.4 / 5.8 / 5.5 / 6.0 ms for its own passes against 9.6 / 9.3 / 9.0 / 9.2 for
the other's, so the first trial sent the group to Partition, which walks that batch 1.3x slower.
And a subset's time does not predict the batch's: the museum's reflection batch, its Partition
group walked faster by Ranged in the trial (6.3 against 8.1 ms), walked 9% faster split, as the
rule had it, than whole by Ranged. A measure of whole batches (the same batch walked by each
choice over successive frames) would see what the split costs; it was not built.

Unlike the shadow order (``engine.render.shadow_order``, which counts node visits so that a
scene always gets the same choice), these verdicts come from timings: walking a packet by
Ranged or by Partition differs in kinds of work (box tests, triangle tests, partitioning), not
only in how much, so a count would need a cost model per strategy. The answers never depend on
the verdict; the speed does, and which strategy a group got is reported (``--stats``:
``extra.plugins.KIND.auto.trials``).
"""
from __future__ import annotations

import time
from collections import OrderedDict

import numpy as np

from engine.packet.strategies import CHOSEN_NAMES, MASKED, PARTITION, RANGED

#: A group of fewer packets than this is not tried (each timed pass would hold an eighth of it).
TRIAL_MIN_PACKETS = 256
#: A group's packets are dealt in runs of TRIAL_RUN consecutive ones; of every TRIAL_PERIOD runs,
#: the first four go to the trial's passes 0..3 (own, other, other, own), the rest to the winner.
TRIAL_RUN = 16
TRIAL_PERIOD = 8
#: The larger group goes to the other strategy when its packets took under (1 - MARGIN) of the
#: time each that the group's own took; the smaller group keeps its own strategy (a split batch)
#: only when that took under (1 - SPLIT_MARGIN) of the larger group's strategy's time.
MARGIN = 0.03
SPLIT_MARGIN = 0.10
#: Verdicts a book keeps (the oldest are dropped first): an animation brings new signatures.
BOOK_CAPACITY = 256
#: The side each of the four timed passes walks: 0 = the group's own strategy, 1 = the other.
PASS_SIDES = (0, 1, 1, 0)


def other_strategy(strategy: int) -> int:
    """Ranged for Partition and Partition for Ranged (the two strategies a trial compares)."""
    return PARTITION if strategy == RANGED else RANGED


def trial_labels(choices: np.ndarray, group: int) -> np.ndarray:
    """i8[K]: for each packet k with choices[k] == group, the trial pass (0..3) that walks it,
    or 4 for the rest of the group, by its rank r within the group: run r // TRIAL_RUN, and of
    the runs, (run % TRIAL_PERIOD), 4 when that is 4 or more; -1 for every other packet."""
    labels = np.full(choices.shape[0], -1, np.int8)
    members = np.flatnonzero(choices == group)
    labels[members] = np.minimum((np.arange(members.size) // TRIAL_RUN) % TRIAL_PERIOD, 4)
    return labels


def winner(group: int, own_each: float, other_each: float, larger: bool) -> int:
    """The strategy the rest of ``group`` is walked by, from the trial's seconds per packet of
    the group's own strategy and of the other: for the larger group, the other one when it took
    under (1 - MARGIN) of the own one's time; for the smaller, its own one only when that took
    under (1 - SPLIT_MARGIN) of the other's (else the batch is walked whole, see the module doc)."""
    if larger:
        return other_strategy(group) if other_each < (1.0 - MARGIN) * own_each else group
    return group if own_each < (1.0 - SPLIT_MARGIN) * other_each else other_strategy(group)


class TrialBook:
    """Verdicts of the trials by batch signature, at most BOOK_CAPACITY signatures (the oldest
    dropped first): for each, {group strategy: strategy that walks it} and the trials that
    decided it (``trials_of``). ``clock`` times the trial passes (``time.perf_counter``; the
    tests give a fake one)."""

    def __init__(self, clock=time.perf_counter):
        self.clock = clock
        self._verdicts: OrderedDict = OrderedDict()
        self._trials: dict = {}

    @staticmethod
    def signature(kind: str, n_packets: int, n_rays: int) -> tuple:
        """A batch's signature: the same batch of the next frame of a static scene has the same."""
        return (kind, int(n_packets), int(n_rays))

    @staticmethod
    def signature_of(rays, packets) -> tuple:
        """``signature`` of a RayBatch in its Packets."""
        return TrialBook.signature(rays.kind, len(packets.offsets) - 1, rays.org.shape[0])

    def open(self, signature) -> None:
        """Mark ``signature`` as seen (its verdicts, possibly none, follow): a batch whose groups
        are too small to try is not tried again."""
        self._verdicts[signature] = {}
        self._trials[signature] = []
        self._verdicts.move_to_end(signature)
        while len(self._verdicts) > BOOK_CAPACITY:
            dropped, _ = self._verdicts.popitem(last=False)
            del self._trials[dropped]

    def verdicts(self, signature) -> dict | None:
        """{group strategy: strategy} decided for the batch ``signature``, or None."""
        return self._verdicts.get(signature)

    def trials_of(self, signature) -> list:
        """The trials that decided ``signature``'s verdicts, one dict per group tried: kind,
        packets, group, larger, tried_packets, own_seconds, own_packets, other_seconds,
        other_packets, walked_by."""
        return list(self._trials.get(signature, ()))

    def decide(self, signature, group: int, own: tuple, other: tuple, larger: bool) -> int:
        """Record the trial of ``group`` in batch ``signature`` -- (seconds, packets) walked by
        its own strategy and by the other; ``larger``: the larger of the batch's two groups --
        and return its winner."""
        (own_seconds, own_packets), (other_seconds, other_packets) = own, other
        chosen = winner(group, own_seconds / max(own_packets, 1), other_seconds / max(other_packets, 1), larger)
        n_tried = own_packets + other_packets
        if signature not in self._verdicts:
            self.open(signature)
        self._verdicts[signature][group] = chosen
        self._trials[signature].append({"kind": signature[0], "packets": signature[1], "group": CHOSEN_NAMES[group],
                                        "larger": bool(larger), "tried_packets": int(n_tried),
                                        "own_seconds": float(own_seconds), "own_packets": int(own_packets),
                                        "other_seconds": float(other_seconds), "other_packets": int(other_packets),
                                        "walked_by": CHOSEN_NAMES[chosen]})
        return chosen


def apply_verdicts(choices: np.ndarray, verdicts: dict) -> None:
    """Give each packet of a group with a verdict the verdict's strategy (choices i8[K], in place)."""
    original = choices.copy()
    for group, chosen in verdicts.items():
        choices[original == group] = chosen


def tried_walk(walk, choices: np.ndarray, book: TrialBook, signature) -> None:
    """Walk a batch chosen packet by packet (choices i8[K], the rule's strategy per packet, -1:
    not walked), trying its groups first when ``book`` has no verdict for ``signature`` (see the
    module doc). ``walk(strategy, chosen)`` walks the packets k with chosen[k] == strategy.
    choices is left holding the strategy that walked each packet."""
    known = book.verdicts(signature)
    if known is not None:
        apply_verdicts(choices, known)
        walk_by_strategy(walk, choices)
        return
    walked = choices.copy()  # the strategy that walks each packet, as it is decided
    book.open(signature)
    sizes = {group: int(np.count_nonzero(choices == group)) for group in (RANGED, PARTITION)}
    for group in (RANGED, PARTITION):
        labels = trial_labels(choices, group)
        tried = (labels >= 0) & (labels < 4)
        if sizes[group] < TRIAL_MIN_PACKETS:
            continue
        sides = (group, other_strategy(group))
        seconds, packets = [0.0, 0.0], [0, 0]
        for trial_pass, side in enumerate(PASS_SIDES):
            strategy = sides[side]
            start = book.clock()
            walk(strategy, np.where(labels == trial_pass, strategy, -1).astype(np.int8))
            seconds[side] += book.clock() - start
            packets[side] += int(np.count_nonzero(labels == trial_pass))
            walked[labels == trial_pass] = strategy
        larger = sizes[group] >= sizes[other_strategy(group)]
        walked[labels == 4] = book.decide(signature, group, (seconds[0], packets[0]), (seconds[1], packets[1]),
                                          larger)
        choices[tried] = -1  # walked by the trial: not again
    choices[choices >= 0] = walked[choices >= 0]
    walk_by_strategy(walk, choices)
    choices[:] = walked


def walk_by_strategy(walk, choices: np.ndarray) -> None:
    """One pass per strategy some packet of ``choices`` has (a strategy no packet has costs none)."""
    present = np.bincount(choices[choices >= 0], minlength=len(CHOSEN_NAMES))
    for strategy in (RANGED, PARTITION, MASKED):
        if present[strategy] > 0:
            walk(strategy, choices)
