"""``masked``: the whole packet descends while any of its rays hits; lane masks at the leaves.

Overbeck, Ramamoorthi, Mark 2008, Section 3 (the classic packet traversal, Wald et al.): the
stack holds nodes only. On a pop, the packet's SIMD rays are tried in order until one hits the
box (the first one, then the packet frustum as early reject, then the rest); one hit sends the
whole packet into the children, near child first from the packet's direction signs. At a leaf
(unless the frustum rejects it) every SIMD ray tests the leaf box, and the lanes that hit it
test the triangles the frustum does not cull.

Inner nodes cost little while rays are coherent, but the packet is never narrowed: as
coherence falls it visits ever more nodes that most of its rays miss.
"""
from __future__ import annotations

from engine.core.registry import register_traversal
from engine.packet.plugin import PacketTraversal
from engine.packet.strategies import MASKED


@register_traversal("masked")
class MaskedTraversal(PacketTraversal):
    """Large packets that descend while any ray hits, lane masks at the leaves (Overbeck et al. 2008)."""

    strategy = MASKED
