"""The packet walk's vocabulary: which strategy walks the BVH, and what a node visit came to.

The packet traversals of Overbeck, Ramamoorthi and Mark (2008) share one walk
(``engine.packet.walk``) and differ in the steps it takes at a node and at a leaf
(``engine.packet.steps``), chosen by the strategy number a plugin names:

- ``MASKED``: the whole packet descends while any SIMD ray hits; lane masks at the leaves.
- ``RANGED``: the packet carries the index of its first SIMD ray that may still hit.
- ``PARTITION``: the packet carries an in-place partitioned list of its SIMD rays that hit.
- ``SIMD``: each 2x2 SIMD ray walks alone (the small-packet baseline).
- ``AUTO``: each packet is walked by MASKED, RANGED or PARTITION, chosen per packet from cheap
  measures of its rays (``engine.packet.choose``).

``STRATEGIES`` maps each strategy's name (the paper's, which is also its traversal plugin's
config name) to its number.

A node visit ends in one of three outcomes: ``CULLED`` (the packet frustum rejected the box),
``MISSED`` (no live lane's segment meets the box) or ``ENTERED`` (the walk goes on into the
node's children or triangles).
"""
from __future__ import annotations

MASKED, RANGED, PARTITION, SIMD, AUTO = range(5)
N_STRATEGIES = 5

STRATEGIES = {"masked": MASKED, "ranged": RANGED, "partition": PARTITION, "simd": SIMD, "auto": AUTO}
#: The strategies ``AUTO`` chooses among, by number (index = strategy number).
CHOSEN_NAMES = ("masked", "ranged", "partition")

CULLED, MISSED, ENTERED = range(3)
