"""Tie-aware comparison of our answers with an oracle's.

Two answers for one ray *agree* when both miss, or both hit the same triangle at t within
tolerance. When they differ, the disagreement is a *tie* (an equally valid answer that
floating point may decide either way) when:

- both hit, at t within tolerance, and each hit point lies within a small distance of
  the other answer's triangle as well as its own: a hit on or next to an edge or vertex
  shared by or bordering both triangles (or on coincident, overlapping surfaces);
- both hit, and one of the hits lies at the very start of the segment (t = tmin within that
  distance): the ray starts on another surface, as a secondary ray leaving a corner does;
- one hits and the other misses, and the hit point lies within that distance of its
  triangle's boundary (the ray grazes an outer edge), or at the very ends of the ray's
  [tmin, tmax] segment.

Anything else is a *mismatch*. The distance is ``DISTANCE_ULPS`` float32 ulps of the
largest coordinate involved; t tolerance is ``T_RELATIVE`` of t plus that distance.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from engine.core.types import Hits, RayBatch, Triangles

DISTANCE_ULPS = 64.0
T_RELATIVE = 1e-4
F32_EPS = float(np.finfo(np.float32).eps)


class Comparison(NamedTuple):
    """Per-ray classification (bool[R] each, over live rays) and the worst t error on agreeing rays."""

    agree: np.ndarray
    tie: np.ndarray
    mismatch: np.ndarray
    max_abs_t_err: float


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """(distance to the triangle, distance to its boundary): f64[M] each, for f[M,3] inputs."""
    p, a, b, c = (np.asarray(x, np.float64) for x in (p, a, b, c))

    def segment(q0, q1):
        e = q1 - q0
        length2 = np.einsum("ij,ij->i", e, e)
        s = np.clip(np.einsum("ij,ij->i", p - q0, e) / np.where(length2 > 0, length2, 1), 0, 1)
        return np.linalg.norm(p - (q0 + s[:, None] * e), axis=1)

    edge = np.minimum(np.minimum(segment(a, b), segment(b, c)), segment(c, a))
    n = np.cross(b - a, c - a)
    area2 = np.einsum("ij,ij->i", n, n)
    safe = np.where(area2 > 0, area2, 1)
    # Barycentrics of the projection onto the plane: inside when all are >= 0.
    w1 = np.einsum("ij,ij->i", np.cross(p - a, c - a), n) / safe
    w2 = np.einsum("ij,ij->i", np.cross(b - a, p - a), n) / safe
    inside = (area2 > 0) & (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
    plane = np.abs(np.einsum("ij,ij->i", p - a, n)) / np.sqrt(safe)
    return np.where(inside, plane, edge), edge


def _tolerance(rays, idx, t):
    scale = np.maximum(np.abs(rays.org[idx]).max(axis=1),
                       np.abs(rays.org[idx] + np.nan_to_num(t, posinf=0)[:, None] * rays.dir[idx]).max(axis=1))
    return DISTANCE_ULPS * F32_EPS * np.maximum(scale, 1.0)


def _corners(tris, prim):
    return tris.v0[prim], tris.v1[prim], tris.v2[prim]


def _grazes(rays, idx, t, prim, tris, tol):
    """The hit (t, prim) of rays idx touches its triangle's boundary or the segment's ends."""
    p = rays.org[idx].astype(np.float64) + t[:, None] * rays.dir[idx]
    _, to_edge = point_triangle_distance(p, *_corners(tris, prim))
    speed = np.linalg.norm(rays.dir[idx], axis=1)
    at_end = (np.abs(t - rays.tmin[idx]) * speed <= tol) | (np.abs(t - rays.tmax[idx]) * speed <= tol + T_RELATIVE * t * speed)
    return (to_edge <= tol) | at_end


def compare_hits(rays: RayBatch, ours: Hits, oracle: Hits, tris: Triangles) -> Comparison:
    """Classify every live ray of a closest-hit query."""
    n = rays.org.shape[0]
    live = rays.tmin <= rays.tmax
    agree = np.zeros(n, bool)
    tie = np.zeros(n, bool)
    both_miss = live & (ours.prim < 0) & (oracle.prim < 0)
    agree |= both_miss
    speed = np.linalg.norm(rays.dir, axis=1)
    same = live & (ours.prim >= 0) & (ours.prim == oracle.prim)
    idx = np.flatnonzero(same)
    max_err = 0.0
    if idx.size:
        tol = _tolerance(rays, idx, ours.t[idx])
        err = np.abs(ours.t[idx].astype(np.float64) - oracle.t[idx]) * speed[idx]
        ok = err <= tol + T_RELATIVE * ours.t[idx] * speed[idx]
        agree[idx[ok]] = True
        if ok.any():
            max_err = float(np.abs(ours.t[idx[ok]].astype(np.float64) - oracle.t[idx[ok]]).max())
    both = np.flatnonzero(live & (ours.prim >= 0) & (oracle.prim >= 0) & (ours.prim != oracle.prim))
    if both.size:
        t_a, t_b = ours.t[both].astype(np.float64), oracle.t[both].astype(np.float64)
        tol = _tolerance(rays, both, np.maximum(t_a, t_b))
        close_t = np.abs(t_a - t_b) * speed[both] <= tol + T_RELATIVE * np.maximum(t_a, t_b) * speed[both]
        p_a = rays.org[both] + t_a[:, None] * rays.dir[both]
        p_b = rays.org[both] + t_b[:, None] * rays.dir[both]
        d_ab, _ = point_triangle_distance(p_a, *_corners(tris, oracle.prim[both]))
        d_ba, _ = point_triangle_distance(p_b, *_corners(tris, ours.prim[both]))
        tie[both[close_t & (d_ab <= tol) & (d_ba <= tol)]] = True
        # A ray whose origin lies on another surface (a secondary ray leaving a corner) may
        # report that surface at t = tmin or skip it: both are valid.
        start = rays.tmin[both].astype(np.float64)
        at_start = (np.abs(t_a - start) * speed[both] <= tol) | (np.abs(t_b - start) * speed[both] <= tol)
        tie[both[at_start]] = True
        # A ray through an edge or vertex of a closed surface: the nearer side hit it there, the
        # other slipped through to a farther surface -- the same event as a miss past such a
        # point (below). Embree does so on rays aimed at a capsule's or icosphere's vertices
        # (session 37: float64 puts the vertex first).
        nearer_ours = t_a < t_b
        ours_grazes = _grazes(rays, both, t_a, ours.prim[both], tris, tol)
        oracle_grazes = _grazes(rays, both, t_b, oracle.prim[both], tris, tol)
        tie[both[(nearer_ours & ours_grazes) | (~nearer_ours & oracle_grazes)]] = True
    for side, other in ((ours, oracle), (oracle, ours)):
        one = np.flatnonzero(live & (side.prim >= 0) & (other.prim < 0))
        if one.size:
            t = side.t[one].astype(np.float64)
            tie[one[_grazes(rays, one, t, side.prim[one], tris, _tolerance(rays, one, t))]] = True
    mismatch = live & ~agree & ~tie
    return Comparison(agree, tie, mismatch, max_err)


def compare_occlusion(rays: RayBatch, ours: np.ndarray, oracle: np.ndarray, tris: Triangles,
                      closest_ours: Hits, closest_oracle: Hits) -> Comparison:
    """Classify every live ray of an occlusion query. ``closest_*`` are closest-hit answers for
    the same rays (only read where the two occlusion answers differ): a differing answer is a
    tie when the occluding side's hit grazes an edge or an end of the segment."""
    n = rays.org.shape[0]
    live = rays.tmin <= rays.tmax
    agree = live & (ours == oracle)
    tie = np.zeros(n, bool)
    for side, closest in ((ours, closest_ours), (oracle, closest_oracle)):
        one = np.flatnonzero(live & side & ~agree & (closest.prim >= 0))
        if one.size:
            t = closest.t[one].astype(np.float64)
            tie[one[_grazes(rays, one, t, closest.prim[one], tris, _tolerance(rays, one, t))]] = True
    mismatch = live & ~agree & ~tie
    return Comparison(agree, tie, mismatch, 0.0)
