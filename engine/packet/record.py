"""A packet walk's record: every node visit, in the order the walk made them.

``engine.packet.walk`` writes one when given a ``PacketRecord`` (``record=None`` compiles a
kernel without any of it), for ``packetrt show`` (``engine.debug.packet_trace``). The walk of
a batch runs packets on several threads, so a record is kept for batches of one packet. A
record without room keeps nothing, not even the count: it is what a walk that counts but does
not record is given (``engine.packet.walk.instrumented``).

    visits: i32[V, 4]  per visit the columns NODE, DEPTH, OUTCOME (``engine.packet.strategies``:
                       CULLED, MISSED, ENTERED) and LANES (live lanes whose segment met the box)
    count: i64[1]      visits made; when more than V, only the first V were kept
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

NODE, DEPTH, OUTCOME, LANES = range(4)


class PacketRecord(NamedTuple):
    visits: np.ndarray
    count: np.ndarray


def new_record(capacity: int) -> PacketRecord:
    """An empty record with room for ``capacity`` visits."""
    return PacketRecord(np.zeros((capacity, 4), np.int32), np.zeros(1, np.int64))


def kept_visits(record: PacketRecord) -> np.ndarray:
    """i32[count, 4], the visits made; ValueError when the record ran out of room."""
    count = int(record.count[0])
    if count > record.visits.shape[0]:
        raise ValueError(f"the record holds {record.visits.shape[0]} visits, the walk made {count}")
    return record.visits[:count]


@njit(cache=True, inline="always")
def record_visit(record, node, depth, outcome, lanes):
    """Append one visit (see the module doc)."""
    # Unpacked, not read by attribute: inside a prange, numba 0.68 loses the stores made
    # through a named tuple's attribute (``record.visits[i] = ...``).
    visits, count = record
    i = count[0]
    if i < visits.shape[0]:
        visits[i, NODE] = node
        visits[i, DEPTH] = depth
        visits[i, OUTCOME] = outcome
        visits[i, LANES] = lanes
    count[0] = i + 1
