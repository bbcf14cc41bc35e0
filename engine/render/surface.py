"""What a ray hit: the surface at each hit of a batch, and the background where it missed.

``shade_surface`` is the first shading pass over a traced batch, in parallel over its packets:
for every live lane that missed it adds the background (times the lane's weight) to the lane's
pixel; for every hit it fills the lane's row of a ``Surface``: the hit point, rounded once from
double (``engine.core.offset``), the ray-facing geometric normal, the interpolated shading normal,
the material, the texel, the ambient term and the origin for rays that leave towards the ray's
side. A pixel belongs to one tile and a tile to one packet, so a packet's lanes are the only
writers of their pixels: no atomics, and a pixel's contributions land in lane order.

Every expression follows the numpy shading it replaced, operation for operation, in the same
precision, so images stay bit-identical: dot products are (x + y) + z of float32 products, as
numpy's einsum sums three terms.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from engine.core.lanes8 import rows_contiguous, rows_of_three
from engine.core.offset import MIN_MAGNITUDE, OFFSET_SCALE
from engine.packet.compact import new_array
from engine.render.surface8 import surface8
from engine.render.surface_record import RECORD_WIDTH


class Surface(NamedTuple):
    """Per-lane shading state of a batch of R rays (rows of lanes that did not hit are unset).

    hit: bool[R]; point: f32[R,3] the hit point; magnitude: f32[R] the offset scale
    (``engine.core.offset.coordinate_magnitude``); view: f32[R,3] the unit ray direction;
    normal: f32[R,3] the shading normal, facing the ray; facing: f32[R,3] the geometric normal,
    facing the ray; entering: bool[R] the ray hit the front face; material: i32[R];
    texel: f32[R,3]; color: f32[R,3] the light gathered so far (ambient, then each light);
    leave: f32[R,3] the origin of rays leaving towards the ray's side (zero on lanes without a
    hit); texel_row: i32[R] the row of the lane's texel in the stacked texels (-1: untextured),
    kept between the two loops of ``shade_surface``.
    """

    hit: np.ndarray
    point: np.ndarray
    magnitude: np.ndarray
    view: np.ndarray
    normal: np.ndarray
    facing: np.ndarray
    entering: np.ndarray
    material: np.ndarray
    texel: np.ndarray
    color: np.ndarray
    leave: np.ndarray
    texel_row: np.ndarray


#: Per-lane shape tail and dtype of each Surface field.
SURFACE_FIELDS = {"hit": ((), np.bool_), "point": ((3,), np.float32), "magnitude": ((), np.float32),
                  "view": ((3,), np.float32), "normal": ((3,), np.float32), "facing": ((3,), np.float32),
                  "entering": ((), np.bool_), "material": ((), np.int32), "texel": ((3,), np.float32),
                  "color": ((3,), np.float32), "leave": ((3,), np.float32),
                  "texel_row": ((), np.int32)}


def new_surface(r: int, allocate=new_array) -> Surface:
    """Uninitialised per-lane arrays for a batch of ``r`` rays, from ``allocate(name, rows,
    tail, dtype)``."""
    return Surface(*(allocate(name, r, tail, dtype) for name, (tail, dtype) in SURFACE_FIELDS.items()))


@njit(cache=True, inline="always")
def dot3(a, b):
    """(a0 b0 + a1 b1) + a2 b2 for float32 rows, summed as numpy's einsum does."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def unit_wrap(s):
    """s mod 1 in [0, 1), as numpy's float remainder gives it; most coordinates already lie in
    [0, 1), and skipping the fmod call for them halves the cost of a texture lookup."""
    one = np.float32(1.0)
    return s if np.float32(0.0) <= s < one else s % one


@njit(cache=True, inline="always")
def texel_at(start, width, height, s, t):
    """Row of the stacked texels (``MaterialTable``) of the nearest texel, wrapping, of the
    texture that begins at row ``start`` (width x height) at (s, t)."""
    # int(): math.floor gives an integer on the CPU target but a float on CUDA.
    x = int(math.floor(unit_wrap(s) * np.float32(width)))
    y = int(math.floor((np.float32(1.0) - unit_wrap(t)) * np.float32(height)))
    # x lies in [0, width] and y in [0, height] (the product may round up to the edge): the
    # wrap of the edge is the integer modulo, without its division.
    if x >= width:
        x -= width
    if y >= height:
        y -= height
    return start + y * width + x


@njit(cache=True, inline="always")
def fill_surface_lane(i, p, dirs, u, v, v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude,
                      interpolated, texture_layout, point, magnitude, view, normal, facing, entering, material,
                      leave):
    """Row ``i`` of a Surface (point .. leave, all but texel and color) for a ray along dirs[i]
    that hit triangle ``p`` at barycentrics u[i], v[i]; returns the row of its texel in the
    stacked texels, -1 when its material has no texture (``texel_color_lane`` then looks it up).
    The per-lane shading of both targets: ``shade_surface`` calls it on the CPU and
    ``engine.gpu.frame`` compiles its device twin (``engine.gpu.twin``). interpolated:
    (has_normals, has_uvs), one tuple because numba's inliner refuses a call of more than 30
    arguments, and inlined is 2.5x faster here than called (kitchen surface pass)."""
    has_normals, has_uvs = interpolated
    one = np.float32(1.0)
    length = np.float32(math.sqrt(dot3(dirs[i], dirs[i])))
    for a in range(3):
        view[i, a] = dirs[i, a] / length
    # The hit point from the exact corners in double, rounded once.
    u64, v64 = np.float64(u[i]), np.float64(v[i])
    w64 = 1.0 - u64 - v64
    largest = np.float32(0.0)
    for a in range(3):
        x = np.float32(w64 * np.float64(v0[p, a]) + u64 * np.float64(v1[p, a]) + v64 * np.float64(v2[p, a]))
        point[i, a] = x
        largest = max(largest, abs(x))
    magnitude[i] = max(largest, corner_magnitude[p])
    front = dot3(ng[p], view[i]) < 0
    entering[i] = front
    for a in range(3):
        facing[i, a] = ng[p, a] if front else -ng[p, a]
    w = one - u[i] - v[i]
    if has_normals:
        nx = w * normals[p, 0, 0] + u[i] * normals[p, 1, 0] + v[i] * normals[p, 2, 0]
        ny = w * normals[p, 0, 1] + u[i] * normals[p, 1, 1] + v[i] * normals[p, 2, 1]
        nz = w * normals[p, 0, 2] + u[i] * normals[p, 1, 2] + v[i] * normals[p, 2, 2]
        size = np.float32(math.sqrt(nx * nx + ny * ny + nz * nz))
        if size > 0:
            nx, ny, nz = nx / size, ny / size, nz / size
        else:  # degenerate interpolation: the geometric normal (then turned to the ray)
            nx, ny, nz = ng[p, 0], ng[p, 1], ng[p, 2]
        if nx * facing[i, 0] + ny * facing[i, 1] + nz * facing[i, 2] < 0:
            nx, ny, nz = -nx, -ny, -nz
        normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
    else:
        for a in range(3):
            normal[i, a] = facing[i, a]
    m = tri_material[p]
    material[i] = m
    start = texture_layout[0, m]
    if has_uvs and start >= 0:
        s = w * uvs[p, 0, 0] + u[i] * uvs[p, 1, 0] + v[i] * uvs[p, 2, 0]
        t = w * uvs[p, 0, 1] + u[i] * uvs[p, 1, 1] + v[i] * uvs[p, 2, 1]
        row = texel_at(start, texture_layout[1, m], texture_layout[2, m], s, t)
    else:
        row = -1
    step = OFFSET_SCALE * max(magnitude[i], MIN_MAGNITUDE)
    for a in range(3):
        leave[i, a] = point[i, a] + step * facing[i, a]
    return row


@njit(cache=True, inline="always")
def texel_color_lane(i, row, m, texels, palette, ambient_light, ambient, texel, color):
    """Texel (white for row -1) and ambient colour of lane ``i``, material ``m``, whose texel is
    row ``row`` of the stacked texels (``fill_surface_lane``'s answer)."""
    for c in range(3):
        x = palette[texels[row, c]] if row >= 0 else np.float32(1.0)
        texel[i, c] = x
        color[i, c] = ambient_light[c] * ambient[m, c] * x


@njit(cache=True, inline="always")
def fill_surface_row(j, pixel, prim, dirs, u, v, v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude,
                     interpolated, texture_layout, hit, point, magnitude, view, normal, facing, entering, material,
                     leave, texel_row):
    """Lane j's Surface row (hit .. leave and texel_row), one lane at a time: ``surface8``'s
    scalar twin. A lane without a hit gets hit False and leave zero: a dead shadow lane starts
    there (``light_directions``), at a finite point."""
    p = prim[j] if pixel[j] >= 0 else -1
    hit[j] = p >= 0
    if p < 0:
        for a in range(3):
            leave[j, a] = np.float32(0.0)
        return
    texel_row[j] = fill_surface_lane(j, p, dirs, u, v, v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude,
                                     interpolated, texture_layout, point, magnitude, view, normal, facing, entering,
                                     material, leave)


@njit(cache=True)
def eight_lanes_fit(dirs, point, view, normal, facing, leave, records, n_triangles):
    """Whether ``shade_surface`` may take a batch eight lanes at a time (``surface8``): its lane
    rows (dirs .. leave) are 12 contiguous bytes each and ``records`` are the surface records of
    the n_triangles triangles (``engine.render.surface_record``) with contiguous rows. (Until
    session 33 the step read the triangle arrays themselves; until session 20 absent corner
    normals or uvs, shape (0, 3, k) with strides 0, failed this test, and the surface pass of
    every scene without them ran serially, lane by lane: ERW6 at 1024x1024 17.8 -> 5.8 ms.)"""
    return rows_of_three(dirs) and rows_of_three(point) and rows_of_three(view) and rows_of_three(normal) \
        and rows_of_three(facing) and rows_of_three(leave) and records.shape[0] == n_triangles \
        and records.shape[1] == RECORD_WIDTH and rows_contiguous(records)


@njit(cache=True, parallel=True)
def shade_surface(offsets, dirs, pixel, weight, prim, u, v,
                  v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude, records,
                  ambient, texture_layout, texels, palette, ambient_light, background, image,
                  hit, point, magnitude, view, normal, facing, entering, material, texel, color, leave,
                  texel_row):
    """Fill the Surface rows (hit .. texel_row, see ``Surface``) of a batch and add the background
    of its misses to ``image`` (f32[W*H,3]).

    Batch: packets offsets i32[K+1], dirs f32[R,3], pixel i32[R] (-1: padding), weight f32[R,3];
    its hits prim i32[R], u, v f32[R]. Triangles: corners v0, v1, v2, unit normals ng f32[T,3],
    corner normals f32[T,3,3] and uvs f32[T,3,2] (or none: first dimension 0), tri_material
    i32[T], corner_magnitude f32[T] (``triangle_magnitudes``), and the same in one record per
    triangle, records f32[T, 32] (``engine.render.surface_record.surface_records``: what the
    eight-lane step reads; the lane-by-lane one reads the arrays). Materials: ambient f32[M,3],
    textures as in ``engine.render.materials.MaterialTable``. ambient_light, background f32[3].

    The texel gathers run in a second loop over the packet's lanes: there they are independent
    loads back to back, so their cache misses overlap, where inside the long per-lane work of the
    first loop each one stalled it (kitchen primary rays, one thread: 46 -> 41 ms).
    """
    has_normals = normals.shape[0] > 0
    has_uvs = uvs.shape[0] > 0
    # The rows: eight lanes a step (``surface8``: the same bits) where the rows allow it, over the
    # whole batch regardless of packets (2x2 packets have four lanes); else lane by lane.
    vector = eight_lanes_fit(dirs, point, view, normal, facing, leave, records, v0.shape[0])
    n_lanes = dirs.shape[0]
    blocks = n_lanes // 8 if vector else 0
    for b in prange(blocks):
        surface8(dirs, pixel, prim, u, v, records, texture_layout, has_normals, has_uvs, hit, point, magnitude,
                 view, normal, facing, entering, material, leave, texel_row, 8 * b)
    # The lanes past the last block -- or every lane, serially, of a batch whose rows are not 12
    # contiguous bytes (not the renderer's): one inlined copy of the lane-by-lane step.
    for j in range(8 * blocks, n_lanes):
        fill_surface_row(j, pixel, prim, dirs, u, v, v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude,
                         (has_normals, has_uvs), texture_layout, hit, point, magnitude, view, normal, facing,
                         entering, material, leave, texel_row)
    # Per packet (a pixel belongs to one packet's lanes), lane by lane: the texel of a hit, or
    # the background of a miss added to its pixel (in lane order, the only image writes here).
    for k in prange(offsets.shape[0] - 1):
        for j in range(offsets[k], offsets[k + 1]):
            if hit[j]:
                texel_color_lane(j, texel_row[j], material[j], texels, palette, ambient_light, ambient, texel,
                                 color)
            elif pixel[j] >= 0:
                for c in range(3):
                    image[pixel[j], c] += weight[j, c] * background[c]
