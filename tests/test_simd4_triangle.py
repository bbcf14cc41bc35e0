"""engine.packet.simd4_triangle.intersect4 answers exactly as the scalar leaf loop it replaces.

The reference is the loop written out in scalar numba code: for each selected live lane, for each
leaf triangle, ``intersect_triangle`` then ``closer`` (any-hit: the lane dies at its first hit).
Both run the same sequence of leaves on the same packet rows; every row (THI, BEST_T/U/V/PRIM)
and the (tests, died) counts must agree bit for bit. The random cases aim rays at vertices and
edges of a shared-edge mesh, mix dominant axes inside one SIMD ray, put t exactly on TLO / THI,
and add degenerate, duplicated and tiny (edge-function underflow) triangles and axis-parallel
rays. The generated code must hold no fast-math flags and no fused multiply-add.
"""
from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from engine.core.triangle import F32_INF, closer, intersect_triangle, safe_inverse
from engine.packet.kernels import (BEST_PRIM, BEST_T, BEST_U, BEST_V, KX, KY, KZ, OKX, OKY, OKZ, RF_ROWS, RI_ROWS,
                                   SX, SY, SZ, THI, TLO, load_packet)
from engine.packet.simd4_triangle import intersect4, intersect4x2, triangles_block

LANES = 32
F32_NEG_INF = np.float32(-np.inf)


@njit(cache=True)
def leaves_scalar(rf, ri, calls, leaf_tris, v0, v1, v2, any_hit):
    """The scalar loop, one leaf per row of calls (lane0, mask, first, count); (tests, died) per call."""
    out = np.zeros((calls.shape[0], 2), np.int64)
    for c in range(calls.shape[0]):
        lane0, mask, first, n_tris = calls[c, 0], calls[c, 1], calls[c, 2], calls[c, 3]
        tests = 0
        finished = 0
        for lane in range(4):
            r = lane0 + lane
            t_lo = rf[TLO, r]
            t_hi = rf[THI, r]
            if (mask >> lane) & 1 == 0 or not t_lo <= t_hi:
                continue
            best_t, best_prim, best_u, best_v = rf[BEST_T, r], ri[BEST_PRIM, r], rf[BEST_U, r], rf[BEST_V, r]
            for j in range(first, first + n_tris):
                tri = leaf_tris[j]
                tests += 1
                t, u, v = intersect_triangle(rf[OKX, r], rf[OKY, r], rf[OKZ, r], ri[KX, r], ri[KY, r], ri[KZ, r],
                                             rf[SX, r], rf[SY, r], rf[SZ, r], t_lo, t_hi, v0, v1, v2, tri)
                if t < F32_INF and closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v = t, tri, u, v
                    t_hi = t
                    if any_hit:
                        t_hi = F32_NEG_INF
                        finished += 1
                        break
            rf[THI, r] = t_hi
            rf[BEST_T, r], ri[BEST_PRIM, r], rf[BEST_U, r], rf[BEST_V, r] = best_t, best_prim, best_u, best_v
        out[c, 0], out[c, 1] = tests, finished
    return out


@njit(cache=True)
def leaves_vector(rf, ri, calls, leaf_tris, v0, v1, v2, any_hit):
    """The same calls through intersect4."""
    out = np.zeros((calls.shape[0], 2), np.int64)
    for c in range(calls.shape[0]):
        first, n_tris = calls[c, 2], calls[c, 3]
        out[c, 0], out[c, 1] = intersect4(rf, ri, calls[c, 0], calls[c, 1], leaf_tris[first:first + n_tris], n_tris,
                                          v0, v1, v2, any_hit)
    return out


@njit(cache=True)
def leaves_pairs(rf, ri, pairs, leaf_tris, v0, v1, v2, any_hit):
    """Rows of pairs (lane0, lane1, mask8, first, count) through intersect4x2."""
    out = np.zeros((pairs.shape[0], 2), np.int64)
    for c in range(pairs.shape[0]):
        first, n_tris = pairs[c, 3], pairs[c, 4]
        out[c, 0], out[c, 1] = intersect4x2(rf, ri, pairs[c, 0], pairs[c, 1], pairs[c, 2],
                                            leaf_tris[first:first + n_tris], n_tris, v0, v1, v2, any_hit)
    return out


@njit(cache=True)
def all_t(rf, ri, v0, v1, v2):
    """f32[LANES, T]: every lane's t for every triangle on [0, inf] (inf: miss)."""
    out = np.full((rf.shape[1], v0.shape[0]), np.inf, np.float32)
    for r in range(rf.shape[1]):
        for tri in range(v0.shape[0]):
            out[r, tri] = intersect_triangle(rf[OKX, r], rf[OKY, r], rf[OKZ, r], ri[KX, r], ri[KY, r], ri[KZ, r],
                                             rf[SX, r], rf[SY, r], rf[SZ, r], np.float32(0.0), F32_INF,
                                             v0, v1, v2, tri)[0]
    return out


def make_scene(rng, scale):
    """(v0, v1, v2) f32[T,3]: a shared-edge grid mesh, random triangles, degenerate ones and copies."""
    n = 3
    grid = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1).reshape(-1, 2).astype(float)
    grid = np.concatenate([grid + rng.normal(scale=0.1, size=grid.shape), rng.normal(scale=0.3, size=(len(grid), 1))], 1)
    tri = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j + 1
            tri += [(a, b, c), (c, b, d)]
    tri = np.array(tri)
    corners = [grid[tri[:, k]] for k in range(3)]
    m = 8
    rand = [rng.normal(size=(m, 3)) * 1.5 + 1.5 for _ in range(3)]
    corners = [np.concatenate([c, r]) for c, r in zip(corners, rand)]
    k = len(corners[0])
    # Degenerate: a repeated corner, and three collinear corners.
    corners[1][k - 1] = corners[0][k - 1]
    corners[2][k - 2] = 0.5 * (corners[0][k - 2] + corners[1][k - 2])
    # Copies of mesh triangles (same t: ties go to the smaller index), one with its winding reversed.
    dup = rng.choice(len(tri), 3, replace=False)
    extra = [np.concatenate([c[dup], c[dup[:1]]]) for c in corners]
    extra[1][-1], extra[2][-1] = corners[2][dup[0]], corners[1][dup[0]]
    corners = [np.concatenate([c, e]) for c, e in zip(corners, extra)]
    # A random rotation, so the mesh is not axis-aligned, then the scale.
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return [np.ascontiguousarray((c @ q.T) * scale, np.float32) for c in corners]


def make_rays(rng, v0, v1, v2, scale):
    """(org, dir) f32[LANES,3] aimed at vertices, edge points and interiors of the triangles."""
    t = rng.integers(0, len(v0), LANES)
    w = rng.dirichlet(np.ones(3), LANES)
    kind = rng.integers(0, 4, LANES)
    w[kind == 0] = np.eye(3)[rng.integers(0, 3, (kind == 0).sum())]  # a vertex
    edge = kind == 1
    w[edge, rng.integers(0, 3, edge.sum())] = 0.0  # a point on an edge
    w[edge] /= w[edge].sum(1, keepdims=True)
    mid = kind == 2
    w[mid] = np.array([[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])[rng.integers(0, 3, mid.sum())]  # midpoint
    target = w[:, :1] * v0[t] + w[:, 1:2] * v1[t] + w[:, 2:] * v2[t]
    org = (target + rng.normal(size=(LANES, 3)) * 4 * scale).astype(np.float32)
    d = (target - org).astype(np.float32)
    # Half the SIMD rays coherent (one permutation for all lanes), the rest with lanes of different
    # dominant axes; some axis-parallel rays.
    for i in np.flatnonzero(rng.random(LANES // 4) < 0.5):
        d[4 * i + 1:4 * i + 4] = d[4 * i] + rng.normal(size=(3, 3)) * 0.05 * np.abs(d[4 * i]).max()
    d[rng.random(LANES) < 0.1] *= -1
    flat = rng.random((LANES, 3)) < 0.08
    d[flat] = 0.0
    d[np.all(d == 0, axis=1)] = (1.0, 0.0, 0.0)
    return org, d


def make_case(seed):
    rng = np.random.default_rng(seed)
    scale = [1.0, 1.0, 1e-19, 1e18][seed % 4]  # tiny: edge-function products underflow float32
    v0, v1, v2 = make_scene(rng, scale)
    org, d = make_rays(rng, v0, v1, v2, scale)
    tmin = np.where(rng.random(LANES) < 0.5, 0.0, rng.uniform(0, 2, LANES) * scale).astype(np.float32)
    tmax = np.where(rng.random(LANES) < 0.5, np.inf, rng.uniform(2, 8, LANES) * scale).astype(np.float32)
    dead = rng.random(LANES) < 0.1
    tmin[dead], tmax[dead] = 1.0, 0.0
    rf = np.zeros((RF_ROWS, LANES), np.float32)
    ri = np.zeros((RI_ROWS, LANES), np.int32)
    load_packet(org, safe_inverse(d), d, tmin, tmax, 0, LANES, rf, ri, np.zeros(6, np.int64))
    # t exactly on a segment end: TLO or THI set to a t some lane finds.
    ts = all_t(rf, ri, v0, v1, v2)
    for r in np.flatnonzero(~dead & (rng.random(LANES) < 0.4)):
        hit = np.flatnonzero(np.isfinite(ts[r]))
        if len(hit):
            t = ts[r, rng.choice(hit)]
            if rng.random() < 0.5:
                rf[TLO, r] = min(t, rf[THI, r])
            else:
                rf[THI, r] = max(t, rf[TLO, r])
    # Leaves: random runs of triangle indices, called on random SIMD rays with random lane masks.
    n_calls = 24
    leaf_tris = rng.integers(0, len(v0), 12 * n_calls).astype(np.int32)
    calls = np.zeros((n_calls, 4), np.int64)
    calls[:, 0] = 4 * rng.integers(0, LANES // 4, n_calls)
    calls[:, 1] = np.where(rng.random(n_calls) < 0.5, 15, rng.integers(0, 16, n_calls))
    calls[:, 2] = 12 * np.arange(n_calls)
    calls[:, 3] = rng.integers(0, 13, n_calls)
    return rf, ri, calls, leaf_tris, v0, v1, v2, ts


def bits(a):
    return a.view(np.uint32)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), any_hit=st.booleans())
def test_intersect4_is_the_scalar_leaf_loop(seed, any_hit):
    rf, ri, calls, leaf_tris, v0, v1, v2, ts = make_case(seed)
    rf_s, ri_s = rf.copy(), ri.copy()
    counts = leaves_vector(rf, ri, calls, leaf_tris, v0, v1, v2, any_hit)
    ref_counts = leaves_scalar(rf_s, ri_s, calls, leaf_tris, v0, v1, v2, any_hit)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_array_equal(bits(rf), bits(rf_s))
    np.testing.assert_array_equal(ri, ri_s)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), any_hit=st.booleans())
def test_intersect4x2_is_the_scalar_leaf_loop_on_two_simd_rays(seed, any_hit):
    """A pair call equals the scalar loop on its first SIMD ray, then on its second (lanes are
    independent), whichever SIMD rays of the packet are paired and in either order."""
    rf, ri, calls, leaf_tris, v0, v1, v2, ts = make_case(seed)
    rng = np.random.default_rng(seed + 1)
    simd = rng.permutation(LANES // 4)
    pairs = np.zeros((len(calls), 5), np.int64)
    pairs[:, 0] = 4 * simd[rng.integers(0, len(simd), len(calls))]
    pairs[:, 1] = (pairs[:, 0] + 4 * rng.integers(1, LANES // 4, len(calls))) % LANES  # another SIMD ray
    pairs[:, 2] = calls[:, 1] | (np.where(rng.random(len(calls)) < 0.5, 15, rng.integers(0, 16, len(calls))) << 4)
    pairs[:, 3:] = calls[:, 2:]
    singles = np.zeros((2 * len(calls), 4), np.int64)
    singles[0::2, 0], singles[1::2, 0] = pairs[:, 0], pairs[:, 1]
    singles[0::2, 1], singles[1::2, 1] = pairs[:, 2] & 15, pairs[:, 2] >> 4
    singles[0::2, 2:] = singles[1::2, 2:] = pairs[:, 3:]
    rf_s, ri_s = rf.copy(), ri.copy()
    counts = leaves_pairs(rf, ri, pairs, leaf_tris, v0, v1, v2, any_hit)
    ref_counts = leaves_scalar(rf_s, ri_s, singles, leaf_tris, v0, v1, v2, any_hit)
    np.testing.assert_array_equal(counts, ref_counts[0::2] + ref_counts[1::2])
    np.testing.assert_array_equal(bits(rf), bits(rf_s))
    np.testing.assert_array_equal(ri, ri_s)


@njit(cache=True)
def windows_vector(rf, ri, windows, blocks):
    """(f32[LANES, W, 12], i64[LANES, W]): triangles_block's answers and hit masks for every lane
    and window k (block k, its first n lanes)."""
    out = np.full((rf.shape[1], windows.shape[0], 12), np.nan, np.float32)
    masks = np.zeros((rf.shape[1], windows.shape[0]), np.int64)
    for r in range(rf.shape[1]):
        for k in range(windows.shape[0]):
            masks[r, k] = triangles_block(blocks, k, windows[k, 1], rf[OKX, r], rf[OKY, r], rf[OKZ, r],
                                          ri[KX, r], ri[KY, r], ri[KZ, r], rf[SX, r], rf[SY, r], rf[SZ, r],
                                          rf[TLO, r], rf[THI, r], out[r, k])
    return out, masks


def window_blocks(windows, v0, v1, v2):
    """f32[W,10,4]: window k's triangles first .. first+n-1 in block k's first n lanes (the
    ``engine.query.leaf_blocks`` layout); the lanes past n hold other triangles of the mesh,
    which the test must ignore, and the last row (the triangle indices there) holds NaN."""
    blocks = np.full((len(windows), 10, 4), np.nan, np.float32)
    for k, (first, n) in enumerate(windows):
        rows = [first + j if j < n else (first + n + 3 * j) % len(v0) for j in range(4)]
        for c, corner in enumerate((v0, v1, v2)):
            blocks[k, 3 * c:3 * c + 3, :] = corner[rows].T
    return blocks


@njit(cache=True)
def windows_scalar(rf, ri, windows, v0, v1, v2):
    out = np.zeros((rf.shape[1], windows.shape[0], 12), np.float32)
    for r in range(rf.shape[1]):
        for k in range(windows.shape[0]):
            for j in range(4):
                t, u, v = F32_INF, np.float32(0.0), np.float32(0.0)
                if j < windows[k, 1]:
                    t, u, v = intersect_triangle(rf[OKX, r], rf[OKY, r], rf[OKZ, r], ri[KX, r], ri[KY, r], ri[KZ, r],
                                                 rf[SX, r], rf[SY, r], rf[SZ, r], rf[TLO, r], rf[THI, r],
                                                 v0, v1, v2, windows[k, 0] + j)
                out[r, k, j], out[r, k, 4 + j], out[r, k, 8 + j] = t, u, v
    return out


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_triangles_block_is_intersect_triangle_on_four_triangles(seed):
    """One ray against a block of 1-4 triangles: each slot is intersect_triangle's answer bit for
    bit, slots past the block's n are misses whatever triangles they hold."""
    rf, ri, calls, leaf_tris, v0, v1, v2, ts = make_case(seed)
    live = rf[TLO] <= rf[THI]
    rf, ri = rf[:, live].copy(), ri[:, live].copy()
    rng = np.random.default_rng(seed)
    windows = np.zeros((16, 2), np.int64)
    windows[:, 1] = rng.integers(1, 5, 16)
    windows[:, 0] = rng.integers(0, len(v0) - windows[:, 1] + 1)
    # Half the windows hold a triangle some live lane hits inside its segment (random windows
    # alone missed every hit for some seeds).
    ts = ts[live]
    hits = np.argwhere(np.isfinite(ts) & (ts >= rf[TLO][:, None]) & (ts <= rf[THI][:, None]))
    if len(hits):
        for k in range(8):
            tri, n = hits[rng.integers(len(hits)), 1], windows[k, 1]
            windows[k, 0] = min(max(tri - rng.integers(0, n), 0), len(v0) - n)
    vector, masks = windows_vector(rf, ri, windows, window_blocks(windows, v0, v1, v2))
    np.testing.assert_array_equal(bits(vector), bits(windows_scalar(rf, ri, windows, v0, v1, v2)))
    assert np.isfinite(vector[:, :, :4]).any() == (len(hits) > 0)
    lanes_hit = (np.isfinite(vector[:, :, :4]) << np.arange(4)).sum(axis=2)   # the mask: exactly the hits
    np.testing.assert_array_equal(masks, lanes_hit)


def test_cases_reach_the_edge_cases():
    """The generator really produces hits, ties, on-boundary t and underflowing edge functions."""
    hits = ties = on_end = 0
    for seed in range(40):
        rf, ri, calls, leaf_tris, v0, v1, v2, ts = make_case(seed)
        finite = np.isfinite(ts)
        hits += finite.sum()
        ties += sum(len(row[finite[r]]) - len(np.unique(row[finite[r]])) for r, row in enumerate(ts))
        on_end += (finite & ((ts == rf[TLO][:, None]) | (ts == rf[THI][:, None]))).sum()
        rf_s, ri_s = rf.copy(), ri.copy()
        leaves_scalar(rf_s, ri_s, calls, leaf_tris, v0, v1, v2, False)
    assert hits > 1000 and ties > 20 and on_end > 50, (hits, ties, on_end)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_whole_scene_as_one_leaf(seed):
    """Every triangle in one leaf, all live lanes on [0, inf]: the closest hits agree."""
    rf, ri, calls, leaf_tris, v0, v1, v2, _ = make_case(seed)
    leaf = np.arange(len(v0), dtype=np.int32)
    calls = np.array([[4 * i, 15, 0, len(v0)] for i in range(LANES // 4)], np.int64)
    live = rf[TLO] <= rf[THI]
    rf[TLO], rf[THI] = np.where(live, 0.0, np.inf), np.where(live, np.inf, -np.inf)
    rf_s, ri_s = rf.copy(), ri.copy()
    leaves_vector(rf, ri, calls, leaf, v0, v1, v2, False)
    leaves_scalar(rf_s, ri_s, calls, leaf, v0, v1, v2, False)
    np.testing.assert_array_equal(bits(rf), bits(rf_s))
    np.testing.assert_array_equal(ri, ri_s)


def test_strided_inputs():
    """Vertex and leaf arrays that are views (any layout) give the contiguous arrays' answers."""
    rf, ri, calls, leaf_tris, v0, v1, v2, _ = make_case(7)
    wide = [np.zeros((len(v), 5), np.float32) for v in (v0, v1, v2)]
    for w, v in zip(wide, (v0, v1, v2)):
        w[:, 1:4] = v
    spread = np.zeros(2 * len(leaf_tris), np.int32)
    spread[::2] = leaf_tris
    rf_s, ri_s = rf.copy(), ri.copy()
    counts = leaves_vector(rf, ri, calls, spread[::2], *(w[:, 1:4] for w in wide), True)
    ref_counts = leaves_vector(rf_s, ri_s, calls, leaf_tris, v0, v1, v2, True)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_array_equal(bits(rf), bits(rf_s))
    np.testing.assert_array_equal(ri, ri_s)


@pytest.mark.parametrize("test", ["intersect4", "intersect4x2", "triangles_block"])
def test_no_fast_math_and_no_fma(test):
    """Bit-identity by construction: plain IEEE ops, nothing LLVM may fuse or reassociate."""
    rf, ri, calls, leaf_tris, v0, v1, v2, _ = make_case(0)
    lanes = 8 if test == "intersect4x2" else 4
    if test == "intersect4":
        fresh = njit(leaves_vector.py_func)  # not from the disk cache, which keeps no IR
        fresh(rf, ri, calls, leaf_tris, v0, v1, v2, False)
    elif test == "intersect4x2":
        fresh = njit(leaves_pairs.py_func)
        calls = np.concatenate([calls[:, :1], (calls[:, :1] + 4) % LANES, calls[:, 1:2] * 17, calls[:, 2:]], 1)
        fresh(rf, ri, calls, leaf_tris, v0, v1, v2, False)
    else:
        fresh = njit(windows_vector.py_func)
        windows = np.array([[0, 4], [1, 3]], np.int64)
        fresh(rf, ri, windows, window_blocks(windows, v0, v1, v2))
    sig = fresh.signatures[0]
    llvm = fresh.inspect_llvm(sig)
    asm = fresh.inspect_asm(sig)
    vector_ops = re.findall(rf"= (fmul|fadd|fsub|fdiv)( [a-z ]*)?<{lanes} x (float|double)>", llvm)
    assert len(vector_ops) >= 20
    assert all(not (flags or "").strip() for _, flags, _ in vector_ops), {flags for _, flags, _ in vector_ops}
    assert not re.search(r"llvm\.fma|llvm\.fmuladd", llvm)
    assert not re.search(r"\bv?f(n)?m(add|sub)", asm)
