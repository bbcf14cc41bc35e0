"""Embree through embreex: one committed scene per triangle set, queried from a thread pool.

Shared by the ``embree`` traversal (a rendering backend and the benchmark's yardstick) and
``validation.oracle`` (the ground truth). Driven as fast as embreex allows from Python:

- No copies of the rays. ``EmbreeScene.run`` takes f32[n,3] views, strided or not, so each
  worker passes slices of the batch's own ``org`` and ``dir``; only the segment lengths
  (``tfar``, f32 per ray of its chunk) are written, by a compiled kernel.
- embreex releases the GIL inside ``run``, so ``threads`` pool workers each answer chunks of
  the batch in parallel (the same thread count as the numba traversals). A batch is cut into
  one chunk per worker (none under ``MIN_CHUNK`` rays) and, when each keeps at least
  ``BALANCE_CHUNK`` rays, into up to ``CHUNKS_PER_THREAD`` per worker, taken from a shared
  queue, so a worker that drew cheap rays takes another chunk instead of idling. (Measured on
  the kitchen's rays: more chunks help the big primary and shadow batches; on batches of a
  few thousand rays each extra call costs more than the balance gains.)
- Everything a worker does besides ``run`` -- segment lengths before, answers into the
  caller's arrays after -- is a ``nogil`` numba kernel over its own chunk, so no step of a
  query is serial except handing out the chunks.

Segments: embreex has no per-ray tnear (it casts from t = 0) but takes a per-ray tfar, which
it overwrites with the hit distance. A live ray gets tfar = tmax - tmin (at most
``EMBREE_TFAR_MAX``, embreex's own "no limit"); when tmin is 0 -- every ray the Whitted loop
casts -- that is all. A chunk holding a live ray with tmin != 0 is moved to
org + tmin * dir (a scratch copy of that chunk only) and tmin is added back to the hit
distance. A dead lane (tmax < tmin, or NaN) gets tfar = -1, which Embree culls at once, and
its answer is written as a miss / not occluded whatever embreex reports (it reports a
negative tfar as occluded).
"""
from __future__ import annotations

import re
import time
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata

import numpy as np
from numba import njit

from engine.core.types import Hits, RayBatch, Triangles

EMBREE_TFAR_MAX = np.float32(1e37)  # embreex's own "no limit"
#: At most this many chunks per worker (load balance against per-call cost) ...
CHUNKS_PER_THREAD = 4
#: ... and more than one per worker only when each keeps at least this many rays.
BALANCE_CHUNK = 16384
#: No chunk is smaller than this many rays (a call costs some microseconds of Python).
MIN_CHUNK = 2048


@njit(cache=True, nogil=True)
def segment_lengths(tmin, tmax, tfar):
    """tfar[i] = min(tmax - tmin, EMBREE_TFAR_MAX) for a live ray, -1 for a dead lane.

    tmin, tmax, tfar: f32[n]. Returns True when some live ray has tmin != 0 (its origin must
    be moved along the ray before Embree casts it from t = 0)."""
    shifted = False
    far = np.float32(EMBREE_TFAR_MAX)
    for i in range(tmin.shape[0]):
        lo, hi = tmin[i], tmax[i]
        if lo <= hi:
            tfar[i] = min(hi - lo, far)
            if lo != 0:
                shifted = True
        else:
            tfar[i] = np.float32(-1.0)
    return shifted


@njit(cache=True, nogil=True)
def moved_origins(org, direction, tmin, tmax, out):
    """out[i] = org[i] + tmin[i] * dir[i] for a live ray, org[i] for a dead lane.

    org, direction, out: f32[n,3]; tmin, tmax: f32[n]."""
    for i in range(org.shape[0]):
        s = tmin[i] if tmin[i] <= tmax[i] else np.float32(0.0)
        for j in range(3):
            out[i, j] = org[i, j] + s * direction[i, j]


@njit(cache=True, nogil=True)
def closest_answers(tmin, tmax, tfar, prim, u, v, out_t, out_prim, out_u, out_v):
    """Embree's closest hits into ours: t = tfar + tmin where a live ray hit, else a miss.

    tmin, tmax, tfar, u, v: f32[n]; prim: i32[n] (-1 = miss); out_*: the caller's Hits
    arrays for the same n rays (t f32, prim i32, u f32, v f32)."""
    for i in range(tmin.shape[0]):
        if tmin[i] <= tmax[i] and prim[i] >= 0:
            out_t[i] = tfar[i] + tmin[i]
            out_prim[i] = prim[i]
            out_u[i] = u[i]
            out_v[i] = v[i]
        else:
            out_t[i] = np.inf
            out_prim[i] = -1
            out_u[i] = 0.0
            out_v[i] = 0.0


@njit(cache=True, nogil=True)
def occlusion_answers(tmin, tmax, answer, out):
    """out[i] = live ray i is occluded; answer: embreex's i32[n] (>= 0 = occluded); out: bool[n]."""
    for i in range(tmin.shape[0]):
        out[i] = tmin[i] <= tmax[i] and answer[i] >= 0


def chunk_bounds(n: int, threads: int) -> list:
    """[(start, stop)] cutting n rays into equal chunks in order: one per thread (fewer when
    that would leave one under MIN_CHUNK rays; a single chunk when n is small), up to
    CHUNKS_PER_THREAD per thread when each keeps at least BALANCE_CHUNK rays."""
    if n == 0:
        return []
    parts = min(threads, max(1, n // MIN_CHUNK))
    if parts == threads:
        parts = threads * max(1, min(CHUNKS_PER_THREAD, n // (threads * BALANCE_CHUNK)))
    edges = np.linspace(0, n, parts + 1).astype(np.int64)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _new_device():
    """(EmbreeDevice, Embree library version); the device's str() is "Embree version: X.Y.Z"."""
    from embreex import rtcore

    device = rtcore.EmbreeDevice()
    match = re.search(r"(\d+\.\d+\.\d+)", str(device))
    return device, (match.group(1) if match else "unknown")


def library_version() -> str:
    """The Embree library's own version (not the binding's), e.g. "3.13.5"."""
    return _new_device()[1]


def _f32(array) -> np.ndarray:
    """``array`` as float32, without a copy when it already is."""
    return np.asarray(array, dtype=np.float32)


class EmbreeScene:
    """A committed Embree scene over ``tris`` (robust mode by default).

    intersect(rays) -> Hits;  occluded(rays) -> bool[R];  intersect_into / occluded_into write
    into the caller's arrays instead.  ``build_seconds`` is Embree's scene build time,
    ``version`` its library version, ``robust`` whether RTC_SCENE_FLAG_ROBUST is set,
    ``threads`` the pool's workers.
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
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="embree") if self.threads > 1 else None
        self._warm_up()

    def _warm_up(self) -> None:
        """Both queries on two rays (one moved by tmin, one dead): the kernels are compiled (or
        loaded from numba's cache) here, with the scene's build, never inside a timed query."""
        zeros, ones = np.zeros(2, np.float32), np.ones(2, np.float32)
        rays = RayBatch(np.zeros((2, 3), np.float32), np.ones((2, 3), np.float32), np.ones((2, 3), np.float32),
                        np.array([0.5, 1.0], np.float32), np.array([1.0, 0.0], np.float32),
                        np.zeros(2, np.int32), np.ones((2, 3), np.float32), "primary")
        self.intersect_into(rays, zeros.copy(), np.zeros(2, np.int32), zeros.copy(), ones.copy())
        self.occluded_into(rays, np.zeros(2, np.bool_))

    @property
    def version(self) -> str:
        return EmbreeScene._version

    @staticmethod
    def binding_version() -> str:
        try:
            return metadata.version("embreex")
        except metadata.PackageNotFoundError:
            return "unknown"

    def _each_chunk(self, n: int, work) -> None:
        """work(start, stop) over the chunks of n rays, on the pool's workers (or here)."""
        chunks = chunk_bounds(n, self.threads)
        if self._pool is None or len(chunks) == 1:
            for a, b in chunks:
                work(a, b)
            return
        for future in [self._pool.submit(work, a, b) for a, b in chunks]:
            future.result()  # re-raises a worker's exception here

    def _cast(self, org, direction, tmin, tmax, a: int, b: int, closest: bool):
        """(embreex's answer, tfar f32[b-a]) for rays a:b: views of the caller's arrays, the
        origins moved by tmin only when some live ray of the chunk has tmin != 0."""
        tfar = np.empty(b - a, np.float32)
        o, d = org[a:b], direction[a:b]
        if segment_lengths(tmin[a:b], tmax[a:b], tfar):
            o = np.empty((b - a, 3), np.float32)
            moved_origins(org[a:b], d, tmin[a:b], tmax[a:b], o)
        if closest:
            return self.scene.run(o, d, dists=tfar, query="INTERSECT", output=1), tfar
        return self.scene.run(o, d, dists=tfar, query="OCCLUDED"), tfar

    def intersect_into(self, rays: RayBatch, t, prim, u, v) -> None:
        """Closest hits of ``rays`` (R rays) into t f32[R] (inf = miss), prim i32[R] (-1),
        u, v f32[R] (0 on a miss)."""
        org, direction, tmin, tmax = _f32(rays.org), _f32(rays.dir), _f32(rays.tmin), _f32(rays.tmax)

        def work(a, b):
            answer, tfar = self._cast(org, direction, tmin, tmax, a, b, closest=True)
            closest_answers(tmin[a:b], tmax[a:b], tfar, answer["primID"], answer["u"], answer["v"],
                            t[a:b], prim[a:b], u[a:b], v[a:b])

        self._each_chunk(org.shape[0], work)

    def occluded_into(self, rays: RayBatch, out) -> None:
        """Occlusion of ``rays`` (R rays: any hit inside [tmin, tmax]) into out bool[R]."""
        org, direction, tmin, tmax = _f32(rays.org), _f32(rays.dir), _f32(rays.tmin), _f32(rays.tmax)

        def work(a, b):
            answer, _ = self._cast(org, direction, tmin, tmax, a, b, closest=False)
            occlusion_answers(tmin[a:b], tmax[a:b], answer, out[a:b])

        self._each_chunk(org.shape[0], work)

    def intersect(self, rays: RayBatch) -> Hits:
        """Closest hits of ``rays`` (R rays) as new Hits arrays."""
        n = rays.org.shape[0]
        hits = Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int32),
                    np.zeros(n, np.float32), np.zeros(n, np.float32))
        self.intersect_into(rays, *hits)
        return hits

    def occluded(self, rays: RayBatch) -> np.ndarray:
        """Occlusion of ``rays`` (R rays) as a new bool[R]."""
        out = np.zeros(rays.org.shape[0], np.bool_)
        self.occluded_into(rays, out)
        return out

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=False)
