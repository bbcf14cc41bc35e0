"""Direct lighting from one point light: the per-hit arithmetic of the Whitted shading loop.

The loop (``engine.render.whitted``) shades a batch's M hits light by light: which hits face the light
(``light_directions``), one shadow-ray batch for those, then the diffuse + Phong specular term of
the unshadowed ones (``add_light``). With several lights and a million hits a frame, this
arithmetic done as numpy array expressions cost more than tracing the shadow rays did; here it is
one parallel pass each, float32 throughout like the arrays it replaces.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_TINY = np.float32(1e-30)
_ZERO = np.float32(0.0)
_TWO = np.float32(2.0)


@njit(cache=True, parallel=True)
def light_directions(leave, ns, ng, light, to_light, dist, ndotl, lit):
    """For hits leaving from ``leave`` (f32[M,3], origins already off the surface) with shading
    normals ``ns`` and ray-facing geometric normals ``ng`` (f32[M,3]) and a light at ``light``
    (f32[3]), fill the unit directions to the light ``to_light`` (f32[M,3]), the distances
    ``dist`` (f32[M]), cos ``ndotl`` = ns . to_light (f32[M]) and ``lit`` (bool[M]): the light is
    in front of both normals."""
    for i in prange(leave.shape[0]):
        x = light[0] - leave[i, 0]
        y = light[1] - leave[i, 1]
        z = light[2] - leave[i, 2]
        length = np.float32(math.sqrt(x * x + y * y + z * z))
        scale = max(length, _TINY)
        x, y, z = x / scale, y / scale, z / scale
        to_light[i, 0], to_light[i, 1], to_light[i, 2] = x, y, z
        dist[i] = length
        cos_s = ns[i, 0] * x + ns[i, 1] * y + ns[i, 2] * z
        ndotl[i] = cos_s
        lit[i] = cos_s > _ZERO and ng[i, 0] * x + ng[i, 1] * y + ng[i, 2] * z > _ZERO


@njit(cache=True, parallel=True)
def add_light(color, visible, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel, light_color):
    """color[i] += light_color * (diffuse * texel * ndotl + specular * max(r . -view, 0)^shininess)
    for each hit i in ``visible`` (i64[V], distinct), r the light direction mirrored about ns.
    color, ns, to_light, view (unit ray directions), texel: f32[M,3]; ndotl: f32[M]; mat: i[M]
    material ids into diffuse, specular (f32[K,3]) and shininess (f32[K]); light_color: f32[3]."""
    for j in prange(visible.shape[0]):
        i = visible[j]
        cos_s = ndotl[i]
        rx = _TWO * cos_s * ns[i, 0] - to_light[i, 0]
        ry = _TWO * cos_s * ns[i, 1] - to_light[i, 1]
        rz = _TWO * cos_s * ns[i, 2] - to_light[i, 2]
        highlight = max(-(rx * view[i, 0] + ry * view[i, 1] + rz * view[i, 2]), _ZERO)
        k = mat[i]
        spec = highlight ** shininess[k]
        for c in range(3):
            color[i, c] += light_color[c] * (diffuse[k, c] * texel[i, c] * cos_s + specular[k, c] * spec)
