"""Shadow rays placed on a grid over their directions from the light, instead of their pixels.

The hierarchy (``engine.rayspace.cone_sphere``) groups rays by a screen grid: 2x2 pixel blocks,
then mip-map levels. Reversed shadow rays all leave one point, so a node's bound is its cone of
directions alone, and neighbouring pixels can send their shadow rays in very different
directions (a silhouette, a surface seen at a grazing angle). Grouping them by direction
instead gives every node the narrowest cone its rays allow:

1. each live ray's direction goes on the octahedral map of the sphere (``octahedral``), and the
   live rays' bounding rectangle on it is cut into 2^b x 2^b cells (``cell_bits``: about four
   cells a ray of the batch, at most 2048 x 2048);
2. the rays are sorted by their cell's Morton code (``cell_key``), stably, so rays of one cell
   stay in ray (ancestral pixel) order;
3. the k-th ray of that order gets the *light-grid pixel* at Morton position k of a square
   ``side x side`` screen (``rank_pixel``; side the smallest power of two with side^2 >= the live
   rays), so every 2x2 block holds four neighbours on the map and every mip-map node a patch.

The build is unchanged and so are the answers: the grouping only decides which (node, triangle)
pairs the stream tests. Placing rays at their map cell directly (no sort) piled up to 191 rays on
one 2x2 block where the map is dense (the default scene), which the GPU's one-pair-per-thread
stream pays for in idle lanes; the rank gives every block four.

Every function here is also compiled for the GPU (``engine.gpu.rayspace.ray_grids`` twins
``octahedral``, ``morton2``, ``cell_key``, ``rank_pixel`` and ``is_live``): float64, and no product added to
anything (nothing a compiler may fuse), so both targets give every ray the same pixel.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.core.checked import one_of
from engine.core.radix import radix_argsort

#: The layouts ``[options.rayspace] shadow_grid`` takes: "light" (this module) or "pixel" (the
#: paper's: shadow rays at their ancestral pixels).
SHADOW_GRIDS = ("light", "pixel")


def checked_shadow_grid(value) -> str:
    """``value`` if it names a layout of ``SHADOW_GRIDS``, else a ConfigError."""
    return one_of(value, "options.rayspace: shadow_grid", SHADOW_GRIDS)


@njit(cache=True, inline="always")
def octahedral(dx, dy, dz):
    """(u, v) in [-1, 1]^2: direction (dx, dy, dz), any length, on the octahedral map of the
    sphere (the upper half folded out inside |u| + |v| <= 1, the lower half outside it).
    A zero or NaN direction maps to (0, 0)."""
    x, y, z = np.float64(dx), np.float64(dy), np.float64(dz)
    s = abs(x) + abs(y) + abs(z)
    if not s > 0.0:
        return 0.0, 0.0
    u = x / s
    v = y / s
    if z < 0.0:
        fold_u = 1.0 - abs(v)
        fold_v = 1.0 - abs(u)
        u = fold_u if x >= 0.0 else -fold_u
        v = fold_v if y >= 0.0 else -fold_v
    return u, v


#: Most cells per side of the map rectangle, as a power of two (2048 x 2048 cells).
MAX_CELL_BITS = 11


def cell_bits(rays: int) -> int:
    """b for a batch of ``rays`` rays (live or not): the smallest with 4^b >= 4 rays, at most
    MAX_CELL_BITS (a cell's rays keep their ray order, so a finer map gains little)."""
    bits = 1
    while bits < MAX_CELL_BITS and 4 ** bits < 4 * rays:
        bits += 1
    return bits


@njit(cache=True, inline="always")
def cell_scale(low, high, cells):
    """Cells per unit of the map so [low, high] spans ``cells`` cells (0 when low == high: the
    live rays then share one column or row)."""
    return cells / (high - low) if high > low else 0.0


@njit(cache=True, inline="always")
def morton2(x, y, bits):
    """The Morton code of (x, y) < 2^bits: x's bits at the even positions, y's at the odd."""
    key = 0
    for bit in range(bits):
        key |= ((x >> bit) & 1) << (2 * bit)
        key |= ((y >> bit) & 1) << (2 * bit + 1)
    return key


@njit(cache=True, inline="always")
def cell_key(u, v, low_u, high_u, low_v, high_v, bits):
    """The Morton code (x bits even, y bits odd) of the cell of map point (u, v) on the
    2^bits x 2^bits grid spanning [low_u, high_u] x [low_v, high_v]."""
    cells = 1 << bits
    x = min(max(int((u - low_u) * cell_scale(low_u, high_u, cells)), 0), cells - 1)
    y = min(max(int((v - low_v) * cell_scale(low_v, high_v, cells)), 0), cells - 1)
    return morton2(x, y, bits)


@njit(cache=True, inline="always")
def rank_pixel(rank, side):
    """The pixel y * side + x at Morton position ``rank`` of a ``side x side`` screen (side a
    power of two, rank < side^2)."""
    x = 0
    y = 0
    bit = 0
    while (1 << bit) < side:
        x |= ((rank >> (2 * bit)) & 1) << bit
        y |= ((rank >> (2 * bit + 1)) & 1) << bit
        bit += 1
    return y * side + x


def grid_side(live_rays: int) -> int:
    """The light grid's side: the smallest power of two whose square holds ``live_rays``."""
    side = 1
    while side * side < live_rays:
        side *= 2
    return side


@njit(cache=True, inline="always")
def is_live(pixel, tmin, tmax, r):
    """The hierarchy's live rays: a pixel, and a non-empty (not NaN) [tmin, tmax]."""
    return pixel[r] >= 0 and tmin[r] <= tmax[r]


@njit(cache=True)
def _bounds(dirs, tmin, tmax, pixel):
    """(low_u, high_u, low_v, high_v) of the live rays' map points; inf, -inf when none."""
    low_u, low_v, high_u, high_v = np.inf, np.inf, -np.inf, -np.inf
    for r in range(dirs.shape[0]):
        if is_live(pixel, tmin, tmax, r):
            u, v = octahedral(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            low_u, high_u = min(low_u, u), max(high_u, u)
            low_v, high_v = min(low_v, v), max(high_v, v)
    return low_u, high_u, low_v, high_v


@njit(cache=True, parallel=True)
def _cell_keys(dirs, tmin, tmax, pixel, low_u, high_u, low_v, high_v, bits, keys):
    for r in prange(dirs.shape[0]):
        if is_live(pixel, tmin, tmax, r):
            u, v = octahedral(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            keys[r] = cell_key(u, v, low_u, high_u, low_v, high_v, bits)
        else:
            keys[r] = -1


@njit(cache=True, parallel=True)
def _rank_pixels(order, side, out):
    for rank in prange(order.shape[0]):
        out[order[rank]] = rank_pixel(rank, side)


def light_grid_pixels(dirs: np.ndarray, tmin: np.ndarray, tmax: np.ndarray, pixel: np.ndarray,
                      width: int, height: int) -> tuple[np.ndarray, int]:
    """(i32[R] light-grid pixels, -1 for dead rays; side): the rays placed on a ``side x side``
    screen as the module doc describes. dirs: f32[R,3]; tmin, tmax: f32[R]; pixel: i32[R] on
    the ``width x height`` screen (a live ray off it is a ValueError, as in the build)."""
    pixel = np.ascontiguousarray(pixel, np.int32)
    check_on_screen(pixel, tmin, tmax, width, height)
    keys = np.empty(pixel.shape[0], np.int64)
    _cell_keys(dirs, tmin, tmax, pixel, *_bounds(dirs, tmin, tmax, pixel), cell_bits(pixel.shape[0]), keys)
    return place_by_keys(keys)


def check_on_screen(pixel: np.ndarray, tmin: np.ndarray, tmax: np.ndarray, width: int, height: int) -> None:
    """A live ray whose pixel is off the ``width x height`` screen is a ValueError, as in the build."""
    live = (pixel >= 0) & (tmin <= tmax)
    if live.any() and int(pixel[live].max()) >= width * height:
        raise ValueError(f"ray pixel {int(pixel[live].max())} is outside the {width}x{height} screen grid")


def place_by_keys(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """(i32[R] pixels, side): rays with key >= 0 sorted by key, stably (equal keys keep ray
    order), the k-th at Morton position k of a ``side x side`` screen; -1 where key < 0.
    keys: i64[R]."""
    order = np.flatnonzero(keys >= 0)
    order = order[radix_argsort(keys[order].astype(np.uint64))]  # stable, as numpy's kind="stable"
    side = grid_side(order.shape[0])
    out = np.full(keys.shape[0], -1, np.int32)
    _rank_pixels(order, side, out)
    return out, side
