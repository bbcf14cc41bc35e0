"""Every triangle's shading data in one 128-byte row, for the eight-lane surface step.

``shade_surface``'s eight-lane step (``engine.render.surface8``) reads, for each hit lane, its
triangle's corners, geometric normal, corner normals, texture coordinates, material and offset
scale. Kept in eight arrays, that is eight row addresses computed per lane and as many cache
lines; in one record per triangle it is one row start per lane and two lines. Measured on a
kitchen-paper frame's surface passes (two threads, 41 paired alternating calls, session 33):
the eight-lane loop 0.70-0.83x the time with the record (camera batch 14.8 -> 11.8 ms,
reflection batch 6.1 -> 4.5 ms), every Surface row the same bits (the same float values are
loaded, only from elsewhere).

Layout of ``records`` f32[T, RECORD_WIDTH] (``RECORD_FIELDS``: name -> (first column, count)):

    v0, v1, v2   columns 0-8    the corners (x, y, z each)
    ng           columns 9-11   the unit geometric normal
    normals      columns 12-20  the corner normals, corner by corner (zero without them)
    uvs          columns 21-26  the corners' (s, t), corner by corner (zero without them)
    magnitude    column 27      the offset scale of the corners (``triangle_magnitudes``)
    material     column 28      the material index, as int32 bits
    (29-31 unused: rows of 32 floats start on 128-byte boundaries in an aligned array)

The arrays it is made from stay the scene's own: the lane-by-lane path (tails, strided views)
and the GPU read them. A renderer makes the records once per scene (``set_scene``: each
animation frame's moved triangles get new ones).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

RECORD_WIDTH = 32
RECORD_FIELDS = {"v0": (0, 3), "v1": (3, 3), "v2": (6, 3), "ng": (9, 3), "normals": (12, 9), "uvs": (21, 6),
                 "magnitude": (27, 1), "material": (28, 1)}
# The first columns, as constants the fill kernel compiles in (one layout: RECORD_FIELDS).
_V0, _V1, _V2, _NG, _NORMALS, _UVS, _MAGNITUDE, _MATERIAL = (
    RECORD_FIELDS[name][0] for name in ("v0", "v1", "v2", "ng", "normals", "uvs", "magnitude", "material"))
_UNUSED = _MATERIAL + 1


def surface_records(v0, v1, v2, ng, normals, uvs, material, magnitude) -> np.ndarray:
    """f32[T, RECORD_WIDTH] records (module doc) of T triangles: corners v0, v1, v2 and unit
    normals ng f32[T,3], corner normals f32[T,3,3] and uvs f32[T,3,2] (or first dimension 0:
    none), material i32[T], magnitude f32[T]."""
    t = v0.shape[0]
    for name, a, tail in (("v1", v1, (3,)), ("v2", v2, (3,)), ("ng", ng, (3,)), ("material", material, ()),
                          ("magnitude", magnitude, ())):
        if a.shape != (t,) + tail:
            raise ValueError(f"surface_records: {name} has shape {a.shape}, expected {(t,) + tail}")
    for name, a, tail in (("normals", normals, (3, 3)), ("uvs", uvs, (3, 2))):
        if a.shape[0] not in (0, t) or a.shape[1:] != tail:
            raise ValueError(f"surface_records: {name} has shape {a.shape}, expected (0 or {t}, {tail})")
    records = np.empty((t, RECORD_WIDTH), np.float32)
    fill_records(v0, v1, v2, ng, normals, uvs, np.ascontiguousarray(material, np.int32), magnitude, records,
                 records.view(np.int32))
    return records


@njit(cache=True, parallel=True)
def fill_records(v0, v1, v2, ng, normals, uvs, material, magnitude, records, record_bits):
    """Fill records f32[T, RECORD_WIDTH] (record_bits: its int32 view) from the triangle arrays."""
    has_normals = normals.shape[0] > 0
    has_uvs = uvs.shape[0] > 0
    for i in prange(records.shape[0]):
        for a in range(3):
            records[i, _V0 + a] = v0[i, a]
            records[i, _V1 + a] = v1[i, a]
            records[i, _V2 + a] = v2[i, a]
            records[i, _NG + a] = ng[i, a]
        for c in range(3):
            for a in range(3):
                records[i, _NORMALS + 3 * c + a] = normals[i, c, a] if has_normals else np.float32(0.0)
            for a in range(2):
                records[i, _UVS + 2 * c + a] = uvs[i, c, a] if has_uvs else np.float32(0.0)
        records[i, _MAGNITUDE] = magnitude[i]
        record_bits[i, _MATERIAL] = material[i]
        for a in range(_UNUSED, RECORD_WIDTH):
            records[i, a] = np.float32(0.0)
