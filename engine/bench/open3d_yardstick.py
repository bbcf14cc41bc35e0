"""Open3D's ``RaycastingScene`` as the benchmark's second yardstick, on the very same batches.

Embree through embreex (the ``embree`` traversal) is the first yardstick; Open3D wraps its own
Embree build behind a different front end, so it says what a user of another widely used Python
library gets on the same rays. The scene, the thread count and the mapping of our segments
onto Open3D's queries are ``validation.open3d_oracle.Open3DOracle``'s (see its module doc):
origins moved to ``org + tmin * dir`` and tmin added back; a closest hit beyond ``tmax`` is a
miss; occlusion over a finite segment casts ``dir * (tmax - tmin)`` with ``tfar = 1``, over an
unbounded one ``dir`` with ``tfar = inf``; a one-point segment is occluded when a surface
passes through it; dead lanes (``tmax < tmin``) are not cast.

Driven as well as Open3D can be from Python: Open3D takes one f32[L,6] array of live rays
(origin, direction) per call, so a compiled kernel writes it in one pass over the batch and
Open3D reads it in place (``Tensor.from_numpy``, no copy); its answers are read in place
(``Tensor.numpy()``) and scattered into the caller's arrays by another kernel. (The oracle's
own query path, written for clarity, spends about as long in numpy as Open3D spends tracing;
it is not what is timed here.)

Threads: Open3D gets numba's thread count, as every other variant. Its per-call ``nthreads``
cannot give that: measured with Open3D 0.20 (per-thread CPU time from /proc), any
``nthreads > 0`` -- 1, 2, 3 or 4 -- keeps one thread busy, and only ``nthreads = 0`` ("all")
spreads the work. What does limit it is TBB's global cap, ``open3d.utility.set_max_threads``,
so each query runs with ``nthreads = 0`` under a cap of ``threads``, and the cap in force
before is put back after the call (``_capped``): nothing is left set between queries.

``Open3DTraversal`` has the traversal plugins' ``intersect`` / ``occluded`` signature so the
renderer's ``Tracer`` times it exactly as it times ours and Embree; ``Open3DYardstick`` measures
it once per distinct batch set, like ``engine.bench.runner.EmbreeYardstick``.
"""
from __future__ import annotations

from contextlib import contextmanager

import numba
import numpy as np
from numba import njit

from engine.bench.yardstick import replay_once
from engine.core.types import RAY_KINDS, RayBatch, check_answer_arrays, empty_hits

#: Segment classes of a ray (``segment_class``).
DEAD, FINITE, UNBOUNDED, POINT = 0, 1, 2, 3
NO_PRIMITIVE = np.uint32(0xFFFFFFFF)  # Open3D's "no hit" primitive id

#: At most this fraction of a kind's checked rays may disagree with the reference before
#: Open3D's rate for that kind is dropped (see ``open3d_rates``).
OPEN3D_MISMATCH_TOLERANCE = 1e-3


@njit(cache=True, nogil=True)
def segment_class(lo, hi):
    """DEAD (hi < lo, or a NaN segment), POINT (hi == lo), UNBOUNDED (hi - lo infinite) or FINITE."""
    reach = hi - lo
    if not (lo <= hi and reach >= 0):
        return DEAD
    if reach == 0:
        return POINT
    if np.isinf(reach):
        return UNBOUNDED
    return FINITE


@njit(cache=True, nogil=True)
def class_counts(tmin, tmax):
    """i64[4]: rays per segment class (DEAD, FINITE, UNBOUNDED, POINT); tmin, tmax f32[R]."""
    counts = np.zeros(4, np.int64)
    for i in range(tmin.shape[0]):
        counts[segment_class(tmin[i], tmax[i])] += 1
    return counts


@njit(cache=True, nogil=True)
def pack_rays(org, direction, tmin, tmax, classes, scale, out, index):
    """Open3D's rays for the rays whose segment class is in ``classes``, in batch order.

    org, direction: f32[R,3]; tmin, tmax: f32[R]; classes: bool[4] (by class); scale: the
    direction is multiplied by tmax - tmin (occlusion over a finite segment, tfar = 1);
    out: f32[L,6] (origin moved to org + tmin * dir, then the direction); index: i64[L],
    the batch row of each packed ray. Returns the number packed."""
    m = 0
    for i in range(tmin.shape[0]):
        lo, hi = tmin[i], tmax[i]
        if not classes[segment_class(lo, hi)]:
            continue
        s = hi - lo if scale else np.float32(1.0)
        for j in range(3):
            out[m, j] = org[i, j] + lo * direction[i, j]
            out[m, 3 + j] = direction[i, j] * s
        index[m] = i
        m += 1
    return m


@njit(cache=True, nogil=True)
def scatter_hits(index, tmin, tmax, t_hit, prim, uv, out_t, out_prim, out_u, out_v):
    """Open3D's closest hits of the packed rays into ours: a hit inside the segment gets
    t = t_hit + tmin, else the ray stays a miss.

    index: i64[L] batch rows; tmin, tmax: f32[R]; t_hit: f32[L]; prim: u32[L]; uv: f32[L,2];
    out_*: the caller's Hits arrays (R rays), already misses."""
    for j in range(index.shape[0]):
        i = index[j]
        t = t_hit[j]
        if prim[j] != NO_PRIMITIVE and np.isfinite(t) and t <= tmax[i] - tmin[i]:
            out_t[i] = t + tmin[i]
            out_prim[i] = np.int32(prim[j])
            out_u[i] = uv[j, 0]
            out_v[i] = uv[j, 1]


@njit(cache=True, nogil=True)
def scatter_flags(index, flags, out):
    """out[index[j]] = flags[j]; index: i64[L]; flags, out: bool."""
    for j in range(index.shape[0]):
        out[index[j]] = flags[j]


@njit(cache=True, nogil=True)
def scatter_touching(index, t_hit, out):
    """One-point segments: out[index[j]] = a surface passes through the point (t_hit <= 0)."""
    for j in range(index.shape[0]):
        out[index[j]] = t_hit[j] <= 0


def require_open3d(source: str) -> None:
    """Import Open3D now, before any cell runs; ConfigError naming the matrix and the fix if it cannot."""
    from engine.core.errors import ConfigError
    from validation.open3d_oracle import Open3DUnavailable, load_open3d

    try:
        load_open3d()
    except Open3DUnavailable as exc:
        raise ConfigError(f"{source}: open3d: {exc}; or set open3d = false to benchmark without it") from None


class Open3DTraversal:
    """Open3D ``RaycastingScene`` queries in the traversal plugins' signature (BVH, packets
    and frusta ignored), over the triangle set it was built for, ``threads`` Open3D threads."""

    name = "open3d"

    def __init__(self, tris, threads: int | None = None):
        from validation.open3d_oracle import Open3DOracle, load_open3d

        self.oracle = Open3DOracle(tris, threads=numba.get_num_threads() if threads is None else threads)
        self.tris, self.threads, self.version = tris, self.oracle.threads, self.oracle.version
        o3d = load_open3d()
        self._tensor = o3d.core.Tensor.from_numpy  # shares the array's memory
        self._utility = o3d.utility
        self._warm_up()

    @contextmanager
    def _capped(self):
        """Open3D's thread cap set to ``threads`` inside (queries pass nthreads = 0), restored after."""
        before = self._utility.get_max_threads()
        self._utility.set_max_threads(self.threads)
        try:
            yield
        finally:
            self._utility.set_max_threads(before)

    def _warm_up(self) -> None:
        """Both queries on one ray of each segment class: the kernels are compiled (or loaded from
        numba's cache) and Open3D commits its scene here, never inside a timed query."""
        n = 4  # finite, unbounded, one-point, dead
        rays = RayBatch(np.zeros((n, 3), np.float32), np.ones((n, 3), np.float32), np.ones((n, 3), np.float32),
                        np.array([0, 0, 1, 2], np.float32), np.array([1, np.inf, 1, 1], np.float32),
                        np.zeros(n, np.int32), np.ones((n, 3), np.float32), "primary")
        self.intersect(None, self.tris, rays, None, None, empty_hits(n), None)
        self.occluded(None, self.tris, rays, None, None, np.zeros(n, np.bool_), None)

    def _packed(self, rays, classes, scale: bool, n: int):
        """(f32[n,6] Open3D rays, i64[n] batch rows) of the rays of the given classes."""
        out, index = np.empty((n, 6), np.float32), np.empty(n, np.int64)
        wanted = np.zeros(4, np.bool_)
        wanted[list(classes)] = True
        pack_rays(rays.org, rays.dir, rays.tmin, rays.tmax, wanted, scale, out, index)
        return self._tensor(out), index

    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        """Closest hits of ``rays`` (R rays) into ``hits`` (Hits arrays of R)."""
        check_answer_arrays(rays.org.shape[0], hits.t, hits.prim, hits.u, hits.v)
        hits.t.fill(np.inf), hits.prim.fill(-1), hits.u.fill(0), hits.v.fill(0)
        counts = class_counts(rays.tmin, rays.tmax)
        live = int(counts[FINITE] + counts[UNBOUNDED] + counts[POINT])
        if live == 0:
            return
        tensor, index = self._packed(rays, (FINITE, UNBOUNDED, POINT), False, live)
        with self._capped():
            answer = self.oracle.scene.cast_rays(tensor, nthreads=0)
        scatter_hits(index, rays.tmin, rays.tmax, answer["t_hit"].numpy(), answer["primitive_ids"].numpy(),
                     answer["primitive_uvs"].numpy(), hits.t, hits.prim, hits.u, hits.v)

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats):
        """Occlusion of ``rays`` (R rays, any hit inside [tmin, tmax]) into ``occluded`` bool[R]."""
        check_answer_arrays(rays.org.shape[0], occluded)
        occluded.fill(False)
        counts = class_counts(rays.tmin, rays.tmax)
        scene = self.oracle.scene
        for cls, scale, tfar in ((FINITE, True, 1.0), (UNBOUNDED, False, float("inf"))):
            if counts[cls]:
                tensor, index = self._packed(rays, (cls,), scale, int(counts[cls]))
                with self._capped():
                    flags = scene.test_occlusions(tensor, tnear=0.0, tfar=tfar, nthreads=0)
                scatter_flags(index, flags.numpy(), occluded)
        if counts[POINT]:
            tensor, index = self._packed(rays, (POINT,), False, int(counts[POINT]))
            with self._capped():
                answer = scene.cast_rays(tensor, nthreads=0)
            scatter_touching(index, answer["t_hit"].numpy(), occluded)

    def describe(self) -> dict:
        return {"name": self.name, "version": self.version, "threads": self.threads}


class Open3DYardstick:
    """Open3D's seconds on a recorded batch set, measured once per distinct set (by digest),
    through the renderer's ``Tracer`` (timed as ours and Embree are: query + answer arrays)."""

    def __init__(self):
        self.digest, self.runs, self.answers = None, None, None
        self.traversal = None  # one Open3D scene per triangle set, reused across cells

    def tracer(self, renderer):
        """The renderer's triangles traced by Open3D for every kind (no frusta)."""
        if self.traversal is None or self.traversal.tris.v0 is not renderer.tris.v0 \
                or self.traversal.threads != renderer.threads:
            self.traversal = None  # one Open3D scene alive at a time
            self.traversal = Open3DTraversal(renderer.tris, threads=renderer.threads)
        return renderer.tracer.with_traversal(dict.fromkeys(RAY_KINDS, self.traversal), dict.fromkeys(RAY_KINDS))

    def seconds(self, renderer, recorder, repeat: int, timed_replays) -> tuple:
        """(``repeat`` dicts {kind: seconds}, last answers) of Open3D on exactly the recorded
        batches; ``timed_replays(batches, tracer, repeat)`` is the runner's timing loop."""
        # The untimed first query also lets Open3D commit (build) its scene, which it does lazily.
        return replay_once(self, renderer, recorder, repeat, timed_replays)

    def close(self) -> None:
        self.traversal = None


def open3d_rates(rates: dict, check: dict) -> dict:
    """Open3D's Mrays/s with the kinds whose answers disagree with the reference on more than
    OPEN3D_MISMATCH_TOLERANCE of their checked rays set to None (and "all" then too).

    Ours and Embree lose a kind's rate on a single mismatch: they claim exact answers. Open3D
    makes no watertightness promise for our rays (its own Embree build and settings), so a few
    disagreeing rays on edges and grazes are expected of it and say nothing about its speed:
    its rate is kept and the record's ``checks.open3d`` shows the count (the summary marks the
    rate). Beyond the tolerance the answers are not the same work -- a wrong driver, not a few
    edge rays -- and the rate is dropped like any other."""
    bad = [k for k in RAY_KINDS if check[k]["mismatches"] > OPEN3D_MISMATCH_TOLERANCE * max(check[k]["checked"], 1)]
    return {k: (None if k in bad or (k == "all" and bad) else v) for k, v in rates.items()}
