"""The 4-wide vector kernels of engine.packet.simd4 answer exactly as their scalar definitions.

slab4 must give, lane by lane, engine.core.triangle.slab_test's answer (including dead lanes and
axis-parallel rays); planes4_box / planes4_triangle must agree with the plane tests written out
in scalar numba code, on random data with many near-boundary cases.
"""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from engine.core.triangle import F32_INF, HUGE_INV, safe_inverse, slab_test
from engine.packet.kernels import IX, OX, RF_ROWS, THI, TLO
from engine.packet.simd4 import planes4_box, planes4_triangle, slab1x8, slab4, slab4x2
from engine.query.wide import pack_nodes

LANES = 32
BOXES = 40


@njit(cache=True)
def masks_vector(rf, bmin, bmax):
    out = np.zeros((LANES // 4, bmin.shape[0]), np.int64)
    for i in range(LANES // 4):
        for node in range(bmin.shape[0]):
            out[i, node] = slab4(rf, 4 * i, bmin[node, 0], bmin[node, 1], bmin[node, 2],
                                 bmax[node, 0], bmax[node, 1], bmax[node, 2])
    return out


@njit(cache=True)
def masks_scalar(rf, bmin, bmax):
    out = np.zeros((LANES // 4, bmin.shape[0]), np.int64)
    for i in range(LANES // 4):
        for node in range(bmin.shape[0]):
            for lane in range(4):
                r = 4 * i + lane
                if slab_test(rf[OX, r], rf[OX + 1, r], rf[OX + 2, r], rf[IX, r], rf[IX + 1, r], rf[IX + 2, r],
                             rf[TLO, r], rf[THI, r], bmin, bmax, node) < F32_INF:
                    out[i, node] |= 1 << lane
    return out


@njit(cache=True)
def masks_pairs(rf, bmin, bmax, pairs):
    """slab4x2 of SIMD rays pairs[p, 0] and pairs[p, 1], split back into two 4-lane masks."""
    out = np.zeros((LANES // 4, bmin.shape[0]), np.int64)
    for p in range(pairs.shape[0]):
        i0, i1 = pairs[p, 0], pairs[p, 1]
        for node in range(bmin.shape[0]):
            both = slab4x2(rf, 4 * i0, 4 * i1, bmin[node, 0], bmin[node, 1], bmin[node, 2],
                           bmax[node, 0], bmax[node, 1], bmax[node, 2])
            out[i0, node] = both & 0xF
            out[i1, node] = both >> 4
    return out


def random_lanes_and_boxes(rng):
    """(rf f32[RF_ROWS, LANES], bmin, bmax f32[BOXES, 3]) with dead lanes, axis-parallel rays
    and flat boxes."""
    rf = np.zeros((RF_ROWS, LANES), np.float32)
    d = rng.normal(size=(LANES, 3)).astype(np.float32)
    d[rng.random((LANES, 3)) < 0.15] = 0.0  # axis-parallel rays: inv_dir is +-HUGE_INV
    rf[OX:OX + 3] = rng.normal(size=(3, LANES)) * 2
    rf[IX:IX + 3] = safe_inverse(d).T
    rf[TLO] = np.where(rng.random(LANES) < 0.5, 0.0, rng.uniform(0, 2, LANES))
    rf[THI] = rf[TLO] + rng.exponential(3, LANES)
    dead = rng.random(LANES) < 0.15
    rf[TLO, dead], rf[THI, dead] = np.inf, -np.inf
    lo = rng.normal(size=(BOXES, 3)) * 2
    bmin = lo.astype(np.float32)
    bmax = (lo + np.abs(rng.normal(size=(BOXES, 3))) * rng.choice([0.0, 1.0], (BOXES, 3), p=[0.1, 0.9])).astype(np.float32)
    return rf, bmin, bmax


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_slab4_is_slab_test_on_four_lanes(seed):
    rf, bmin, bmax = random_lanes_and_boxes(np.random.default_rng(seed))
    vector = masks_vector(rf, bmin, bmax)
    np.testing.assert_array_equal(vector, masks_scalar(rf, bmin, bmax))
    assert np.abs(rf[IX:IX + 3]).max() <= HUGE_INV


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_slab4x2_is_slab_test_on_two_simd_rays_in_any_order(seed):
    rng = np.random.default_rng(seed)
    rf, bmin, bmax = random_lanes_and_boxes(rng)
    pairs = rng.permutation(LANES // 4).reshape(-1, 2).astype(np.int64)  # not neighbours, either order
    np.testing.assert_array_equal(masks_pairs(rf, bmin, bmax, pairs), masks_scalar(rf, bmin, bmax))


@njit(cache=True)
def children_vector(box, org, inv, t_lo, t_hi):
    """(f32[R, W, 8] entry distances, i64[R, W] masks): slab1x8 of every ray and wide node."""
    out = np.zeros((org.shape[0], box.shape[0], 8), np.float32)
    masks = np.zeros((org.shape[0], box.shape[0]), np.int64)
    for r in range(org.shape[0]):
        for w in range(box.shape[0]):
            masks[r, w] = slab1x8(box, w, org[r, 0], org[r, 1], org[r, 2], inv[r, 0], inv[r, 1], inv[r, 2],
                                  t_lo[r], t_hi[r], out[r, w])
    return out, masks


@njit(cache=True)
def children_scalar(bmin, bmax, org, inv, t_lo, t_hi):
    """f32[R, W, 8]: slab_test of every ray and box 8 w + s (boxes: f32[8W, 3])."""
    out = np.zeros((org.shape[0], bmin.shape[0] // 8, 8), np.float32)
    for r in range(org.shape[0]):
        for b in range(bmin.shape[0]):
            out[r, b // 8, b % 8] = slab_test(org[r, 0], org[r, 1], org[r, 2], inv[r, 0], inv[r, 1], inv[r, 2],
                                              t_lo[r], t_hi[r], bmin, bmax, b)
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_slab1x8_is_slab_test_on_eight_child_boxes(seed):
    """The mesh queries' 8-wide node test: each slot's entry distance is slab_test's, bit for bit,
    the mask has exactly the slots with a finite entry, and empty slots (NaN boxes, as
    ``engine.query.wide`` stores them) are never hit."""
    rng = np.random.default_rng(seed)
    _, bmin, bmax = random_lanes_and_boxes(rng)
    empty = rng.random(BOXES) < 0.1
    box = np.concatenate([bmin, bmax], axis=1).reshape(-1, 8, 6).transpose(0, 2, 1)  # f32[W, 6, 8]
    box = np.ascontiguousarray(box)
    slots = np.flatnonzero(empty)
    box[slots // 8, :, slots % 8] = np.nan
    d = rng.normal(size=(LANES, 3)).astype(np.float32)
    d[rng.random((LANES, 3)) < 0.15] = 0.0
    org = (rng.normal(size=(LANES, 3)) * 2).astype(np.float32)
    aimed = np.flatnonzero(~empty)[:4]  # four rays aimed at the centres of non-empty boxes
    d[:4] = (bmin[aimed] + bmax[aimed]) / 2 - org[:4]
    inv = safe_inverse(d)
    t_lo = np.where(rng.random(LANES) < 0.5, 0.0, rng.uniform(0, 2, LANES)).astype(np.float32)
    t_hi = (t_lo + rng.exponential(3, LANES)).astype(np.float32)
    t_hi[rng.random(LANES) < 0.3] = np.inf
    t_lo[:4], t_hi[:4] = 0, np.inf
    vector, masks = children_vector(box, org, inv, t_lo, t_hi)
    scalar = children_scalar(bmin, bmax, org, inv, t_lo, t_hi)
    empty_slots = empty.reshape(-1, 8)
    assert np.isinf(vector[:, empty_slots]).all()
    scalar[:, empty_slots] = np.inf
    np.testing.assert_array_equal(vector.view(np.uint32), scalar.view(np.uint32))
    bits = (masks[:, :, None] >> np.arange(8)) & 1
    np.testing.assert_array_equal(bits == 1, np.isfinite(vector))
    assert np.isfinite(vector).any() and np.isinf(vector).any()
    # The same boxes in the walks' packed nodes (eight rows a node, ``engine.query.wide``).
    n_wide = box.shape[0]
    nodes = pack_nodes(box, np.zeros((n_wide, 8), np.int32), np.zeros((n_wide, 8), np.int32))
    packed, packed_masks = children_vector(nodes, org, inv, t_lo, t_hi)
    np.testing.assert_array_equal(packed.view(np.uint32), vector.view(np.uint32))
    np.testing.assert_array_equal(packed_masks, masks)


@njit(cache=True)
def planes_vector(fr, bmin, bmax, v0, v1, v2):
    boxes = np.zeros(bmin.shape[0], np.bool_)
    tris = np.zeros(v0.shape[0], np.bool_)
    for g in range(bmin.shape[0]):
        boxes[g] = planes4_box(fr, bmin[g, 0], bmin[g, 1], bmin[g, 2], bmax[g, 0], bmax[g, 1], bmax[g, 2])
    for g in range(v0.shape[0]):
        tris[g] = planes4_triangle(fr, v0[g, 0], v0[g, 1], v0[g, 2], v1[g, 0], v1[g, 1], v1[g, 2],
                                   v2[g, 0], v2[g, 1], v2[g, 2])
    return boxes, tris


@njit(cache=True)
def planes_scalar(fr, bmin, bmax, v0, v1, v2):
    boxes = np.zeros(bmin.shape[0], np.bool_)
    tris = np.zeros(v0.shape[0], np.bool_)
    for p in range(4):
        nx, ny, nz, d = fr[p], fr[4 + p], fr[8 + p], fr[12 + p]
        for g in range(bmin.shape[0]):
            s = (max(nx * bmin[g, 0], nx * bmax[g, 0]) + max(ny * bmin[g, 1], ny * bmax[g, 1])
                 + max(nz * bmin[g, 2], nz * bmax[g, 2]) + d)
            boxes[g] |= s < 0
        for g in range(v0.shape[0]):
            s0 = nx * v0[g, 0] + ny * v0[g, 1] + nz * v0[g, 2]
            s1 = nx * v1[g, 0] + ny * v1[g, 1] + nz * v1[g, 2]
            s2 = nx * v2[g, 0] + ny * v2[g, 1] + nz * v2[g, 2]
            tris[g] |= max(max(s0, s1), s2) + d < 0
    return boxes, tris


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_plane_tests_match_scalar_definition(seed):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(4, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    fr = np.concatenate([normals.T.ravel(), rng.normal(size=4)]).astype(np.float32)
    lo = rng.normal(size=(BOXES, 3))
    bmin = lo.astype(np.float32)
    bmax = (lo + np.abs(rng.normal(size=(BOXES, 3))) * 0.5).astype(np.float32)
    v0, v1, v2 = (rng.normal(size=(BOXES, 3)).astype(np.float32) for _ in range(3))
    boxes, tris = planes_vector(fr, bmin, bmax, v0, v1, v2)
    ref_boxes, ref_tris = planes_scalar(fr, bmin, bmax, v0, v1, v2)
    np.testing.assert_array_equal(boxes, ref_boxes)
    np.testing.assert_array_equal(tris, ref_tris)
