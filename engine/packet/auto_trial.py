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
with at least ``TRIAL_MIN_PACKETS`` packets is tried. In packet order, the group's packets of
rank 8i and 8i + 3 are walked by the group's own strategy and those of rank 8i + 1 and 8i + 2 by
the other one, as four timed parallel passes in the order own, other, other, own, so that the
host's drift and the caches warming over the four passes fall on both sides alike. The rest of
the group (half of it) is walked by the side that took less time, the group's own strategy
unless the other took under ``1 - MARGIN`` of its time. Every packet is walked exactly once, so
the answers are the plain traversals' answers (all strategies find the same hits).

The verdicts are kept in a ``TrialBook`` under the batch's signature (ray kind, packet count, ray
count): the same batch of the next frame of a static scene has the same signature, and its
groups are walked by their verdicts at once, with no trial and no extra pass. A batch not seen
before (a new frame of an animation, another resolution) is tried afresh. The book belongs to one
``auto`` plugin instance (one renderer or query), so nothing is shared between renders.

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
#: Ranks within a group: in every run of TRIAL_PERIOD packets, the first four go to the trial's
#: passes 0..3 (own, other, other, own), the rest to the winner.
TRIAL_PERIOD = 8
#: The other strategy wins a group when it took under (1 - MARGIN) of the group's own time.
MARGIN = 0.03
#: Verdicts a book keeps (the oldest are dropped first): an animation brings new signatures.
BOOK_CAPACITY = 256
#: The side each of the four timed passes walks: 0 = the group's own strategy, 1 = the other.
PASS_SIDES = (0, 1, 1, 0)


def other_strategy(strategy: int) -> int:
    """Ranged for Partition and Partition for Ranged (the two strategies a trial compares)."""
    return PARTITION if strategy == RANGED else RANGED


def trial_labels(choices: np.ndarray, group: int) -> np.ndarray:
    """i8[K]: for each packet k with choices[k] == group, the trial pass (0..3) that walks it,
    or 4 for the rest of the group, by its rank r within the group (r % TRIAL_PERIOD, 4 when
    that is 4 or more); -1 for every other packet."""
    labels = np.full(choices.shape[0], -1, np.int8)
    members = np.flatnonzero(choices == group)
    labels[members] = np.minimum(np.arange(members.size) % TRIAL_PERIOD, 4)
    return labels


def winner(group: int, own_seconds: float, other_seconds: float, margin: float = MARGIN) -> int:
    """The strategy the rest of ``group`` is walked by: the other one when it took under
    (1 - margin) of the group's own strategy's time on the trial's packets, else ``group``."""
    return other_strategy(group) if other_seconds < (1.0 - margin) * own_seconds else group


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
        packets, group, tried_packets, own_seconds, other_seconds, walked_by."""
        return list(self._trials.get(signature, ()))

    def decide(self, signature, group: int, own_seconds: float, other_seconds: float, n_tried: int) -> int:
        """Record the trial of ``group`` in batch ``signature`` and return its winner."""
        chosen = winner(group, own_seconds, other_seconds)
        if signature not in self._verdicts:
            self.open(signature)
        self._verdicts[signature][group] = chosen
        self._trials[signature].append({"kind": signature[0], "packets": signature[1], "group": CHOSEN_NAMES[group],
                                        "tried_packets": int(n_tried), "own_seconds": float(own_seconds),
                                        "other_seconds": float(other_seconds), "walked_by": CHOSEN_NAMES[chosen]})
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
    for group in (RANGED, PARTITION):
        labels = trial_labels(choices, group)
        tried = (labels >= 0) & (labels < 4)
        if np.count_nonzero(labels >= 0) < TRIAL_MIN_PACKETS:
            continue
        sides = (group, other_strategy(group))
        seconds = [0.0, 0.0]
        for trial_pass, side in enumerate(PASS_SIDES):
            strategy = sides[side]
            start = book.clock()
            walk(strategy, np.where(labels == trial_pass, strategy, -1).astype(np.int8))
            seconds[side] += book.clock() - start
            walked[labels == trial_pass] = strategy
        walked[labels == 4] = book.decide(signature, group, seconds[0], seconds[1], np.count_nonzero(tried))
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
