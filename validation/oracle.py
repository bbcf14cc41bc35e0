"""EmbreeOracle: Embree's closest-hit and occlusion answers on any RayBatch (ground truth)."""
from __future__ import annotations

import numba

from engine.core.embree_scene import EmbreeScene
from engine.core.types import Hits, RayBatch, Triangles


class EmbreeOracle:
    """Ground truth from Intel Embree in robust (watertight) mode.

    intersect(rays) -> Hits; occluded(rays) -> bool[R]; ``describe()`` gives
    {"name", "version", "robust"} for reports.
    """

    name = "embree"

    def __init__(self, tris: Triangles, robust: bool = True):
        self.scene = EmbreeScene(tris, robust=robust, threads=numba.get_num_threads())

    def intersect(self, rays: RayBatch) -> Hits:
        return self.scene.intersect(rays)

    def occluded(self, rays: RayBatch):
        return self.scene.occluded(rays)

    def describe(self) -> dict:
        return {"name": self.name, "version": self.scene.version, "embreex": self.scene.binding_version(),
                "robust": self.scene.robust}
