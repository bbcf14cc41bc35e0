"""Rays placed on a grid by key on the device, as ``engine.rayspace.light_grid`` (shadow rays by
direction from their light) and ``engine.rayspace.direction_grid`` (reflection and refraction
rays by screen tile, then direction) place them on the CPU: their key functions
(``octahedral``, ``morton2``, ``cell_key``, ``tile_direction_key``, ``rank_pixel``, ``is_live``) compiled as
device twins, so every ray gets the CPU's pixel.

Keys: for the light grid ``_bounds`` first reduces the live rays' map rectangle (per thread over a
grid stride, per block in shared memory, one atomic per block and bound); ``_count_keys`` keys
each live ray by its light-grid cell or by its tile and direction, and counts the keys; a scan
gives each key its first slot, ``_fill_cells`` puts a key's rays in its slots in whatever order
the atomics ran, and ``_place_ranked`` gives each ray the rank the CPU's stable sort gives it
(its key's first slot plus the rays of its key with a smaller id) and writes the pixel of that
rank. One host wait: the scan's total, which sizes the screen.

The rank is counted, not sorted: one thread a ray, each reading its key's slots (the threads of a
warp mostly share a key, so the reads are broadcasts). A key's rays were first sorted in place,
one thread a key (insertion sort): a mirror's 32 x 32 tile sends up to 2,048 rays into one
direction cell, and that one thread's k^2/4 dependent steps made the sort the largest kernel of a
kitchen-paper frame on an H100 (55 ms of 133 ms, session 36). Counting costs k steps a ray, in
parallel; a key holding most of a queue (every ray in one direction) still costs k^2 in all.
"""
from __future__ import annotations

import numpy as np

from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.fill import fill_array
from engine.gpu.twin import device_twin
from engine.rayspace import direction_grid, light_grid
from engine.rayspace.direction_grid import key_bits, tile_size
from engine.rayspace.light_grid import cell_bits, grid_side

cuda = require_cuda()

_octahedral = device_twin(light_grid.octahedral)
_morton2 = device_twin(light_grid.morton2)
_cell_key = device_twin(light_grid.cell_key, cell_scale=device_twin(light_grid.cell_scale), morton2=_morton2)
_rank_pixel = device_twin(light_grid.rank_pixel)
_is_live = device_twin(light_grid.is_live)
_tile_direction_key = device_twin(direction_grid.tile_direction_key, octahedral=_octahedral, morton2=_morton2)

#: Blocks of the bounds reduction: each thread folds n / (REDUCE_BLOCKS * BLOCK) rays first.
REDUCE_BLOCKS = 128
_EMPTY_BOUNDS = np.array([np.inf, -np.inf, np.inf, -np.inf])


@cuda.jit
def _bounds(dirs, tmin, tmax, pixel, n, bounds):
    """bounds f64[4] (low_u, high_u, low_v, high_v, starting at inf, -inf, inf, -inf) over the
    live rays 0 .. n-1."""
    shared = cuda.shared.array(4, np.float64)
    if cuda.threadIdx.x == 0:
        shared[0] = np.inf
        shared[1] = -np.inf
        shared[2] = np.inf
        shared[3] = -np.inf
    cuda.syncthreads()
    low_u, high_u, low_v, high_v = np.inf, -np.inf, np.inf, -np.inf
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        if _is_live(pixel, tmin, tmax, r):
            u, v = _octahedral(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            low_u, high_u = min(low_u, u), max(high_u, u)
            low_v, high_v = min(low_v, v), max(high_v, v)
    if low_u <= high_u:
        cuda.atomic.min(shared, 0, low_u)
        cuda.atomic.max(shared, 1, high_u)
        cuda.atomic.min(shared, 2, low_v)
        cuda.atomic.max(shared, 3, high_v)
    cuda.syncthreads()
    if cuda.threadIdx.x == 0 and shared[0] <= shared[1]:
        cuda.atomic.min(bounds, 0, shared[0])
        cuda.atomic.max(bounds, 1, shared[1])
        cuda.atomic.min(bounds, 2, shared[2])
        cuda.atomic.max(bounds, 3, shared[3])


#: ``_count_keys``'s key kinds.
LIGHT_CELL, TILE_DIRECTION = 0, 1


@cuda.jit
def _count_keys(dirs, tmin, tmax, pixel, n, n_pixels, kind, bounds, bits, width, tile, keys, key_count, bad_pixel):
    """keys[r]: live ray r's key (-1 when dead), counted per key: its light-grid cell (kind
    LIGHT_CELL: map rectangle ``bounds``, 2^bits cells a side) or its tile-direction key (kind
    TILE_DIRECTION: screen ``width`` wide, ``tile`` pixel tiles). A live ray off the screen goes
    to bad_pixel[0] (atomic max) instead."""
    r = cuda.grid(1)
    if r < n:
        keys[r] = -1
        if _is_live(pixel, tmin, tmax, r):
            if pixel[r] >= n_pixels:
                cuda.atomic.max(bad_pixel, 0, pixel[r])
            else:
                if kind == LIGHT_CELL:
                    u, v = _octahedral(dirs[r, 0], dirs[r, 1], dirs[r, 2])
                    key = _cell_key(u, v, bounds[0], bounds[1], bounds[2], bounds[3], bits)
                else:
                    key = _tile_direction_key(dirs[r, 0], dirs[r, 1], dirs[r, 2], pixel[r], width, tile)
                keys[r] = key
                cuda.atomic.add(key_count, key, 1)


@cuda.jit
def _fill_cells(keys, n, cell_start, fill, order):
    r = cuda.grid(1)
    if r < n and keys[r] >= 0:
        order[cell_start[keys[r]] + cuda.atomic.add(fill, keys[r], 1)] = r


@cuda.jit
def _place_ranked(keys, order, cell_start, n_live, side, out):
    """out[ray] = the pixel of the ray's rank in the stable order by key, for the ray in slot k
    (``order`` i32[n_live] as ``_fill_cells`` left it; cell_start i32[cells+1])."""
    k = cuda.grid(1)
    if k < n_live:
        ray = order[k]
        key = keys[ray]
        rank = cell_start[key]
        for j in range(cell_start[key], cell_start[key + 1]):
            if order[j] < ray:
                rank += 1
        out[ray] = _rank_pixel(rank, side)


def _key_arrays(scratch, n: int, n_cells: int):
    """(keys i32[n], count i32[n_cells] zeroed, bad_pixel i32[1] = -1) scratch arrays."""
    keys = scratch.get("grid_key", n, np.int32)
    count = scratch.get("grid_cell_count", n_cells, np.int32)
    bad = scratch.get("grid_bad_pixel", 1, np.int32)
    scratch.launch(fill_array, blocks(n_cells), BLOCK, count, n_cells, 0)
    scratch.launch(fill_array, 1, BLOCK, bad, 1, -1)
    return keys, count, bad


def _place_by_keys(scratch, scanner, keys, count, bad, n: int, n_cells: int, width: int, height: int):
    """(i32[n] pixels, side) from counted keys (``engine.rayspace.light_grid.place_by_keys``)."""
    out = scratch.get("grid_pixel", n, np.int32)
    fill = scratch.get("grid_cell_fill", n_cells, np.int32)
    start = scratch.get("grid_cell_start", n_cells + 1, np.int32)
    launch = scratch.launch
    launch(fill_array, blocks(n_cells), BLOCK, fill, n_cells, 0)
    if n:
        launch(fill_array, blocks(n), BLOCK, out, n, -1)
    n_live = scanner.exclusive_scan(count, n_cells, start)
    worst = int(bad.copy_to_host()[0])
    if worst >= 0:
        raise ValueError(f"ray pixel {worst} is outside the {width}x{height} screen grid")
    side = grid_side(n_live)
    if n_live:
        order = scratch.get("grid_order", n_live, np.int32)
        launch(_fill_cells, blocks(n), BLOCK, keys, n, start, fill, order)
        launch(_place_ranked, blocks(n_live), BLOCK, keys, order, start, n_live, side, out)
    return out, side


def light_grid_pixels(scratch, scanner, dirs, tmin, tmax, pixel, n: int, width: int, height: int):
    """(i32[n] device array, side): rays 0 .. n-1 of the device queue (dirs f32[C,3]; tmin, tmax
    f32[C]; pixel i32[C] on the ``width x height`` screen) at their light-grid pixels on a
    ``side x side`` screen, as ``engine.rayspace.light_grid.light_grid_pixels`` places them;
    -1 for dead rays. A live ray off the screen raises ValueError, as the build does."""
    bits = cell_bits(n)
    n_cells = 1 << (2 * bits)
    bounds = scratch.get("light_bounds", 4, np.float64)
    bounds.copy_to_device(_EMPTY_BOUNDS)
    keys, count, bad = _key_arrays(scratch, n, n_cells)
    if n:
        scratch.launch(_bounds, min(REDUCE_BLOCKS, blocks(n)), BLOCK, dirs, tmin, tmax, pixel, n, bounds)
        scratch.launch(_count_keys, blocks(n), BLOCK, dirs, tmin, tmax, pixel, n, int(width) * int(height), LIGHT_CELL,
                       bounds, bits, 0, 0, keys, count, bad)
    return _place_by_keys(scratch, scanner, keys, count, bad, n, n_cells, int(width), int(height))


def direction_grid_pixels(scratch, scanner, dirs, tmin, tmax, pixel, n: int, width: int, height: int):
    """(i32[n] device array, side): rays 0 .. n-1 placed by screen tile and direction, as
    ``engine.rayspace.direction_grid.direction_grid_pixels`` places them (arguments as
    ``light_grid_pixels``)."""
    n_cells = 1 << key_bits(int(width), int(height))
    keys, count, bad = _key_arrays(scratch, n, n_cells)
    if n:
        bounds = scratch.get("light_bounds", 4, np.float64)  # not read for this kind
        scratch.launch(_count_keys, blocks(n), BLOCK, dirs, tmin, tmax, pixel, n, int(width) * int(height),
                       TILE_DIRECTION, bounds, 0, int(width), tile_size(int(width), int(height)), keys, count, bad)
    return _place_by_keys(scratch, scanner, keys, count, bad, n, n_cells, int(width), int(height))
