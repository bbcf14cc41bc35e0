"""Shared data contracts: named tuples of C-contiguous arrays, no logic.

Every plugin, kernel and tool in packetrt passes these around. They are plain
data so they can be unpacked straight into numba kernels. Shapes use
T = triangles, N = BVH nodes, P = primitive references, R = rays, K = packets.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Ray kinds, in the order the Whitted loop casts them.
RAY_KINDS = ("primary", "shadow", "reflection", "refraction")

#: Depth buckets of the per-depth counters; the BVH builder never goes deeper.
MAX_BVH_DEPTH = 64

#: Counter rows in ``Stats.counters``.
COUNTER_RAY_AABB, COUNTER_RAY_TRI, COUNTER_NODES = 0, 1, 2
COUNTER_NAMES = ("ray_aabb", "ray_tri", "nodes")


class Triangles(NamedTuple):
    """Triangle soup ready for intersection.

    v0, e1, e2, ng: f32[T,3]  first vertex, edges v1-v0 and v2-v0, unit geometric normal
                              (zero for a degenerate triangle).
    v1, v2: f32[T,3]          the exact other corners: the watertight test needs the real
                              vertices, since v0 + e1 is rounded and would open cracks.
    material: i32[T]          index into the scene's material table.
    normals: f32[T,3,3]       per-corner shading normals, or shape (0,3,3) when absent.
    uvs: f32[T,3,2]           per-corner texture coordinates, or shape (0,3,2) when absent.
    """

    v0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    ng: np.ndarray
    v1: np.ndarray
    v2: np.ndarray
    material: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray


class BVH(NamedTuple):
    """Flat bounding-volume hierarchy.

    bmin, bmax: f32[N,3]  node boxes.
    first: i32[N]         inner node (count == 0): index of the left child; the right child
                          is first + 1. Leaf: start of its range in ``prim``.
    count: i32[N]         0 for an inner node, else the number of primitives in the leaf.
    prim: i32[P]          triangle indices, each triangle exactly once.
    depth: int            deepest level (root = 0).
    build_seconds: float  wall time of the build (or refit).
    """

    bmin: np.ndarray
    bmax: np.ndarray
    first: np.ndarray
    count: np.ndarray
    prim: np.ndarray
    depth: int
    build_seconds: float


class RayBatch(NamedTuple):
    """Rays of one kind, ordered packet by packet.

    org, dir, inv_dir: f32[R,3]  origin, direction (not necessarily unit), 1/dir with zero
                                 components replaced by a huge finite value (never inf).
    tmin, tmax: f32[R]           valid segment; a dead lane has tmax < tmin.
    pixel: i32[R]                ancestral pixel (y * width + x), -1 for padding lanes.
    weight: f32[R,3]             colour weight carried from the camera.
    kind: str                    one of RAY_KINDS.
    """

    org: np.ndarray
    dir: np.ndarray
    inv_dir: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    pixel: np.ndarray
    weight: np.ndarray
    kind: str


class Packets(NamedTuple):
    """Packet boundaries over a RayBatch.

    offsets: i32[K+1]  packet k holds rays offsets[k] : offsets[k+1]; every packet length is
                       a multiple of 4 (whole 2x2 SIMD rays).
    size: int          n of the n x n screen tiles the packets came from.
    width, height: int the image the tiles cover (pixel = y * width + x).
    """

    offsets: np.ndarray
    size: int
    width: int
    height: int


def copied_batch(rays: RayBatch, packets: Packets) -> tuple:
    """(RayBatch, Packets) with arrays of their own. A renderer's observer gets views of its
    per-lane arrays, which later batches of the same frame overwrite (the next light's shadow
    rays, the generation after next): whoever keeps a batch past the call keeps a copy."""
    return (RayBatch(*(np.array(getattr(rays, f)) for f in RayBatch._fields[:-1]), rays.kind),
            packets._replace(offsets=np.array(packets.offsets)))


class Frusta(NamedTuple):
    """One bounding frustum per packet.

    planes: f32[K,4,4]  four side planes (nx, ny, nz, d); a point p is inside a plane when
                        n.p + d >= 0 (planes point inwards).
    valid: bool[K]      False = no frustum could be built; do not cull this packet.
    """

    planes: np.ndarray
    valid: np.ndarray


class Hits(NamedTuple):
    """Closest-hit answers.

    t: f32[R]     hit distance along dir (inf = miss).
    prim: i32[R]  triangle index (-1 = miss).
    u, v: f32[R]  barycentrics: hit = (1-u-v) v0 + u v1 + v v2.
    """

    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray


class Stats(NamedTuple):
    """Per-thread traversal counters, summed after a pass.

    counters: i64[threads, 3, MAX_BVH_DEPTH]  rows COUNTER_RAY_AABB, COUNTER_RAY_TRI,
              COUNTER_NODES, bucketed by the BVH depth at which the test happened
              (plugins without a BVH use bucket 0 or their own level index).
    extra: dict   plugin-specific numbers (for example the ray-space hierarchy's per-level
                  counts); plain Python values.
    """

    counters: np.ndarray
    extra: dict


def empty_hits(n: int) -> Hits:
    """Hits for ``n`` rays, all misses."""
    return Hits(
        t=np.full(n, np.inf, np.float32),
        prim=np.full(n, -1, np.int32),
        u=np.zeros(n, np.float32),
        v=np.zeros(n, np.float32),
    )


def check_answer_arrays(n_rays: int, *arrays) -> None:
    """Raise ValueError unless every answer array has one entry per ray.

    Kernels index answers by ray without bounds checks, so a short array would be written
    past its end: every traversal checks before it calls one.
    """
    lengths = [a.shape[0] for a in arrays]
    if any(length != n_rays for length in lengths):
        raise ValueError(f"answer arrays must have one entry per ray ({n_rays}), got {lengths}")


def new_stats(threads: int) -> Stats:
    """Zeroed counters for ``threads`` worker threads."""
    return Stats(np.zeros((max(threads, 1), 3, MAX_BVH_DEPTH), np.int64), {})


def thread_counters(stats: Stats | None):
    """``stats.counters`` for a kernel that counts into row ``numba.get_thread_id()`` (None
    without stats). Fewer rows than the threads numba runs now is a ValueError: such a kernel
    would write past the array's end (heap corruption, found in session 34 behind crashes at
    exit and wrong answers of tests that passed ``new_stats(1)`` to a two-thread traversal)."""
    if stats is None:
        return None
    import numba

    threads = numba.get_num_threads()
    if stats.counters.ndim != 3 or stats.counters.shape[0] < threads:
        raise ValueError(f"stats counters have {stats.counters.shape[0]} thread rows, fewer than the {threads} "
                         f"threads numba runs now: make them with new_stats(numba.get_num_threads())")
    return stats.counters


def stats_totals(stats: Stats) -> dict:
    """{"ray_aabb": n, "ray_tri": n, "nodes": n} summed over threads and depths."""
    summed = stats.counters.sum(axis=(0, 2))
    return {name: int(summed[i]) for i, name in enumerate(COUNTER_NAMES)}


def stats_by_depth(stats: Stats) -> dict:
    """{"ray_aabb": [n per depth], ...}, trailing zero depths trimmed."""
    per_depth = stats.counters.sum(axis=0)
    used = np.nonzero(per_depth.sum(axis=0))[0]
    last = int(used[-1]) + 1 if used.size else 0
    return {name: per_depth[i, :last].tolist() for i, name in enumerate(COUNTER_NAMES)}
