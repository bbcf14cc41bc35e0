"""Embree through embreex: one committed scene per triangle set, queried from a thread pool.

Shared by the ``embree`` traversal (a rendering backend) and ``validation.oracle`` (the
ground truth). embreex releases the GIL inside a query, so ``threads`` pool workers each
answer one chunk of rays in parallel: the same thread count as the numba traversals.

embreex takes no per-ray tnear, so a ray with tmin > 0 is moved to org + tmin * dir with
tfar = tmax - tmin, and tmin is added back to the answer.
"""
from __future__ import annotations

import re
import time
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata

import numpy as np

from engine.core.types import Hits, RayBatch, Triangles

EMBREE_TFAR_MAX = np.float32(1e37)  # embreex's own "no limit"


def _new_device():
    """(EmbreeDevice, Embree library version); the device's str() is "Embree version: X.Y.Z"."""
    from embreex import rtcore

    device = rtcore.EmbreeDevice()
    match = re.search(r"(\d+\.\d+\.\d+)", str(device))
    return device, (match.group(1) if match else "unknown")


def library_version() -> str:
    """The Embree library's own version (not the binding's), e.g. "3.13.5"."""
    return _new_device()[1]


class EmbreeScene:
    """A committed Embree scene over ``tris`` (robust mode by default).

    intersect(rays) -> Hits;  occluded(rays) -> bool[R].  ``build_seconds`` is Embree's
    scene build time, ``version`` its library version, ``robust`` whether
    RTC_SCENE_FLAG_ROBUST is set.
    """

    _device = None
    _version = "unknown"

    def __init__(self, tris: Triangles, robust: bool = True, threads: int = 1):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        if EmbreeScene._device is None:
            EmbreeScene._device, EmbreeScene._version = _new_device()
        start = time.perf_counter()
        self.scene = rtcore_scene.EmbreeScene(EmbreeScene._device, robust=robust)
        corners = np.ascontiguousarray(np.stack([tris.v0, tris.v1, tris.v2], axis=1), np.float32)
        self.mesh = TriangleMesh(self.scene, corners)
        # embreex commits lazily on the first query: force it so the build is timed here.
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
        self.build_seconds = time.perf_counter() - start
        self.robust = robust
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    @property
    def version(self) -> str:
        return EmbreeScene._version

    @staticmethod
    def binding_version() -> str:
        try:
            return metadata.version("embreex")
        except metadata.PackageNotFoundError:
            return "unknown"

    def _query(self, rays: RayBatch, closest: bool):
        live = np.flatnonzero(rays.tmin <= rays.tmax)
        tmin = rays.tmin[live]
        org = rays.org[live] + tmin[:, None] * rays.dir[live]
        dirs = np.ascontiguousarray(rays.dir[live])
        tfar = np.minimum(rays.tmax[live] - tmin, EMBREE_TFAR_MAX).astype(np.float32)
        org = np.ascontiguousarray(org, np.float32)
        chunks = np.array_split(np.arange(len(live)), self.threads) if len(live) else []

        def run(index):
            return self.scene.run(org[index], dirs[index], dists=tfar[index].copy(),
                                  query="INTERSECT" if closest else "OCCLUDED",
                                  output=1 if closest else None)

        answers = list(self._pool.map(run, chunks)) if self._pool else [run(c) for c in chunks]
        return live, tmin, chunks, answers

    def intersect(self, rays: RayBatch) -> Hits:
        n = rays.org.shape[0]
        hits = Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int32),
                    np.zeros(n, np.float32), np.zeros(n, np.float32))
        live, tmin, chunks, answers = self._query(rays, closest=True)
        for index, answer in zip(chunks, answers):
            rows = live[index]
            prim = answer["primID"].astype(np.int32)
            hit = prim >= 0
            hits.prim[rows[hit]] = prim[hit]
            hits.t[rows[hit]] = answer["tfar"][hit] + tmin[index][hit]
            hits.u[rows[hit]] = answer["u"][hit]
            hits.v[rows[hit]] = answer["v"][hit]
        return hits

    def occluded(self, rays: RayBatch) -> np.ndarray:
        out = np.zeros(rays.org.shape[0], np.bool_)
        live, _, chunks, answers = self._query(rays, closest=False)
        for index, answer in zip(chunks, answers):
            out[live[index]] = np.asarray(answer) >= 0
        return out

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=False)
