"""``light_directions`` eight lanes at a time (LLVM vector IR through ``engine.core.lanes8``).

``light_directions8(hit, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax,
inv_to_light, start)`` does for lanes start .. start+7 what ``engine.render.direct_light``'s
per-lane loop does -- the direction to the light, its length, the cosine, whether the light is in
front of both normals, the shadow ray's end and inverse direction -- with the same float32
operations in the same order, so every array holds the same bits (``dist`` and ``ndotl`` are
written on hit lanes only, as the scalar loop leaves the others). Returns the mask of lit lanes.

Why: per lane the pass is a square root and six divisions (the normalisation and the inverse
direction), which scalar code issues one at a time: 8 ms of the kitchen-paper frame on two
threads. The arrays are f32[R,3] with 12-byte rows (the caller checks), f32[R] and bool[R].
"""
from __future__ import annotations

import numpy as np
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import Lanes
from engine.core.triangle import HUGE_INV

_TINY = float(np.float32(1e-30))
_SHADOW_TMAX_SCALE = float(np.float32(1.0 - 1e-4))
#: 1 / HUGE_INV in float32, what ``inverse_component`` puts in place of a zero component.
_INVERSE_TINY = float(np.float32(1.0) / np.float32(HUGE_INV))


@intrinsic
def light_directions8(typingctx, hit, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax,
                      inv_to_light, start):
    """Lanes start .. start+7 of ``light_directions``; returns the lit lanes' bit mask (int64)."""
    rows3 = (leave, ns, ng, to_light, inv_to_light)
    rows1 = (dist, ndotl, shadow_tmax)
    if not all(isinstance(a, types.Array) and a.dtype == types.float32 and a.ndim == 2 for a in rows3):
        raise TypingError("leave, ns, ng, to_light, inv_to_light must be f32[R,3] arrays")
    if not all(isinstance(a, types.Array) and a.dtype == types.float32 and a.ndim == 1 for a in rows1 + (light,)):
        raise TypingError("dist, ndotl, shadow_tmax and light must be f32 vectors")
    if not all(isinstance(a, types.Array) and a.dtype == types.boolean and a.ndim == 1 for a in (hit, lit)):
        raise TypingError("hit and lit must be bool[R] arrays")
    if not isinstance(start, types.Integer):
        raise TypingError(f"start must be an integer, got {start}")
    sig = types.int64(hit, leave, ns, ng, light, to_light, dist, ndotl, lit, shadow_tmax, inv_to_light, start)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        (hit_a, leave_a, ns_a, ng_a, light_a, to_light_a, dist_a, ndotl_a, lit_a, tmax_a,
         inv_a) = (lanes.array(t, v) for t, v in zip(signature.args[:11], args[:11]))
        start_ = lanes.index(signature.args[11], args[11])
        hits = lanes.row(hit_a, start_, boolean=True)
        light_xyz = [lanes.splat(builder.load(builder.gep(light_a.data, [context.get_constant(types.intp, a)])))
                     for a in range(3)]
        lx, ly, lz = lanes.rows3(leave_a, start_)
        x, y, z = light_xyz[0] - lx, light_xyz[1] - ly, light_xyz[2] - lz
        length = lanes.sqrt(x * x + y * y + z * z)
        scale = lanes.max(length, _TINY)
        x, y, z = x / scale, y / scale, z / scale
        nsx, nsy, nsz = lanes.rows3(ns_a, start_)
        ngx, ngy, ngz = lanes.rows3(ng_a, start_)
        cos_s = nsx * x + nsy * y + nsz * z
        lit_ = hits & (cos_s > 0.0) & (ngx * x + ngy * y + ngz * z > 0.0)
        # Lanes without a hit point along +z (a dead shadow ray the walk can still load).
        x, y, z = lanes.where(hits, x, 0.0), lanes.where(hits, y, 0.0), lanes.where(hits, z, 1.0)
        lanes.store_rows3(to_light_a, start_, (x, y, z))
        lanes.store_row(dist_a, start_, length, mask=hits)
        lanes.store_row(ndotl_a, start_, cos_s, mask=hits)
        lanes.store_row(lit_a, start_, lit_)
        lanes.store_row(tmax_a, start_, lanes.where(lit_, length * _SHADOW_TMAX_SCALE, float("-inf")))

        def inverse(d):  # engine.packet.compact.inverse_component
            return 1.0 / lanes.where(d.eq(0.0), lanes.copysign(lanes.splat(_INVERSE_TINY), d), d)

        lanes.store_rows3(inv_a, start_, (inverse(x), inverse(y), inverse(z)))
        return lanes.bitmask(lit_)

    return sig, codegen
