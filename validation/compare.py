"""Tie-aware comparison of our answers with an oracle's.

Two answers for one ray *agree* when both miss, or both hit the same triangle at t within
tolerance and at barycentrics (u, v) naming points on it within the same distance. When they differ, the disagreement is a *tie* (an equally valid answer that
floating point may decide either way) when:

- both hit, at t within tolerance, and each hit point lies within a small distance of
  the other answer's triangle as well as its own: a hit on or next to an edge or vertex
  shared by or bordering both triangles (or on coincident, overlapping surfaces);
- both hit, and one of the hits lies at the very start of the segment (t = tmin within that
  distance): the ray starts on another surface, as a secondary ray leaving a corner does;
- one hits and the other misses, and the hit point lies within that distance of its
  triangle's boundary (the ray grazes an outer edge), or at the very ends of the ray's
  [tmin, tmax] segment.

Every rule first asks that our hit (the first answer) is a real one: its point lies on its own
triangle and inside the segment, within the same tolerances. A hit on a triangle the ray never
meets, or at t = tmin on a surface the origin is not on, is a mismatch however close its t.
And a miss (or a farther hit) where the other side hit an *interior* edge -- one shared with a
single other triangle, the two lying on opposite sides of the ray -- or a vertex whose fan of
triangles closes around the ray is a crack, not a graze: a watertight test hits one of them.
Only a hit on an outer edge, or on an edge or vertex the ray touches from outside (a
silhouette), makes a miss a tie.

Anything else is a *mismatch*. The distance is ``DISTANCE_ULPS`` float32 ulps of the
largest coordinate involved; t tolerance is ``T_RELATIVE`` of t plus that distance.
"""
from __future__ import annotations

import math
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


def point_segment_distance(p: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """f64[M]: distance from points p to segments q0-q1, all f64[M,3]."""
    e = q1 - q0
    length2 = np.einsum("ij,ij->i", e, e)
    s = np.clip(np.einsum("ij,ij->i", p - q0, e) / np.where(length2 > 0, length2, 1), 0, 1)
    return np.linalg.norm(p - (q0 + s[:, None] * e), axis=1)


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """(distance to the triangle, distance to its boundary): f64[M] each, for f[M,3] inputs."""
    p, a, b, c = (np.asarray(x, np.float64) for x in (p, a, b, c))
    edge = np.minimum(np.minimum(point_segment_distance(p, a, b), point_segment_distance(p, b, c)),
                      point_segment_distance(p, c, a))
    n = np.cross(b - a, c - a)
    area2 = np.einsum("ij,ij->i", n, n)
    safe = np.where(area2 > 0, area2, 1)
    # Barycentrics of the projection onto the plane: inside when all are >= 0.
    w1 = np.einsum("ij,ij->i", np.cross(p - a, c - a), n) / safe
    w2 = np.einsum("ij,ij->i", np.cross(b - a, p - a), n) / safe
    inside = (area2 > 0) & (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
    plane = np.abs(np.einsum("ij,ij->i", p - a, n)) / np.sqrt(safe)
    return np.where(inside, plane, edge), edge


def barycentric_distance(tris, prim, u_a, v_a, u_b, v_b) -> np.ndarray:
    """f64[M]: distance between the points (u_a, v_a) and (u_b, v_b) name on triangles prim
    (point = v0 + u e1 + v e2, the convention of Embree, Open3D and packetrt's kernels)."""
    e1 = np.asarray(tris.e1[prim], np.float64)
    e2 = np.asarray(tris.e2[prim], np.float64)
    du = (np.asarray(u_a, np.float64) - u_b)[:, None]
    dv = (np.asarray(v_a, np.float64) - v_b)[:, None]
    return np.linalg.norm(du * e1 + dv * e2, axis=1)


def _tolerance(rays, idx, t):
    scale = np.maximum(np.abs(rays.org[idx]).max(axis=1),
                       np.abs(rays.org[idx] + np.nan_to_num(t, posinf=0)[:, None] * rays.dir[idx]).max(axis=1))
    return DISTANCE_ULPS * F32_EPS * np.maximum(scale, 1.0)


def _corners(tris, prim):
    return tris.v0[prim], tris.v1[prim], tris.v2[prim]


def _at_segment_end(rays, idx, t, tol):
    speed = np.linalg.norm(rays.dir[idx], axis=1)
    return (np.abs(t - rays.tmin[idx]) * speed <= tol) | (np.abs(t - rays.tmax[idx]) * speed <= tol + T_RELATIVE * t * speed)


def _grazes(rays, idx, t, prim, tris, tol):
    """The hit (t, prim) of rays idx touches its triangle's boundary or the segment's ends."""
    p = rays.org[idx].astype(np.float64) + t[:, None] * rays.dir[idx]
    _, to_edge = point_triangle_distance(p, *_corners(tris, prim))
    return (to_edge <= tol) | _at_segment_end(rays, idx, t, tol)


def is_real_hit(rays, idx, t, prim, tris, u=None, v=None):
    """bool[M]: hit (t f64[M], prim i32[M]) of rays idx lies on its own triangle and inside the
    ray's [tmin, tmax], within the distance tolerance plus ``T_RELATIVE`` of the distance (the
    slack t comparisons get too, so a grazing hit's rounded t still counts); with barycentrics
    u, v f32[M], the point they name on the triangle is the ray's point at t within the same."""
    speed = np.linalg.norm(rays.dir[idx], axis=1).astype(np.float64)
    slack = _tolerance(rays, idx, t) + T_RELATIVE * np.abs(t) * speed
    p = rays.org[idx].astype(np.float64) + t[:, None] * rays.dir[idx]
    on_triangle, _ = point_triangle_distance(p, *_corners(tris, prim))
    in_segment = ((t - rays.tmin[idx]) * speed >= -slack) & ((t - rays.tmax[idx]) * speed <= slack)
    real = np.isfinite(t) & (on_triangle <= slack) & in_segment
    if u is not None:
        named = (np.asarray(tris.v0[prim], np.float64) + np.asarray(u, np.float64)[:, None] * tris.e1[prim]
                 + np.asarray(v, np.float64)[:, None] * tris.e2[prim])
        with np.errstate(invalid="ignore"):
            real &= np.linalg.norm(np.nan_to_num(p, posinf=0, neginf=0) - named, axis=1) <= slack
    return real


def _edge_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One hashable key per undirected edge (a, b): f32[M,3] endpoints, compared exactly."""
    # + 0.0 turns -0.0 into 0.0, which compares equal but has other bytes.
    a, b = np.asarray(a, np.float32) + np.float32(0), np.asarray(b, np.float32) + np.float32(0)
    swap = np.zeros(len(a), bool)
    for axis in range(3):
        undecided = ~swap & np.all(a[:, :axis] == b[:, :axis], axis=1)
        swap |= undecided & (a[:, axis] > b[:, axis])   # lexicographic order: canonical either way round
    lo = np.where(swap[:, None], b, a)
    hi = np.where(swap[:, None], a, b)
    both = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    return both.view(np.dtype((np.void, both.dtype.itemsize * 6))).ravel()


def _exact_matches(keys: np.ndarray, wanted: np.ndarray) -> list:
    """For each of ``wanted`` (keys from ``_edge_keys`` / ``_point_keys``), the positions in
    ``keys`` that hold the same key: i64 arrays, one per wanted key."""
    order = np.argsort(keys)
    sorted_keys = keys[order]
    first = np.searchsorted(sorted_keys, wanted, side="left")
    last = np.searchsorted(sorted_keys, wanted, side="right")
    return [order[lo:hi] for lo, hi in zip(first, last)]


def crosses_interior_edge(rays, idx, t, prim, tris, tol):
    """bool[M]: the hit (t, prim) of rays idx lies on one edge of its triangle (not at a vertex),
    that edge is shared with other triangles, and the triangles' third corners lie strictly on
    both sides of the plane through the edge and the ray: the ray passes through the surface
    there, so a watertight test must hit one of them."""
    out = np.zeros(len(idx), bool)
    if not len(idx):
        return out
    corners = [np.asarray(c, np.float64) for c in _corners(tris, prim)]
    p = rays.org[idx].astype(np.float64) + t[:, None] * rays.dir[idx]
    at_vertex = np.min([np.linalg.norm(p - c, axis=1) for c in corners], axis=0) <= tol
    edges = ((0, 1, 2), (1, 2, 0), (2, 0, 1))   # (end, end, opposite corner)
    near = np.stack([point_segment_distance(p, corners[i], corners[j]) <= tol for i, j, _ in edges], axis=1)
    one_edge = ~at_vertex & (near.sum(axis=1) == 1)
    if not one_edge.any():
        return out
    which = np.argmax(near, axis=1)
    rows = np.flatnonzero(one_edge)
    all_corners = (tris.v0, tris.v1, tris.v2)
    all_keys = np.concatenate([_edge_keys(all_corners[i], all_corners[j]) for i, j, _ in edges])
    n_tris = tris.v0.shape[0]
    end_a = np.array([corners[edges[w][0]][r] for r, w in zip(rows, which[rows])])
    end_b = np.array([corners[edges[w][1]][r] for r, w in zip(rows, which[rows])])
    own_opposite = np.array([corners[edges[w][2]][r] for r, w in zip(rows, which[rows])])
    matches = _exact_matches(all_keys, _edge_keys(end_a, end_b))
    for k, r in enumerate(rows):
        # Positions e * n_tris + triangle of the triangles with this edge, this one included.
        edge_slot, other = np.divmod(matches[k], n_tris)
        keep = other != prim[r]
        if not keep.any():
            continue   # an outer edge
        # The ray passes between the triangles at this edge when some lie on each side of the
        # plane through the edge and the ray (two for a manifold edge; a fin or a duplicate
        # triangle at a non-manifold one changes nothing).
        normal = np.cross(end_b[k] - end_a[k], rays.dir[idx[r]].astype(np.float64))
        sides = [np.dot(own_opposite[k] - end_a[k], normal)]
        for slot, neighbour in zip(edge_slot[keep].tolist(), other[keep].tolist()):
            sides.append(np.dot(np.asarray(all_corners[edges[slot][2]][neighbour], np.float64) - end_a[k], normal))
        out[r] = min(sides) < 0 < max(sides)
    return out


def _point_keys(points: np.ndarray) -> np.ndarray:
    """One hashable key per point f32[M,3], compared exactly (-0.0 as 0.0)."""
    p = np.ascontiguousarray(np.asarray(points, np.float32) + np.float32(0))
    return p.view(np.dtype((np.void, p.dtype.itemsize * 3))).ravel()


#: A fan whose projection along the ray winds this close to a full turn covers the ray's point.
FULL_TURN_SLACK = 0.05


def crosses_at_vertex(rays, idx, t, prim, tris, tol):
    """bool[M]: the hit (t, prim) of rays idx lies at a corner P of its triangle, and the fan of
    triangles with a corner exactly at P, seen along the ray, winds once around P (signed angles
    summing to a full turn, consistently wound): the ray passes through the surface at P, so a
    watertight test must hit one of them. A fan seen edge-on or folded (a silhouette vertex)
    winds zero times, and inconsistent winding anything else: those stay ties."""
    out = np.zeros(len(idx), bool)
    if not len(idx):
        return out
    corners = [np.asarray(c, np.float64) for c in _corners(tris, prim)]
    p = rays.org[idx].astype(np.float64) + t[:, None] * rays.dir[idx]
    distance = np.stack([np.linalg.norm(p - c, axis=1) for c in corners], axis=1)
    rows = np.flatnonzero(distance.min(axis=1) <= tol)
    if not rows.size:
        return out
    all_corners = (tris.v0, tris.v1, tris.v2)
    n_tris = tris.v0.shape[0]
    nearest = np.argmin(distance[rows], axis=1)
    vertex = np.array([corners[c][r] for r, c in zip(rows, nearest)])
    matches = _exact_matches(np.concatenate([_point_keys(c) for c in all_corners]), _point_keys(vertex))
    for k, r in enumerate(rows):
        slot, fan = np.divmod(matches[k], n_tris)   # which corner of which triangle is P
        if len(fan) < 3:
            continue
        d = rays.dir[idx[r]].astype(np.float64)
        d /= np.linalg.norm(d)
        turn = 0.0
        seen = set()
        for s, f in zip(slot, fan):
            a = np.asarray(all_corners[(s + 1) % 3][f], np.float64) - vertex[k]
            b = np.asarray(all_corners[(s + 2) % 3][f], np.float64) - vertex[k]
            face = frozenset((tuple(a), tuple(b)))
            if face in seen:   # a triangle listed twice (a double-sided face) covers nothing more
                continue
            seen.add(face)
            a -= np.dot(a, d) * d   # projected on the plane across the ray
            b -= np.dot(b, d) * d
            turn += math.atan2(np.dot(d, np.cross(a, b)), np.dot(a, b))
        out[r] = abs(abs(turn) - 2 * math.pi) <= FULL_TURN_SLACK
    return out


def _cracked(rays, idx, t, prim, tris, tol):
    """bool[M]: a hit inside the segment (not at its ends) that crosses an interior edge or a
    vertex the surface closes around: a side that missed it, or hit farther on, went through a
    crack."""
    inside = ~_at_segment_end(rays, idx, t, tol)
    return inside & (crosses_interior_edge(rays, idx, t, prim, tris, tol) | crosses_at_vertex(rays, idx, t, prim, tris, tol))


def past(rays: RayBatch, idx: np.ndarray, t_from: np.ndarray) -> RayBatch:
    """Rays idx of ``rays`` again, from t_from (f64[M]) to their own tmax: the segment behind an
    answer that a tie rule excuses, for asking the oracle what lies there."""
    return RayBatch(rays.org[idx], rays.dir[idx], rays.inv_dir[idx], np.asarray(t_from, np.float32), rays.tmax[idx],
                    rays.pixel[idx], rays.weight[idx], rays.kind)


def _step_past(rays, idx, t, tol) -> np.ndarray:
    """f64[M]: a t just beyond t (twice the distance slack) for rays idx."""
    speed = np.linalg.norm(rays.dir[idx], axis=1).astype(np.float64)
    return t + 2 * (tol + T_RELATIVE * np.abs(t) * speed) / np.maximum(speed, 1e-30)


def compare_hits(rays: RayBatch, ours: Hits, oracle: Hits, tris: Triangles, again=None) -> Comparison:
    """Classify every live ray of a closest-hit query. ``again``: None, or the oracle's closest
    hits for any RayBatch (``intersect``): where the oracle's hit grazes an edge or lies at tmin
    and ours is a miss or a farther hit, the oracle is asked what lies behind its hit, and ours
    must be that (a miss behind an edge with a surface behind it is wrong)."""
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
        slack = tol + T_RELATIVE * ours.t[idx] * speed[idx]
        err = np.abs(ours.t[idx].astype(np.float64) - oracle.t[idx]) * speed[idx]
        # The barycentrics too (shading interpolates normals and uvs with them): the points they
        # name on the triangle lie within the same distance.
        apart = barycentric_distance(tris, ours.prim[idx], ours.u[idx], ours.v[idx], oracle.u[idx], oracle.v[idx])
        ok = (err <= slack) & (apart <= slack)
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
        both_tie = close_t & (d_ab <= tol) & (d_ba <= tol)
        # A ray whose origin lies on another surface (a secondary ray leaving a corner) may
        # report that surface at t = tmin or skip it: both are valid (ours skipping it: below).
        start = rays.tmin[both].astype(np.float64)
        both_tie |= np.abs(t_a - start) * speed[both] <= tol
        # A ray through a vertex or a silhouette edge of a closed surface: the nearer side hit it
        # there, the other slipped through to a farther surface -- the same event as a miss past
        # such a point (below). Embree does so on rays aimed at a capsule's or icosphere's
        # vertices (session 37: float64 puts the vertex first). Through an interior edge it is
        # a crack in our test, not a tie.
        nearer_ours = t_a < t_b
        ours_grazes = _grazes(rays, both, t_a, ours.prim[both], tris, tol)
        oracle_grazes = _grazes(rays, both, t_b, oracle.prim[both], tris, tol)
        theirs_first = np.flatnonzero(~nearer_ours & oracle_grazes)
        oracle_grazes[theirs_first] &= ~_cracked(rays, both[theirs_first], t_b[theirs_first],
                                                  oracle.prim[both[theirs_first]], tris, tol[theirs_first])
        both_tie |= nearer_ours & ours_grazes
        # The oracle's hit grazes or lies at tmin and ours is farther: ours must be what lies
        # behind the oracle's hit (asked of the oracle when it can be).
        behind = (~nearer_ours & oracle_grazes) | (np.abs(t_b - start) * speed[both] <= tol)
        check = np.flatnonzero(behind & ~both_tie)
        if again is not None and check.size:
            rows = both[check]
            next_hit = again(past(rays, rows, _step_past(rays, rows, t_b[check], tol[check])))
            slack = tol[check] + T_RELATIVE * t_a[check] * speed[rows]
            behind[check] = (next_hit.prim == ours.prim[rows]) | (
                np.abs(next_hit.t.astype(np.float64) - t_a[check]) * speed[rows] <= slack)
        both_tie |= behind
        tie[both[both_tie & is_real_hit(rays, both, t_a, ours.prim[both], tris, ours.u[both], ours.v[both])]] = True
    one = np.flatnonzero(live & (ours.prim >= 0) & (oracle.prim < 0))
    if one.size:   # we hit, the oracle missed: a real hit of ours grazing an edge or an end
        t = ours.t[one].astype(np.float64)
        tol = _tolerance(rays, one, t)
        tie[one[_grazes(rays, one, t, ours.prim[one], tris, tol) & is_real_hit(rays, one, t, ours.prim[one], tris, ours.u[one], ours.v[one])]] = True
    one = np.flatnonzero(live & (oracle.prim >= 0) & (ours.prim < 0))
    if one.size:   # we missed where the oracle hit at an edge: a tie unless that edge is a crack
        t = oracle.t[one].astype(np.float64)
        tol = _tolerance(rays, one, t)
        grazes = _grazes(rays, one, t, oracle.prim[one], tris, tol)
        grazes &= ~_cracked(rays, one, t, oracle.prim[one], tris, tol)
        check = np.flatnonzero(grazes)
        if again is not None and check.size:   # and nothing lies behind the graze
            rows = one[check]
            next_hit = again(past(rays, rows, _step_past(rays, rows, t[check], tol[check])))
            far = next_hit.prim >= 0
            if far.any():   # a surface behind it: only another graze (or an end) excuses the miss
                t_next = next_hit.t[far].astype(np.float64)
                far_rows = rows[far]
                far[far] = ~_grazes(rays, far_rows, t_next, next_hit.prim[far], tris, _tolerance(rays, far_rows, t_next))
            grazes[check] = ~far
        tie[one[grazes]] = True
    mismatch = live & ~agree & ~tie
    return Comparison(agree, tie, mismatch, max_err)


def compare_occlusion(rays: RayBatch, ours: np.ndarray, oracle: np.ndarray, tris: Triangles,
                      closest_ours: Hits, closest_oracle: Hits, again=None) -> Comparison:
    """Classify every live ray of an occlusion query. ``closest_*`` are closest-hit answers for
    the same rays (only read where the two occlusion answers differ): a differing answer is a
    tie when the occluding side's hit grazes an edge or an end of the segment (ours must be a
    real hit; the oracle's must not cross an interior edge, see the module docstring). ``again``:
    None, or the oracle's occlusion of any RayBatch (``occluded``): where we are not occluded and
    the oracle's blocker grazes, nothing may block the segment behind it."""
    n = rays.org.shape[0]
    live = rays.tmin <= rays.tmax
    agree = live & (ours == oracle)
    tie = np.zeros(n, bool)
    one = np.flatnonzero(live & ours & ~agree & (closest_ours.prim >= 0))
    if one.size:   # we are occluded, the oracle is not: our real hit grazes an edge or an end
        t, prim = closest_ours.t[one].astype(np.float64), closest_ours.prim[one]
        tie[one[_grazes(rays, one, t, prim, tris, _tolerance(rays, one, t)) & is_real_hit(rays, one, t, prim, tris, closest_ours.u[one], closest_ours.v[one])]] = True
    one = np.flatnonzero(live & oracle & ~agree & (closest_oracle.prim >= 0))
    if one.size:   # the oracle is occluded, we are not: its hit grazes, and not through a crack
        t, prim = closest_oracle.t[one].astype(np.float64), closest_oracle.prim[one]
        tol = _tolerance(rays, one, t)
        grazes = _grazes(rays, one, t, prim, tris, tol) & ~_cracked(rays, one, t, prim, tris, tol)
        check = np.flatnonzero(grazes)
        if again is not None and check.size:
            rows = one[check]
            grazes[check] = ~np.asarray(again(past(rays, rows, _step_past(rays, rows, t[check], tol[check]))), bool)
        tie[one[grazes]] = True
    mismatch = live & ~agree & ~tie
    return Comparison(agree, tie, mismatch, 0.0)
