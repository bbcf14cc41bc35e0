"""``embree``: Intel Embree through embreex, as a rendering backend.

The yardstick for every speed figure: the same rays, the same thread count (a thread
pool of numba's ``threads`` workers taking chunks of each batch; embreex releases the GIL),
driven as fast as embreex can be from Python: the batch's own arrays are passed as views
and the answers written straight into the caller's (``engine.core.embree_scene``). Ignores
the packet layout, frusta and our BVH: Embree builds its own. The Embree scene is built
once per triangle set and reused. Counters are not available (Embree does not expose
them); ``stats.extra["embree"]`` records version, robust flag and build time.

Options: ``robust`` (default true) sets Embree's robust (watertight) mode; false is
Embree's faster default mode, whose answers may differ from the reference on edges.
"""
from __future__ import annotations

import numba

from engine.core.embree_scene import EmbreeScene
from engine.core.errors import ConfigError
from engine.core.registry import register_traversal
from engine.core.types import check_answer_arrays


@register_traversal("embree")
class EmbreeTraversal:
    """Intel Embree (embreex), robust mode, same thread count as numba."""

    #: Frusta are not read: the tracer builds none for this traversal.
    uses_frusta = False

    OPTIONS = {"robust": True}
    #: Embree builds its own scene (``prepare``); the engine's BVH is not read.
    uses_bvh = False

    def __init__(self, robust=OPTIONS["robust"]):
        """``robust``: Embree's robust (watertight) mode; a bool, else ConfigError."""
        if not isinstance(robust, bool):
            raise ConfigError(f"options.embree: robust must be true or false, got {robust!r}")
        self.robust = robust
        self._scenes: dict = {}  # this instance's Embree scene, per triangle set

    def scene_for(self, tris) -> EmbreeScene:
        threads = numba.get_num_threads()
        key = (id(tris.v0), tris.v0.shape[0], self.robust, threads)
        entry = self._scenes.get(key)
        if entry is None or entry[0] is not tris.v0:
            self._scenes.clear()  # one scene at a time: renders do not interleave triangle sets
            entry = (tris.v0, EmbreeScene(tris, robust=self.robust, threads=threads))
            self._scenes[key] = entry
        return entry[1]

    def prepare(self, tris) -> float:
        """Build (or reuse) the Embree scene for ``tris``; returns Embree's build seconds."""
        return self.scene_for(tris).build_seconds

    def _record(self, scene, stats):
        if stats is not None:
            stats.extra["embree"] = {"version": scene.version, "embreex": scene.binding_version(),
                                     "robust": scene.robust, "build_seconds": scene.build_seconds}

    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        check_answer_arrays(rays.org.shape[0], hits.t, hits.prim, hits.u, hits.v)
        scene = self.scene_for(tris)
        scene.intersect_into(rays, hits.t, hits.prim, hits.u, hits.v)
        self._record(scene, stats)

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats):
        check_answer_arrays(rays.org.shape[0], occluded)
        scene = self.scene_for(tris)
        scene.occluded_into(rays, occluded)
        self._record(scene, stats)
