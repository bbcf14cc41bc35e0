"""engine.packet.load8.load_rays8 loads eight rays exactly as the scalar step does.

load_packet loads a packet eight rays at a time through the vector intrinsic and the rest one by
one (``load_lane``). Every packet-local row (origin, inverse, segment, the watertight test's axes,
shear and permuted origin, the empty best hit) must hold the same bits as when each ray goes
through ``load_lane``, including dead lanes (tmin > tmax, NaN segments), ties between direction
components, negative and zero components, and packets whose length is not a multiple of eight.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from engine.core.triangle import safe_inverse
from engine.packet.kernels import RF_ROWS, RI_ROWS, load_lane, load_packet

SENTINEL_F = np.float32(7.5)
SENTINEL_I = 77


@njit(cache=True)
def load_one_by_one(org, inv, dirs, tmin, tmax, start, n, rf, ri):
    live = 0
    for i in range(n):
        live += load_lane(org, inv, dirs, tmin, tmax, start + i, rf, ri, i)
    return live


@njit(cache=True)
def load_whole_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near):
    return load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)


def awkward_rays(rng, n):
    """n rays with ties between |direction| components, negative dominant components, zeros,
    dead and NaN segments."""
    org = rng.normal(size=(n, 3)).astype(np.float32)
    dirs = rng.normal(size=(n, 3)).astype(np.float32)
    dirs[::5, 1] = dirs[::5, 0]             # |dx| == |dy|
    dirs[::7, 2] = -dirs[::7, 1]            # |dy| == |dz|, opposite signs
    dirs[::9] = -np.abs(dirs[::9])          # every component negative
    dirs[::11, 0] = 0.0
    dirs[::13, 1:] = 0.0                    # along x only
    dirs[::17] = np.float32(0.5)            # all three equal
    dirs[np.all(dirs == 0, axis=1)] = (0.0, 0.0, -1.0)  # a ray has a direction (ray_shear)
    inv = safe_inverse(dirs)
    tmin = np.zeros(n, np.float32)
    tmax = rng.uniform(-1.0, 10.0, n).astype(np.float32)  # some tmax < tmin: dead
    tmin[::19] = np.nan
    tmax[::23] = np.nan
    tmin[::29] = np.float32(2.0)
    tmax[::29] = np.float32(2.0)            # a point segment is live
    return org, inv, dirs, tmin, tmax


def loaded(loader, rays, start, n, extra=()):
    rf = np.full((RF_ROWS, n + 8), SENTINEL_F, np.float32)
    ri = np.full((RI_ROWS, n + 8), SENTINEL_I, np.int32)
    live = loader(*rays, start, n, rf, ri, *extra)
    return live, rf, ri


@pytest.mark.parametrize("n", [8, 64, 256, 36, 4])
def test_packets_load_as_ray_by_ray(n):
    rays = awkward_rays(np.random.default_rng(n), 300)
    start = 12
    live_1, rf_1, ri_1 = loaded(load_one_by_one, rays, start, n)
    live_8, rf_8, ri_8 = loaded(load_whole_packet, rays, start, n, (np.zeros(6, np.int64),))
    assert live_8 == live_1
    assert np.array_equal(rf_8.view(np.uint32), rf_1.view(np.uint32))
    assert np.array_equal(ri_8, ri_1)
    # Lanes past the packet are not written.
    assert np.all(rf_8[:, n:] == SENTINEL_F) and np.all(ri_8[:, n:] == SENTINEL_I)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40).map(lambda k: 4 * k))
def test_random_packets_load_as_ray_by_ray(seed, n):
    rng = np.random.default_rng(seed)
    rays = awkward_rays(rng, n + 16)
    start = int(rng.integers(0, 16))
    live_1, rf_1, ri_1 = loaded(load_one_by_one, rays, start, n)
    live_8, rf_8, ri_8 = loaded(load_whole_packet, rays, start, n, (np.zeros(6, np.int64),))
    assert live_8 == live_1
    assert np.array_equal(rf_8.view(np.uint32), rf_1.view(np.uint32))
    assert np.array_equal(ri_8, ri_1)


def test_rows_that_are_not_three_contiguous_floats_load_one_by_one():
    """A view whose rows are not 12 contiguous bytes (here every other row of a batch) cannot
    be read eight rows at a time; the packet still loads, ray by ray, with the same answer."""
    org, inv, dirs, tmin, tmax = awkward_rays(np.random.default_rng(5), 128)
    strided = (org[::2], inv[::2], dirs[::2], tmin[::2], tmax[::2])
    contiguous = tuple(np.ascontiguousarray(a) for a in strided)
    live_s, rf_s, ri_s = loaded(load_whole_packet, strided, 0, 64, (np.zeros(6, np.int64),))
    live_c, rf_c, ri_c = loaded(load_whole_packet, contiguous, 0, 64, (np.zeros(6, np.int64),))
    assert live_s == live_c
    assert np.array_equal(rf_s.view(np.uint32), rf_c.view(np.uint32))
    assert np.array_equal(ri_s, ri_c)


def test_near_child_order_follows_the_live_rays_summed_direction():
    """The near-child table: per axis, the upper child first when the live rays travel towards
    -axis in sum; dead lanes (here pointing the other way) do not count."""
    n = 16
    org = np.zeros((n, 3), np.float32)
    dirs = np.tile(np.array([[-1.0, 0.5, -0.25]], np.float32), (n, 1))
    dirs[8:] = -dirs[8:]
    tmin = np.zeros(n, np.float32)
    tmax = np.full(n, 10.0, np.float32)
    tmax[8:] = -1.0  # the reversed rays are dead
    near = np.zeros(6, np.int64)
    loaded(load_whole_packet, (org, safe_inverse(dirs), dirs, tmin, tmax), 0, n, (near,))
    assert list(near) == [1, 0, 0, 1, 1, 0]
