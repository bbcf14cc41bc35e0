"""``auto``: packets walked by Ranged, Partition or Masked, chosen from measures of the packets.

Overbeck, Ramamoorthi and Mark (2008) find Ranged the faster traversal on coherent packets and
Partition on incoherent ones, and pick one per ray kind. ``auto`` asks a rule for a strategy per
packet, from measures of 16 of its lanes taken before the walk (``engine.packet.choose``): the
fraction of them that are live, its footprint (the spread of its origins plus the widening of its
direction cone over its rays' reach, in the scene's typical leaf widths) and whether it has a
frustum. It asks for 64 packets spread over each batch, 32 over a batch under
``split_min_packets`` (``engine.packet.walk.choose_batch``). When they all get the same strategy,
it walks the whole batch. When they do not, a batch of at least ``split_min_packets`` packets is
chosen packet by packet (a parallel pass asks the rule for every packet, then each strategy walks
its own packets); a smaller one is walked whole by the strategy most of its 32 got. Small batches
go whole because splitting them measured slower: on the small
scenes at 256x256 a batch walked by two strategies in two passes lost to the better single
strategy by up to 18%, where a packet's whole walk costs about a microsecond, while the
kitchen's 1024x1024 reflection batch (1,710 16x16 packets) walked 17% faster chosen packet by
packet than whole by the sample's majority (Ranged) (see the README). The packets are walked by
the chosen strategy's own copy of the one packet walk (``engine.packet.walk``), so their hits are
the other traversals' hits, bit for bit.

With ``trials = true`` a batch chosen packet by packet is also checked by timing
(``engine.packet.auto_trial``): the first time the plugin walks it, each group of at least 256
packets (those the rule gave Ranged, those it gave Partition) has about an eighth of its packets
walked by each strategy in four interleaved timed passes, and the rest of the group goes to the
faster one; the verdicts are kept by batch signature (ray kind, packets, rays) for the next
frame. It is off by default: measured on the 1024x1024 frames it left ``auto`` slower than the
better strategy in more rows than the rule alone (the module doc has the numbers).

Options (``[options.auto]``), each defaulting to the fitted value in
``engine/packet/auto_thresholds.json`` (``tools/fit_auto.py``):

- ``ranged_max_footprint``: packets at most this wide (and live enough) walk by Ranged;
- ``masked_max_footprint``: packets at most this wide (and live enough) walk by Masked
  (negative: never);
- ``min_live``: the least fraction of live lanes for Ranged or Masked;
- ``invalid_frustum``: the strategy for packets without a frustum;
- ``split_min_packets``: the fewest packets a batch whose sample is split must have to be chosen
  packet by packet (0: every such batch; a huge number: never), default SPLIT_MIN_PACKETS;
- ``split_min_share``: a batch chosen packet by packet is walked split only when the packets the
  smaller strategies got hold at least this share of it, else whole by the strategy most got
  (0: always split), default SPLIT_MIN_SHARE;
- ``trials``: check the per-packet choice by timed trials (default false: measured slower than
  the rule alone, see ``engine.packet.auto_trial``).

Statistics (``--stats``: ``extra.plugins.KIND.auto``): ``packets``, the packets walked by each
strategy, ``per_batch``, the same for every walk of a batch, in order (a shadow batch walked as a
trial of both ends, ``engine.render.shadow_order``, has one entry per group walked), and ``trials``, for each batch
whose groups were tried (in any earlier frame), one entry per group tried (kind, packets, group,
tried_packets, own_seconds, other_seconds, walked_by).
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import ConfigError
from engine.core.registry import register_traversal
from engine.packet.auto_limits import fitted_limits, limits_array
from engine.packet.auto_trial import TrialBook, apply_verdicts
from engine.packet.choose import LIMIT_NAMES
from engine.packet.plugin import PacketTraversal, walk_batch
from engine.packet.strategies import AUTO, CHOSEN_NAMES
from engine.packet.walk import choose_batch
from engine.core.types import thread_counters

#: ``split_min_packets``'s default, set between two measurements, not fitted: the split batches of
#: the 256x256 frames (at most 1,024 packets) walked faster whole, and the kitchen's 1024x1024
#: reflection batch (1,710 16x16 packets) walked 17% faster chosen packet by packet.
SPLIT_MIN_PACKETS = 1536
#: ``split_min_share``'s default, set between measurements, not fitted (1024x1024, 16x16 packets,
#: session 31, docs/auto-measurements.md): split, the kitchen's shadow batch (17% of its packets
#: Partition's) and erw6's reflections (7%) walked 4-7% slower than whole by Ranged, while the
#: museum's reflections (37%) walked 9% faster than both whole ways, and the kitchen's
#: reflections (44%) about as fast as the better. Splitting costs a second pass and packets
#: farther apart in each, which only a large enough share repays.
SPLIT_MIN_SHARE = 0.25


@register_traversal("auto")
class AutoTraversal(PacketTraversal):
    """Large packets walked by Ranged, Partition or Masked, chosen from measures of the packets."""

    strategy = AUTO
    OPTIONS = {**dict.fromkeys(LIMIT_NAMES), "split_min_packets": SPLIT_MIN_PACKETS,
               "split_min_share": SPLIT_MIN_SHARE, "trials": False}  # a limit None: fitted

    def __init__(self, split_min_packets=SPLIT_MIN_PACKETS, split_min_share=SPLIT_MIN_SHARE, trials=False,
                 **limits):
        if isinstance(split_min_packets, bool) or not isinstance(split_min_packets, int) or split_min_packets < 0:
            raise ConfigError(f"options.auto.split_min_packets must be an integer >= 0, got {split_min_packets!r}")
        if (isinstance(split_min_share, bool) or not isinstance(split_min_share, (int, float))
                or not 0.0 <= split_min_share <= 0.5):
            raise ConfigError(f"options.auto.split_min_share must be a number in 0..0.5, got {split_min_share!r}")
        self.split_min_share = float(split_min_share)
        if not isinstance(trials, bool):
            raise ConfigError(f"options.auto.trials must be true or false, got {trials!r}")
        self.split_min_packets = split_min_packets
        self.book = TrialBook() if trials else None  # this instance's verdicts only
        chosen = fitted_limits()
        chosen.update({name: value for name, value in limits.items() if value is not None})
        self.limits = chosen
        self._limits = limits_array(chosen)

    def _per_packet(self, packets) -> bool:
        """Whether a batch in ``packets`` whose sample is split is chosen packet by packet."""
        return len(packets.offsets) - 1 >= self.split_min_packets

    def choose(self, bvh, rays, packets, frusta) -> np.ndarray:
        """i8[K]: the strategy (``engine.packet.strategies`` number) each packet would be walked
        by, without walking (``packetrt show``, tests): the walk's own choice
        (``engine.packet.walk.choose_batch``), with the verdicts of trials already made on this
        batch (a batch not yet tried shows the rule's choice)."""
        offsets = np.ascontiguousarray(packets.offsets, np.int32)
        n_packets = offsets.shape[0] - 1
        valid = np.zeros(n_packets, np.bool_) if frusta is None else np.ascontiguousarray(frusta.valid, np.bool_)
        out = np.empty(n_packets, np.int8)
        _, whole = choose_batch(bvh.bmin, bvh.bmax, rays.org, rays.dir, rays.tmin, rays.tmax, offsets, valid,
                                self._limits, out, per_packet=self._per_packet(packets),
                                min_share=self.split_min_share)
        if whole < 0 and self.book is not None:
            apply_verdicts(out, self.book.verdicts(self.book.signature_of(rays, packets)) or {})
        return out

    def walk_recorded(self, bvh, tris, rays, packets, frusta, any_hit, hits, record, from_end=False):
        walk_batch(AUTO, bvh, tris, rays, packets, frusta, any_hit, hits.t, hits.prim, hits.u, hits.v,
                   record=record, from_end=from_end, limits=self._limits, per_packet=self._per_packet(packets), book=self.book,
                   min_share=self.split_min_share)

    def _run(self, bvh, tris, rays, packets, frusta, any_hit, out_t, out_prim, out_u, out_v, stats,
             from_end=False):
        choices = np.empty(len(packets.offsets) - 1, np.int8)
        walk_batch(AUTO, bvh, tris, rays, packets, frusta, any_hit, out_t, out_prim, out_u, out_v,
                   thread_counters(stats), limits=self._limits, choices=choices,
                   from_end=from_end, per_packet=self._per_packet(packets), book=self.book,
                   min_share=self.split_min_share)
        if stats is not None:
            trials = [] if self.book is None else self.book.trials_of(self.book.signature_of(rays, packets))
            add_choices(stats, choices, trials)

    def _walk_group(self, bvh, tris, rays, packets, frusta, any_hit, stats, from_end, chosen, visits):
        choices = np.empty(len(packets.offsets) - 1, np.int8)
        walk_batch(AUTO, bvh, tris, rays, packets, frusta, True, any_hit.t, any_hit.prim, any_hit.u, any_hit.v,
                   thread_counters(stats), limits=self._limits, choices=choices,
                   from_end=from_end, chosen=chosen, visits=visits,
                   per_packet=self._per_packet(packets), min_share=self.split_min_share)
        if stats is not None:
            add_choices(stats, choices[chosen >= 0])


def add_choices(stats, choices: np.ndarray, trials: list = ()) -> None:
    """Count one batch's choices (i8[K]) into stats.extra["auto"], with the trials that decided
    how its groups are walked (``engine.packet.auto_trial.TrialBook.trials_of``)."""
    per = np.bincount(choices, minlength=len(CHOSEN_NAMES))
    batch = {name: int(per[i]) for i, name in enumerate(CHOSEN_NAMES)}
    total = stats.extra.setdefault("auto", {"packets": dict.fromkeys(CHOSEN_NAMES, 0), "per_batch": []})
    for name, n in batch.items():
        total["packets"][name] += n
    total["per_batch"].append(batch)
    if trials:
        total.setdefault("trials", []).extend(trials)
