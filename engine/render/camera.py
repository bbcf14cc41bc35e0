"""Camera rays: one ray through each pixel centre of a pinhole camera.

``camera_batch`` makes the primary batch straight in packet order (``engine.packet.layout``:
one packet per n x n tile, tiles row by row, inside a tile 2x2 blocks row by row), in parallel
over tiles: no per-pixel sort. ``camera_rays`` is the same rays in row-major pixel order, for
callers that want plain arrays (the API, the tests); both evaluate the direction the same way,
in double, rounded once to float32.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.core.lanes8 import rows_of_three
from engine.core.scene import Scene
from engine.core.types import Packets, RayBatch
from engine.packet.compact import inverse_component, new_array, write_dead_lane
from engine.render.camera8 import camera8


def image_plane(scene: Scene, width: int, height: int):
    """(eye, forward, right, up as f64[3], half_w, half_h): the camera basis and the image
    plane's half extents at distance 1."""
    eye, forward, right, up = scene.camera.basis()
    half_h = math.tan(math.radians(scene.camera.fov) / 2)
    return eye, forward, right, up, half_h * width / height, half_h


def camera_rays(scene: Scene, width: int, height: int):
    """(org f32[W*H,3], dir f32[W*H,3] unit): one ray through each pixel centre, row-major."""
    eye, forward, right, up, half_w, half_h = image_plane(scene, width, height)
    ys, xs = np.mgrid[0:height, 0:width]
    px = ((xs + 0.5) / width * 2 - 1) * half_w
    py = (1 - (ys + 0.5) / height * 2) * half_h
    d = forward + px[..., None] * right + py[..., None] * up
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3).astype(np.float32)
    return np.tile(eye.astype(np.float32), (width * height, 1)), d


@njit(cache=True, inline="always")
def image_x(x, width, half_w):
    """The image-plane coordinate (at distance 1, along ``right``) of pixel column x's centre."""
    return ((x + 0.5) / width * 2 - 1) * half_w


@njit(cache=True, inline="always")
def image_y(y, height, half_h):
    """The image-plane coordinate (at distance 1, along ``up``) of pixel row y's centre."""
    return (1 - (y + 0.5) / height * 2) * half_h


@njit(cache=True, inline="always")
def direction_through(px, py, forward, right, up):
    """The unit direction (3 f32) through the image-plane point (px, py): in double, rounded once.
    forward, right, up: f64[3]."""
    dx = forward[0] + px * right[0] + py * up[0]
    dy = forward[1] + px * right[1] + py * up[1]
    dz = forward[2] + px * right[2] + py * up[2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return np.float32(dx / norm), np.float32(dy / norm), np.float32(dz / norm)


@njit(cache=True, inline="always")
def camera_direction(x, y, width, height, forward, right, up, half_w, half_h):
    """The unit direction (3 f32) through pixel (x, y)'s centre: the expressions of
    ``camera_rays`` in the same order, in double, rounded once. forward, right, up: f64[3].
    Shared by the CPU camera (which takes the two image-plane coordinates once per row and
    column) and its device twin (``engine.gpu.frame``)."""
    return direction_through(image_x(x, width, half_w), image_y(y, height, half_h), forward, right, up)


@njit(cache=True)
def camera_packet_offsets(width, height, n):
    """i32[K+1]: one packet per n x n tile, row by row, each padded to whole 2x2 SIMD rays."""
    tiles_x = -(-width // n)
    n_tiles = tiles_x * (-(-height // n))
    offsets = np.empty(n_tiles + 1, np.int32)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        ty, tx = divmod(t, tiles_x)
        inside = min(n, width - tx * n) * min(n, height - ty * n)
        total += (inside + 3) // 4 * 4
    offsets[n_tiles] = total
    return offsets


@njit(cache=True, inline="always")
def tile_inside(t, tiles_x, n, width, height):
    """Whether tile t (n x n pixels) lies wholly inside the image."""
    ty, tx = divmod(np.int64(t), tiles_x)  # prange's index is unsigned: keep x, y integers
    return (tx + 1) * n <= width and (ty + 1) * n <= height


@njit(cache=True, inline="always")
def fill_camera_tile(t, tiles_x, n, column_x, row_y, eye, forward, right, up, width, height, offsets,
                     org, dirs, inv, tmin, tmax, pixel, weight):
    """Tile t's packet, pixel by pixel (``camera8``'s scalar twin), padded with dead lanes."""
    ty, tx = divmod(np.int64(t), tiles_x)
    half = n // 2
    out = offsets[t]
    for q in range(n * n):
        block, corner = divmod(q, 4)
        y = ty * n + (block // half) * 2 + corner // 2
        x = tx * n + (block % half) * 2 + corner % 2
        if y >= height or x >= width:
            continue
        d = direction_through(column_x[x], row_y[y], forward, right, up)
        for a in range(3):
            org[out, a] = eye[a]
            dirs[out, a] = d[a]
            inv[out, a] = inverse_component(d[a])
            weight[out, a] = np.float32(1.0)
        tmin[out] = np.float32(0.0)
        tmax[out] = np.float32(np.inf)
        pixel[out] = y * width + x
        out += 1
    while out < offsets[t + 1]:  # dead padding to whole 2x2 SIMD rays
        write_dead_lane(out, eye, org, dirs, inv, tmin, tmax, pixel, weight)
        out += 1


@njit(cache=True, inline="always")
def block_corner(t, block, tiles_x, n):
    """(x, y) of the top-left pixel of 2x2 block ``block`` of tile t."""
    ty, tx = divmod(np.int64(t), tiles_x)
    half = n // 2
    return tx * n + (block % half) * 2, ty * n + (block // half) * 2


@njit(cache=True, parallel=True)
def fill_camera_packets(eye, forward, right, up, half_w, half_h, width, height, n, offsets,
                        org, dirs, inv, tmin, tmax, pixel, weight):
    """Fill the primary batch in packet order (org, dir, inv_dir f32[R,3], tmin, tmax f32[R],
    pixel i32[R], weight f32[R,3]) for packets ``offsets``; eye f32[3], basis f64[3] each.

    Pixels inside the image go eight lanes -- two 2x2 blocks -- a step (``camera8``, the same
    bits): two blocks of one tile, or for 2x2 packets two neighbouring tiles; tiles at the
    image's edges go pixel by pixel."""
    tiles_x = -(-width // n)
    n_tiles = offsets.shape[0] - 1
    # Each column's and row's image-plane coordinate once, not once per pixel: two divisions
    # a ray fewer (1024^2 kitchen camera rays, 2 threads: 8.7 -> 6.1 ms), the same values.
    column_x = np.empty(width)
    for column in range(width):
        column_x[column] = image_x(column, width, half_w)
    row_y = np.empty(height)
    for row in range(height):
        row_y[row] = image_y(row, height, half_h)
    # The loop's unit: a tile, or for 2x2 packets two neighbouring tiles (eight lanes).
    per_unit = 2 if n == 2 else 1
    blocks_per_tile = n * n // 4
    vector = (n == 2 or n % 4 == 0) and rows_of_three(org) and rows_of_three(dirs) and rows_of_three(inv) \
        and rows_of_three(weight)
    for unit in prange(-(-n_tiles // per_unit)):
        first = np.int64(unit) * per_unit  # prange's index is unsigned: keep x, y integers
        last = min(first + per_unit, n_tiles)
        whole = vector and last - first == per_unit
        for t in range(first, last):
            whole = whole and tile_inside(t, tiles_x, n, width, height)
        if whole:
            out = offsets[first]
            for step in range(0, per_unit * blocks_per_tile, 2):
                tile0, block0 = divmod(step, blocks_per_tile)
                tile1, block1 = divmod(step + 1, blocks_per_tile)
                x0, y0 = block_corner(first + tile0, block0, tiles_x, n)
                x1, y1 = block_corner(first + tile1, block1, tiles_x, n)
                camera8(column_x, row_y, forward, right, up, eye, width, x0, y0, x1, y1, org, dirs, inv, tmin,
                        tmax, pixel, weight, out)
                out += 8
            continue
        for t in range(first, last):
            fill_camera_tile(t, tiles_x, n, column_x, row_y, eye, forward, right, up, width, height, offsets,
                             org, dirs, inv, tmin, tmax, pixel, weight)


def camera_batch(scene: Scene, width: int, height: int, n: int, allocate=new_array) -> tuple[RayBatch, Packets]:
    """(RayBatch "primary", Packets): the camera rays of a width x height image in n x n packets,
    the layout ``engine.packet.layout.make_batch`` gives ``camera_rays``. ``allocate(name, rows,
    tail, dtype)`` gives the arrays (a renderer passes reused buffers)."""
    eye, forward, right, up, half_w, half_h = image_plane(scene, width, height)
    offsets = camera_packet_offsets(width, height, n)
    r = int(offsets[-1])
    arrays = (allocate("org", r, (3,)), allocate("dir", r, (3,)), allocate("inv_dir", r, (3,)), allocate("tmin", r),
              allocate("tmax", r), allocate("pixel", r, (), np.int32), allocate("weight", r, (3,)))
    fill_camera_packets(eye.astype(np.float32), forward, right, up, half_w, half_h, width, height, n, offsets, *arrays)
    return RayBatch(*arrays, "primary"), Packets(offsets, n, width, height)
