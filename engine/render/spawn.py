"""The end of shading a batch: its light into the image, and the rays it spawns.

``gather_and_spawn`` runs in parallel over the batch's packets. For each hit lane it adds
weight x colour to the lane's pixel (a packet's lanes are the only writers of their pixels, so
contributions land in lane order without atomics) and, when the loop goes deeper, fills the
lane's row of ``Children``: the mirror direction about the shading normal (the geometric one when
the shading normal would send it into the surface), the refracted direction by Snell's law, their
weights and which of them are worth casting. The next batches are built from these rows in the
lanes' own packets by ``engine.packet.compact`` (sources: mirror reflections and total internal
reflections for the reflection batch, refractions for the refraction batch).

Operation order and precision follow the numpy shading it replaced (bit-identical images).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from engine.core.offset import MIN_MAGNITUDE, OFFSET_SCALE
from engine.packet.compact import new_array
from engine.core.lanes8 import rows_of_three
from engine.render.spawn8 import spawn8
from engine.render.surface import dot3

#: Rays carrying less than this weight (in every channel) are not cast.
MIN_WEIGHT = np.float32(1e-3)


class Children(NamedTuple):
    """Per-lane child rays of a batch of R rays.

    mirror: bool[R] cast the mirror reflection (weight reflect_weight); total_internal: bool[R]
    the refraction is totally reflected (cast along reflect_dir with weight transmit_weight);
    refract: bool[R] cast the refraction from ``enter`` along refract_dir (weight
    transmit_weight). reflect_dir, refract_dir, reflect_weight, transmit_weight, enter:
    f32[R,3]. Reflections leave from the Surface's ``leave``.
    """

    mirror: np.ndarray
    total_internal: np.ndarray
    refract: np.ndarray
    reflect_dir: np.ndarray
    refract_dir: np.ndarray
    reflect_weight: np.ndarray
    transmit_weight: np.ndarray
    enter: np.ndarray


#: Per-lane shape tail and dtype of each Children field.
CHILDREN_FIELDS = {"mirror": ((), np.bool_), "total_internal": ((), np.bool_), "refract": ((), np.bool_),
                   "reflect_dir": ((3,), np.float32), "refract_dir": ((3,), np.float32),
                   "reflect_weight": ((3,), np.float32), "transmit_weight": ((3,), np.float32),
                   "enter": ((3,), np.float32)}


def new_children(r: int, allocate=new_array) -> Children:
    """Per-lane child arrays for a batch of ``r`` rays (flags set by the kernel), from
    ``allocate(name, rows, tail, dtype)``."""
    return Children(*(allocate(name, r, tail, dtype) for name, (tail, dtype) in CHILDREN_FIELDS.items()))


@njit(cache=True, inline="always")
def spawn_lane(i, weight, point, magnitude, view, normal, facing, entering, material, reflectance, transmission,
               ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight,
               transmit_weight, enter):
    """The children row ``i`` of a hit lane (flags already False; see ``gather_and_spawn``).
    Shared by the CPU kernel and the device twin in ``engine.gpu.frame``."""
    one = np.float32(1.0)
    two = np.float32(2.0)
    zero = np.float32(0.0)
    d, ns, ng = view[i], normal[i], facing[i]
    m = material[i]
    # Mirror direction about the shading normal; about the geometric one when that
    # would send the ray into the surface.
    cos_i = -dot3(d, ns)
    for a in range(3):
        reflect_dir[i, a] = d[a] + two * cos_i * ns[a]
    if dot3(reflect_dir[i], ng) <= zero:
        cos_g = -dot3(d, ng)
        for a in range(3):
            reflect_dir[i, a] = d[a] + two * cos_g * ng[a]
    strongest = zero
    for c in range(3):
        reflect_weight[i, c] = weight[i, c] * reflectance[m, c]
        strongest = max(strongest, reflect_weight[i, c])
    mirror[i] = reflect and strongest > MIN_WEIGHT

    trans = transmission[m]
    heaviest = max(weight[i, 0], weight[i, 1], weight[i, 2])
    if not (trans > zero and heaviest * trans > MIN_WEIGHT):
        return
    for c in range(3):
        transmit_weight[i, c] = weight[i, c] * trans
    eta = one / ior[m] if entering[i] else ior[m]
    root = one - eta * eta * (one - cos_i * cos_i)
    if root < zero:
        total_internal[i] = True
        return
    refract[i] = True
    bend = eta * cos_i - np.float32(math.sqrt(max(root, zero)))
    for a in range(3):
        refract_dir[i, a] = eta * d[a] + bend * ns[a]
    if dot3(refract_dir[i], ng) >= zero:  # grazing smooth-normal case: straight through
        for a in range(3):
            refract_dir[i, a] = d[a]
    step = OFFSET_SCALE * max(magnitude[i], MIN_MAGNITUDE)
    for a in range(3):
        enter[i, a] = point[i, a] + step * -ng[a]


@njit(cache=True, parallel=True)
def gather_and_spawn(offsets, pixel, weight, hit, point, magnitude, view, normal, facing, entering, material,
                     color, reflectance, transmission, ior, image, spawn, reflect,
                     mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight,
                     transmit_weight, enter):
    """Add weight x color of every hit lane to ``image`` (f32[W*H,3]); with ``spawn``, fill the
    children rows (mirror .. enter, see ``Children``); ``reflect`` False: no mirror reflections
    (total internal reflection still continues a refraction path).

    Batch: packets offsets i32[K+1], pixel i32[R], weight f32[R,3]; its Surface rows (hit ..
    color, see ``engine.render.surface.Surface``); materials reflectance f32[M,3], transmission,
    ior f32[M].
    """
    # The children: eight lanes a step (``spawn8``: the same bits) where the rows allow it, over
    # the whole batch regardless of packets (2x2 packets have four lanes); else lane by lane.
    vector = spawn and reflectance.shape[0] > 0 and rows_of_three(weight) and rows_of_three(point) \
        and rows_of_three(view) and rows_of_three(normal) and rows_of_three(facing) \
        and rows_of_three(reflect_dir) and rows_of_three(refract_dir) and rows_of_three(reflect_weight) \
        and rows_of_three(transmit_weight) and rows_of_three(enter)
    n_lanes = hit.shape[0]
    blocks = n_lanes // 8 if vector else 0
    for b in prange(blocks):
        spawn8(hit, weight, point, magnitude, view, normal, facing, entering, material, reflectance, transmission,
               ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight,
               transmit_weight, enter, 8 * b)
    # Per packet (a pixel belongs to one packet's lanes): the lanes no block took, and the light
    # into the image in lane order.
    for k in prange(offsets.shape[0] - 1):
        lo, hi = offsets[k], offsets[k + 1]
        for j in range(max(lo, 8 * blocks), hi):
            mirror[j] = False
            total_internal[j] = False
            refract[j] = False
            if spawn and hit[j]:
                spawn_lane(j, weight, point, magnitude, view, normal, facing, entering, material, reflectance,
                           transmission, ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir,
                           reflect_weight, transmit_weight, enter)
        for j in range(lo, hi):
            if hit[j]:
                for c in range(3):
                    image[pixel[j], c] += weight[j, c] * color[j, c]
