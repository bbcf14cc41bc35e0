"""``rayspace`` on the device: the ray-space hierarchy of Roger, Assarsson and Holzschuch (2007)
built for every generation on the GPU, as the CPU plugin (``traversals/rayspace.py``) builds it
for every batch, with the same math compiled as device twins.

What runs per call (``DeviceRaySpace.closest`` / ``occluded`` over a queue of n rays):

- ``hierarchy``: rays grouped by 2x2 pixel block (atomic counts, a stable scan, atomic slots,
  then each block sorted by ray id: the CPU's slot order); leaves, then one launch per level
  merging four nodes (or a block's slots) into their parent up to the root; triangle spheres
  and the test's absolute slack.
- ``stream``: per triangle batch, the (node, triangle) stream from the root down: per level
  one launch (children against the triangle's sphere, survivors appended by one atomic per
  block) and one count read back.
- ``final``: the watertight test of every final (ray, triangle) pair; the closest hit per ray by
  an atomic min of t, then of the index among the pairs at that t, then one exact recompute.

Statistics (``DeviceRaySpace.stats``, summed over calls; ``last``: the last call's), with the
CPU plugin's keys, lists indexed by level (0 = rays, last = root): ``pairs_before`` (child
slots before compaction), ``pairs_after``, ``cone_sphere_tests``, ``candidates`` (final
(ray, triangle) tests), ``candidates_per_ray``, ``rays`` (live), ``triangles``, ``batches``,
``retries``, ``peak_pairs``, ``reversed_batches``, ``calls``, ``levels``.

Shadow rays are reversed to leave the light when the caller names the light point
(``occluded(..., light=position)``); otherwise they are indexed forward, as other rays.
"""
from engine.gpu.rayspace.traversal import DeviceRaySpace

__all__ = ["DeviceRaySpace"]
