"""The direction grid (engine/rayspace/direction_grid.py): reflection and refraction rays grouped
by screen tile, then direction."""
from __future__ import annotations

import numpy as np
import pytest

from engine.rayspace.direction_grid import (DIRECTION_BITS, MAX_TILES, TILE, direction_grid_pixels, key_bits,
                                            tile_direction_key, tile_size)


def test_tiles_grow_with_the_screen_and_keys_fit_their_bits():
    assert tile_size(64, 64) == TILE and tile_size(TILE * MAX_TILES, 16) == TILE
    assert tile_size(TILE * MAX_TILES + 1, 16) == 2 * TILE and tile_size(16384, 16384) == 16384 // MAX_TILES
    for width, height in ((8, 8), (1024, 1024), (4096, 300), (16384, 16384)):
        tile = tile_size(width, height)
        corner = tile_direction_key(-1.0, -1.0, -1.0, width * height - 1, width, tile)
        assert 0 <= corner < (1 << key_bits(width, height))
    assert key_bits(1024, 1024) == 2 * 5 + 2 * DIRECTION_BITS


def _block_of(pixels, side):
    return (pixels // side // 2) * (side // 2) + (pixels % side) // 2


def test_a_block_holds_one_tile_and_one_direction():
    """Rays from two tiles, each leaving in one of two directions, interleaved ray by ray: by
    pixel every 2x2 block mixes directions; on the direction grid almost none mixes either."""
    rng = np.random.default_rng(7)
    width = height = 2 * TILE
    n = 512
    pixel = np.where(np.arange(n) % 4 < 2, 0, TILE + 1).astype(np.int32) + rng.integers(0, 4, n).astype(np.int32)
    # Two directions inside one map cell each (away from the cells' edges), slightly spread.
    fan = np.where((np.arange(n) % 2 == 0)[:, None], [0.2, 0.3, 1.0], [1.0, 0.4, 0.2])
    dirs = (fan + rng.uniform(-0.002, 0.002, size=(n, 3))).astype(np.float32)
    tmin, tmax = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    tmax[5] = -1  # dead
    out, side = direction_grid_pixels(dirs, tmin, tmax, pixel, width, height)
    live = tmin <= tmax
    assert (out[~live] == -1).all() and len(np.unique(out[live])) == live.sum()
    group = (pixel // TILE) * 2 + np.arange(n) % 2  # (tile, fan)
    blocks = _block_of(out, side)
    mixed = sum(len(set(group[live & (blocks == b)])) > 1 for b in np.unique(blocks[live]))
    assert mixed <= 3  # only where the sorted order passes from one (tile, fan) to the next
    by_pixel = _block_of(pixel, width)
    assert all(len(set(group[live & (by_pixel == b)])) > 1 for b in np.unique(by_pixel[live]))


def test_a_live_ray_off_the_screen_is_refused():
    dirs = np.tile(np.float32([0, 0, 1]), (3, 1))
    with pytest.raises(ValueError, match="ray pixel 16 is outside the 4x4 screen grid"):
        direction_grid_pixels(dirs, np.zeros(3, np.float32), np.ones(3, np.float32), np.int32([0, 16, 2]), 4, 4)
