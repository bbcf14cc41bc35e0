"""Keeping the BVH current while the scene moves: the ``[accel] update`` policy, per frame.

- ``rebuild``: a fresh binned-SAH build every frame (the tree a static render of that frame
  would use; frames equal ``packetrt render --time t`` byte for byte).
- ``refit``: the first frame's topology kept for the whole path, boxes refitted
  (``engine.core.bvh_refit``): cheap, but the tree loosens as things move apart.
- ``auto``: rebuild when a build is cheap -- the last build took at most ``budget`` of the last
  frame's time -- else refit, then measure the refitted tree's SAH cost against the cost of the
  last build and rebuild past ``degrade`` times that (Wald, Boulos and Shirley 2007 rebuild a
  dynamic BVH when its quality has degraded; Lauterbach et al. 2006 use the same SAH test).
  Both tests are needed: the SAH cost assumes rays spread evenly over the scene, so it misses a
  tree that loosens where the camera looks (BART Museum's flying triangles: SAH +3.5%, trace
  +50%), and there a rebuild is cheap (5-6% of a frame); where a rebuild is dear (the kitchen's,
  a quarter of a frame) the SAH test holds the line.

One ``BVHKeeper`` per animation render: it holds the last tree, the cost that tree had when it
was built and the refit's level order, and nothing outside it.
"""
from __future__ import annotations

import time

import numpy as np

from engine.core.bvh import build_bvh
from engine.core.bvh_refit import refit_bvh, refit_levels, sah_cost
from engine.core.types import BVH, Triangles

UPDATE_POLICIES = ("rebuild", "refit", "auto")
#: What a frame records when no traversal of the config reads the BVH (Embree, the ray-space
#: hierarchy): the tree is then one leaf, only there to give the scene's bounds.
NO_TREE = "none"
#: ``auto`` rebuilds once the refitted tree's SAH cost exceeds this times the last build's.
DEFAULT_DEGRADE = 1.2
#: ``auto`` rebuilds every frame while the last build took at most this share of the last frame.
DEFAULT_BUDGET = 0.10


class BVHKeeper:
    """A BVH kept current for a moving triangle set (same triangles, same order, every frame).

    update: one of UPDATE_POLICIES; leaf_size, bins: the builder's settings; degrade: the
    ``auto`` threshold on the SAH cost ratio (> 1); budget: ``auto`` rebuilds while the last
    build took at most this share of the last frame (0: never for that reason); needs_tree:
    False when no traversal reads
    the BVH, so that no tree is built at all (a one-leaf BVH gives the scene bounds).
    """

    def __init__(self, update: str = "rebuild", *, leaf_size: int = 4, bins: int = 16,
                 degrade: float = DEFAULT_DEGRADE, budget: float = DEFAULT_BUDGET, needs_tree: bool = True):
        self.needs_tree = needs_tree
        if update not in UPDATE_POLICIES:
            raise ValueError(f"accel update must be one of {', '.join(UPDATE_POLICIES)}, got {update!r}")
        self.update_policy, self.leaf_size, self.bins, self.degrade = update, leaf_size, bins, degrade
        self.budget = budget
        self.build_seconds = 0.0   # wall time of the last build
        self.bvh: BVH | None = None
        self.built_cost = 0.0      # SAH cost of the last build, when it was built
        self.levels = None         # refit order of the last build's topology

    def _build(self, tris: Triangles) -> BVH:
        start = time.perf_counter()
        bvh = build_bvh(tris, leaf_size=self.leaf_size, bins=self.bins)
        self.levels = refit_levels(bvh.first, bvh.count) if self.update_policy != "rebuild" else None
        self.built_cost = sah_cost(bvh)
        self.build_seconds = time.perf_counter() - start
        return bvh

    def update(self, tris: Triangles, last_frame_seconds: float | None = None) -> tuple[BVH, dict]:
        """(the BVH for this frame's ``tris``, {"policy": "rebuild" | "refit" (what ran),
        "reason": why a rebuild ran ("first", "policy", "cheap", "degraded"), "sah_cost": the
        tree's SAH cost, "sah_ratio": that over the last build's, "seconds": the update's wall
        time}). ``last_frame_seconds``: the previous frame's time, for ``auto``'s budget."""
        start = time.perf_counter()
        if not self.needs_tree:
            bvh = bounds_only_bvh(tris)
            return bvh._replace(build_seconds=time.perf_counter() - start), {
                "policy": NO_TREE, "sah_cost": None, "sah_ratio": None, "seconds": time.perf_counter() - start}
        same_triangles = self.bvh is not None and self.bvh.prim.shape[0] == tris.v0.shape[0]
        cheap = (self.update_policy == "auto" and last_frame_seconds is not None
                 and self.build_seconds <= self.budget * last_frame_seconds)
        reason = "first" if not same_triangles else "policy" if self.update_policy == "rebuild" else \
            "cheap" if cheap else None
        if reason:
            bvh, ran = self._build(tris), "rebuild"
            cost = self.built_cost
        else:
            bvh, ran = refit_bvh(self.bvh, tris, self.levels), "refit"
            cost = sah_cost(bvh)
            if self.update_policy == "auto" and cost > self.degrade * self.built_cost:
                bvh, ran, reason = self._build(tris), "rebuild", "degraded"
                cost = self.built_cost
        self.bvh = bvh
        seconds = time.perf_counter() - start
        return bvh._replace(build_seconds=seconds), {
            "policy": ran, "reason": reason, "sah_cost": round(cost, 4),
            "sah_ratio": round(cost / self.built_cost, 4) if self.built_cost > 0 else 1.0, "seconds": seconds}


def bounds_only_bvh(tris: Triangles) -> BVH:
    """A BVH of one leaf holding every triangle: the scene box for frustum builders, for
    configs whose traversals read no tree."""
    n = tris.v0.shape[0]
    lo = np.minimum(np.minimum(tris.v0.min(0), tris.v1.min(0)), tris.v2.min(0))
    hi = np.maximum(np.maximum(tris.v0.max(0), tris.v1.max(0)), tris.v2.max(0))
    return BVH(lo[None].astype(np.float32), hi[None].astype(np.float32), np.zeros(1, np.int32),
               np.full(1, n, np.int32), np.arange(n, dtype=np.int32), 0, 0.0)
