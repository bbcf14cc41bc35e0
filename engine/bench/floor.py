"""The per-ray floor of the packet traversals, measured: a frame's batches with the BVH walk
taken out.

Every packet traversal (simd, masked, ranged, partition) pays the same work per ray around its
walk: the frustum builder's pass over the rays, the adapter's checks and answer arrays
(``engine.packet.plugin.PacketTraversal``), ``load_packet`` (transpose to packet-local rows and
the watertight test's shear per ray), ``load_frustum`` and ``store_hits``. ``FloorTraversal``
runs exactly that -- the same adapter, the same helpers, the same decks of packets on the same
threads -- and nothing else, so its time on a cell's recorded batches is the part of the cell's
trace time that no traversal can remove (Amdahl's serial part of a packet-size speed-up).

It answers "no hit" for every ray, so it is not a traversal plugin and is never registered; the
benchmark runner (``engine.bench.runner``) alone uses it.
"""
from __future__ import annotations

from numba import njit, prange

from engine.packet.frustum_cull import load_frustum
from engine.packet.kernels import load_packet, longest_packet, packet_scratch, store_hits
from engine.packet.plugin import PacketTraversal
from engine.core.types import RAY_KINDS


@njit(cache=True, parallel=True)
def trace_floor(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
                counters):
    """Load and store every packet as the traversal kernels do, without walking the BVH (the
    packet traversal kernel signature, ``engine.packet.plugin``)."""
    n_packets = offsets.shape[0] - 1
    max_rays = longest_packet(offsets)
    for chunk in prange(n_chunks):
        rf, ri, near, fr, leaf_tris = packet_scratch(max_rays, 1)
        for k in range(chunk, n_packets, n_chunks):
            start = offsets[k]
            n = offsets[k + 1] - start
            load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
            load_frustum(planes, valid, k, fr)
            store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)


class FloorTraversal(PacketTraversal):
    """The packet traversals' per-ray work without the BVH walk (answers: no hit)."""

    kernel = trace_floor


def floor_tracer(renderer):
    """The renderer's ``Tracer`` with ``FloorTraversal`` for every kind (the same frustum
    builders), for ``engine.bench.runner.replay``: timed as the renderer times a traversal."""
    return renderer.tracer.with_traversal(dict.fromkeys(RAY_KINDS, FloorTraversal()))


def uses_packet_traversals(renderer) -> bool:
    """True when every ray kind of the renderer uses a packet traversal (the floor applies)."""
    return all(isinstance(renderer.traversal[k], PacketTraversal) for k in RAY_KINDS)
