"""``ranged``: the packet walks the BVH with the index range of its active SIMD rays.

Overbeck, Ramamoorthi, Mark 2008, Section 3 (after Wald et al.'s large-packet BVH traversal).
Each stack entry holds a node and ``ia``, the first SIMD ray that may still hit it. On a pop,
getFirstHit advances ``ia`` to the first SIMD ray that hits the node's box (trying ``ia``
itself first, then the packet frustum as early reject); no hit ends the subtree. At a leaf,
getLastHit scans back from the end for the last SIMD ray ``ie - 1`` that hits, and every ray in
[ia, ie) tests the leaf's triangles (those the frustum does not cull). Children are pushed far
first so the near one, chosen from the packet's direction signs, is popped first.

Cheap per node when rays are coherent (usually one box test decides); on incoherent rays the
range [ia, ie) fills with rays that miss the leaf, which ``partition`` avoids.
"""
from __future__ import annotations

from engine.core.registry import register_traversal
from engine.packet.plugin import PacketTraversal
from engine.packet.strategies import RANGED


@register_traversal("ranged")
class RangedTraversal(PacketTraversal):
    """Large packets with the active SIMD rays as an index range [ia, ie) (Overbeck et al. 2008)."""

    strategy = RANGED
