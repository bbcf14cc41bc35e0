"""``simd``: every 2x2 SIMD ray walks the BVH on its own (the paper's "2x2 SIMD" baseline).

Overbeck, Ramamoorthi, Mark 2008, Section 6: the small-packet reference the large packets are
measured against. Packets only group the SIMD rays (and share a frustum): each SIMD ray has its
own stack; on a pop its four lanes test the box together, and the node is skipped when none
hits (or when the packet frustum misses the box, tested first). At a leaf the lanes that hit
the box test the triangles the frustum does not cull. Near child first from the packet's
direction signs.
"""
from __future__ import annotations

from engine.core.registry import register_traversal
from engine.packet.plugin import PacketTraversal
from engine.packet.strategies import SIMD


@register_traversal("simd")
class SimdTraversal(PacketTraversal):
    """Each 2x2 SIMD ray of a packet traverses alone: the small-packet baseline (Overbeck et al. 2008)."""

    strategy = SIMD
