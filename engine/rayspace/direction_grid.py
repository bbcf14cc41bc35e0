"""Reflection and refraction rays placed by screen tile, then direction, instead of by pixel.

Off a curved or finely tessellated surface, the secondary rays of neighbouring pixels leave in
directions that differ a lot, so a 2x2 pixel block's cone opens wide and meets many triangles
(kitchen-paper at 1024^2: a reflection ray's block tests 4,094 triangle spheres down the
hierarchy for 73 final candidates). Here each live ray gets a key: its ancestral pixel's
``tile x tile`` screen tile (Morton order of tiles) and, below it, the cell of its direction on
a 32 x 32 octahedral map of the whole sphere (Morton order of cells). The rays are sorted by
key, stably (a cell's rays keep ray order), and placed at Morton positions of a square screen as
``engine.rayspace.light_grid.place_by_keys`` does: a 2x2 block then holds four rays from one
tile that leave in about the same direction. Camera and shadow rays are not placed this way
(their pixels, or the light grid, group them better). The answers are unchanged.

Counted with the CPU plugin (kitchen-paper, ``rayspace`` for every kind, shadow rays by pixel):
at 1024^2, cone-sphere tests per reflection ray 4,094 -> 2,813, per refraction ray 13,957 ->
5,375; at 512^2, 7,594 -> 4,378 and 16,685 -> 10,688. Tiles of 8, 16, 64 and 128 pixels and
maps of 16^2 or 64^2 cells counted more; a 60-bit Morton key of origin and direction (no
tiles) 2,844 and 9,330 at 1024^2.

Compiled for the GPU as well (``engine.gpu.rayspace.ray_grids`` twins ``tile_direction_key``):
integer tile arithmetic and one float64 product per axis, so both targets give each ray the same key.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.core.checked import one_of
from engine.rayspace.light_grid import check_on_screen, is_live, morton2, octahedral, place_by_keys

#: The layouts ``[options.rayspace] secondary_grid`` takes: "direction" (this module) or "pixel"
#: (the paper's: reflection and refraction rays at their ancestral pixels).
SECONDARY_GRIDS = ("direction", "pixel")


def checked_secondary_grid(value) -> str:
    """``value`` if it names a layout of ``SECONDARY_GRIDS``, else a ConfigError."""
    return one_of(value, "options.rayspace: secondary_grid", SECONDARY_GRIDS)

#: Pixels a tile side (at most MAX_TILES tiles a side: larger screens get larger tiles).
TILE = 32
MAX_TILES = 128
#: Cells a side of the direction map, as a power of two (32 x 32 over the whole sphere).
DIRECTION_BITS = 5


def tile_size(width: int, height: int) -> int:
    """TILE, doubled until the screen is at most MAX_TILES tiles a side."""
    tile = TILE
    while -(-max(width, height) // tile) > MAX_TILES:
        tile *= 2
    return tile


def key_bits(width: int, height: int) -> int:
    """Bits of ``tile_direction_key`` on a ``width x height`` screen."""
    tiles, bits = -(-max(width, height) // tile_size(width, height)), 0
    while (1 << bits) < tiles:
        bits += 1
    return 2 * bits + 2 * DIRECTION_BITS


@njit(cache=True, inline="always")
def tile_direction_key(dx, dy, dz, pixel, width, tile):
    """The key of a ray leaving in direction (dx, dy, dz) from ancestral ``pixel`` (y * width
    + x): Morton code of its tile, then Morton code of its direction's map cell."""
    u, v = octahedral(dx, dy, dz)
    cells = 1 << DIRECTION_BITS
    half = cells * 0.5
    cu = min(max(int((u + 1.0) * half), 0), cells - 1)
    cv = min(max(int((v + 1.0) * half), 0), cells - 1)
    tile_key = morton2((pixel % width) // tile, (pixel // width) // tile, 16)
    return (tile_key << (2 * DIRECTION_BITS)) | morton2(cu, cv, DIRECTION_BITS)


@njit(cache=True, parallel=True)
def _keys(dirs, tmin, tmax, pixel, width, tile, keys):
    for r in prange(dirs.shape[0]):
        if is_live(pixel, tmin, tmax, r):
            keys[r] = tile_direction_key(dirs[r, 0], dirs[r, 1], dirs[r, 2], pixel[r], width, tile)
        else:
            keys[r] = -1


def direction_grid_pixels(dirs: np.ndarray, tmin: np.ndarray, tmax: np.ndarray, pixel: np.ndarray,
                          width: int, height: int) -> tuple[np.ndarray, int]:
    """(i32[R] pixels, -1 for dead rays; side): the rays placed on a ``side x side`` screen as
    the module doc describes. dirs: f32[R,3]; tmin, tmax: f32[R]; pixel: i32[R] ancestral pixels
    on the ``width x height`` screen (a live ray off it is a ValueError, as in the build)."""
    pixel = np.ascontiguousarray(pixel, np.int32)
    check_on_screen(pixel, tmin, tmax, width, height)
    keys = np.empty(pixel.shape[0], np.int64)
    _keys(dirs, tmin, tmax, pixel, width, tile_size(width, height), keys)
    return place_by_keys(keys)
