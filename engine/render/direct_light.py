"""Direct lighting from one point light: shadow-ray candidates, then diffuse + Phong specular.

The Whitted loop (``engine.render.whitted``) shades a batch light by light: which hit lanes face
the light (``light_directions``), one shadow ray for each of those -- in their own packet, either
compacted by ``engine.packet.compact`` or, when nearly every lane casts one, walked where they
are (``light_directions`` leaves every lane ready to be a ray: unlit lanes dead) -- and the
diffuse + Phong specular term of the unshadowed ones (``add_light`` for compacted rays,
``add_light_in_place`` for rays walked in their lanes). Each is one parallel pass, float32 like
the arrays it fills, in the same operation order as the numpy expressions they replaced (images
stay bit-identical).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.core.lanes8 import bit_count8, rows_contiguous, rows_of_three
from engine.packet.compact import inverse_component
from engine.render.add_light8 import add_light8
from engine.render.light8 import light_directions8

_TINY = np.float32(1e-30)
_ZERO = np.float32(0.0)
_TWO = np.float32(2.0)
#: Shadow rays stop just short of the light.
SHADOW_TMAX_SCALE = np.float32(1.0 - 1e-4)
_DEAD_TMAX = np.float32(-np.inf)


@njit(cache=True, inline="always")
def light_direction_lane(i, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax):
    """Row ``i`` of ``light_directions`` for a lane that hit (shared by the CPU kernel and the
    device twin in ``engine.gpu.frame``)."""
    x = light[0] - leave[i, 0]
    y = light[1] - leave[i, 1]
    z = light[2] - leave[i, 2]
    length = np.float32(math.sqrt(x * x + y * y + z * z))
    scale = max(length, _TINY)
    x, y, z = x / scale, y / scale, z / scale
    to_light[i, 0], to_light[i, 1], to_light[i, 2] = x, y, z
    dist[i] = length
    shadow_tmax[i] = length * SHADOW_TMAX_SCALE
    cos_s = ns[i, 0] * x + ns[i, 1] * y + ns[i, 2] * z
    ndotl[i] = cos_s
    lit[i] = cos_s > _ZERO and ng[i, 0] * x + ng[i, 1] * y + ng[i, 2] * z > _ZERO


@njit(cache=True, parallel=True)
def light_directions(hit, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax, inv_to_light):
    """For the lanes with ``hit`` (bool[R]) leaving from ``leave`` (f32[R,3], already off the
    surface) with shading normals ``ns`` and ray-facing geometric normals ``ng`` (f32[R,3]) and a
    light at ``light`` (f32[3]), fill the unit directions to the light ``to_light`` (f32[R,3]),
    the distances ``dist`` (f32[R]), cos ``ndotl`` = ns . to_light (f32[R]), ``lit`` (bool[R]):
    the light is in front of both normals (False on lanes without a hit), and ``shadow_tmax``
    (f32[R]) the shadow ray's end, just short of the light. Returns how many lanes are lit.

    Every lane is left a shadow ray from ``leave`` along ``to_light`` up to ``shadow_tmax``,
    with ``inv_to_light`` (f32[R,3], ``inverse_component`` of to_light) beside it, so that the
    batch's own lanes can be walked as the shadow batch (tmin 0): a lane that is not lit is dead
    (shadow_tmax -inf) and a lane without a hit points along +z."""
    n = leave.shape[0]
    # Eight lanes a step (``light_directions8``, the same bits) where the rows allow it.
    vector = rows_of_three(leave) and rows_of_three(ns) and rows_of_three(ng) and rows_of_three(to_light) \
        and rows_of_three(inv_to_light)
    blocks = n // 8 if vector else 0
    lit_lanes = 0
    for b in prange(blocks):
        lit_lanes += bit_count8(light_directions8(hit, leave, ns, ng, light, to_light, dist, ndotl, lit,
                                                  shadow_tmax, inv_to_light, 8 * b))
    for i in range(8 * blocks, n):
        if hit[i]:
            light_direction_lane(i, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax)
        else:
            lit[i] = False
            to_light[i, 0], to_light[i, 1], to_light[i, 2] = _ZERO, _ZERO, np.float32(1.0)
        if lit[i]:
            lit_lanes += 1
        else:
            shadow_tmax[i] = _DEAD_TMAX
        for a in range(3):
            inv_to_light[i, a] = inverse_component(to_light[i, a])
    return lit_lanes


@njit(cache=True, inline="always")
def add_light_lane(i, color, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel, light_color):
    """color[i] += the diffuse + Phong term of one unshadowed light (see ``add_light``)."""
    cos_s = ndotl[i]
    rx = _TWO * cos_s * ns[i, 0] - to_light[i, 0]
    ry = _TWO * cos_s * ns[i, 1] - to_light[i, 1]
    rz = _TWO * cos_s * ns[i, 2] - to_light[i, 2]
    highlight = max(-(rx * view[i, 0] + ry * view[i, 1] + rz * view[i, 2]), _ZERO)
    k = mat[i]
    # pow is most of this step's time (kitchen primary batch: 1.6 of 4.6 ms), and half the lanes
    # face away from the highlight: 0 ** s is 0 for s > 0 (0 ** 0 is 1, so that case still calls).
    s = shininess[k]
    spec = _ZERO if highlight == _ZERO and s > _ZERO else highlight ** s
    for c in range(3):
        color[i, c] += light_color[c] * (diffuse[k, c] * texel[i, c] * cos_s + specular[k, c] * spec)


@njit(cache=True, parallel=True)
def add_light(color, lane, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel,
              light_color):
    """color[i] += light_color * (diffuse * texel * ndotl + specular * max(r . -view, 0)^shininess)
    for the lane i = lane[j] of every shadow ray j that is not ``occluded``, r the light
    direction mirrored about ns. lane: i64[S] (-1: padding; live entries distinct), occluded:
    bool[S]; color, ns, to_light, view (unit ray directions), texel: f32[R,3]; ndotl: f32[R];
    mat: i32[R] material ids into diffuse, specular (f32[K,3]) and shininess (f32[K]);
    light_color: f32[3]."""
    for j in prange(lane.shape[0]):
        i = lane[j]
        if i < 0 or occluded[j]:
            continue
        add_light_lane(i, color, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel, light_color)


@njit(cache=True, parallel=True)
def add_light_in_place(color, lit, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel,
                       light_color):
    """``add_light`` for shadow rays walked in their own lanes (``light_directions``): lane i
    adds the light when it is ``lit`` and its ray is not ``occluded`` (bool[R] each). Eight
    lanes a step where the rows allow it (``engine.render.add_light8``: the same bits), the rest
    lane by lane."""
    vector = rows_of_three(color) and rows_of_three(ns) and rows_of_three(to_light) and rows_of_three(view) \
        and rows_of_three(texel) and rows_contiguous(diffuse) and rows_contiguous(specular) \
        and diffuse.shape[1] == 3 and specular.shape[1] == 3
    blocks = lit.shape[0] // 8 if vector else 0
    for b in prange(blocks):
        add_light8(color, lit, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel,
                   light_color, 8 * b)
    for i in prange(8 * blocks, lit.shape[0]):
        if lit[i] and not occluded[i]:
            add_light_lane(i, color, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel,
                           light_color)
