"""``partition``: the packet walks the BVH with an in-place partitioned list of its live SIMD rays.

Overbeck, Ramamoorthi, Mark 2008, Section 3 -- the paper's new traversal, robust to degrading
coherence. The packet keeps a list of its SIMD ray indices. At each node (unless the packet
frustum rejects the box outright) partRays tests the first ``m`` listed rays against the box
and swaps those that hit to the front; their count is what the children see, pushed on the stack
with them. Partitions below a node only permute a prefix of its own range, so when the stack
unwinds to a sibling its ``m`` rays are still the first ``m`` of the list. At a leaf only the
live rays -- and of those only the lanes that hit the leaf box -- test the triangles the
frustum does not cull. Near child first, from the packet's direction signs.

Every live ray is tested at every node it reaches, so coherent packets pay more box tests than
``ranged``; incoherent ones (reflections, refractions) save many triangle tests.
"""
from __future__ import annotations

from engine.core.registry import register_traversal
from engine.packet.plugin import PacketTraversal
from engine.packet.strategies import PARTITION


@register_traversal("partition")
class PartitionTraversal(PacketTraversal):
    """Large packets with an in-place partitioned list of live SIMD rays (Overbeck et al. 2008)."""

    strategy = PARTITION
