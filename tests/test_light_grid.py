"""The light grid (engine/rayspace/light_grid.py): rays that share a light grouped by direction."""
from __future__ import annotations

import numpy as np
import pytest

from engine.rayspace.light_grid import cell_bits, grid_side, light_grid_pixels, octahedral, rank_pixel


def _unfold(u, v):
    """The direction (unit) of octahedral map point (u, v): the map's inverse, written apart."""
    z = 1.0 - abs(u) - abs(v)
    if z < 0:
        u, v = (1.0 - abs(v)) * np.sign(u), (1.0 - abs(u)) * np.sign(v)
    d = np.array([u, v, z])
    return d / np.linalg.norm(d)


def test_octahedral_map_is_invertible_on_both_halves():
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(500, 3)).astype(np.float32)
    dirs[:5] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [1, 1, -1]]
    for d in dirs:
        u, v = octahedral(d[0], d[1], d[2])
        assert abs(u) <= 1 and abs(v) <= 1
        assert np.allclose(_unfold(u, v), d / np.linalg.norm(d.astype(np.float64)), atol=1e-12)
    assert octahedral(0.0, 0.0, 0.0) == (0.0, 0.0) and octahedral(np.nan, 0.0, 1.0) == (0.0, 0.0)


def test_rank_pixels_tile_the_screen_four_to_a_block():
    side = 8
    pixels = [rank_pixel(k, side) for k in range(side * side)]
    assert sorted(pixels) == list(range(side * side))
    for first in range(0, side * side, 4):  # ranks 4k .. 4k+3: one 2x2 block
        blocks = {(p % side) // 2 + side * ((p // side) // 2) for p in pixels[first:first + 4]}
        assert len(blocks) == 1
    assert grid_side(0) == 1 and grid_side(64) == 8 and grid_side(65) == 16
    assert cell_bits(1) == 1 and cell_bits(1 << 20) == 11 and cell_bits(1 << 30) == 11


def test_blocks_hold_neighbouring_directions_not_neighbouring_pixels():
    """Two fans of directions interleaved pixel by pixel: by pixel every 2x2 block mixes them,
    on the light grid almost none does; dead rays stay dead, every live ray has a pixel of its own."""
    rng = np.random.default_rng(5)
    n = 256
    fan = np.where(np.arange(n)[:, None] % 2 == 0, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    dirs = (fan + rng.normal(scale=0.01, size=(n, 3))).astype(np.float32)
    tmin, tmax = np.zeros(n, np.float32), np.ones(n, np.float32)
    tmax[7] = -1  # dead: empty interval
    pixel = np.arange(n, dtype=np.int32)
    pixel[9] = -1  # dead: no pixel
    out, side = light_grid_pixels(dirs, tmin, tmax, pixel, 16, 16)
    live = (pixel >= 0) & (tmin <= tmax)
    assert (out[~live] == -1).all() and side == 16
    assert len(np.unique(out[live])) == live.sum() and out[live].max() < side * side
    # Only where the Morton order passes from one fan's cells to the other's can a block mix.
    assert _mixed_blocks(out, live, side) <= 3 < 60 <= _mixed_blocks(pixel, live, 16)


def _mixed_blocks(pixel, live, side):
    """2x2 blocks of ``pixel`` holding rays of both fans (even and odd ray ids)."""
    block = (pixel // side // 2) * (side // 2) + (pixel % side) // 2
    ids = np.arange(pixel.shape[0])
    return sum(len(set(ids[live & (block == b)] % 2)) == 2 for b in np.unique(block[live]))


def test_a_live_ray_off_the_screen_is_refused():
    dirs = np.tile(np.float32([0, 0, 1]), (4, 1))
    with pytest.raises(ValueError, match="ray pixel 16 is outside the 4x4 screen grid"):
        light_grid_pixels(dirs, np.zeros(4, np.float32), np.ones(4, np.float32), np.int32([0, 1, 16, 2]), 4, 4)
