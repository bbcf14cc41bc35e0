"""``spawn_lane`` eight lanes at a time (LLVM vector IR through ``engine.core.lanes8``).

``spawn8(hit, weight, point, magnitude, view, normal, facing, entering, material, reflectance,
transmission, ior, reflect, children..., start)`` fills the ``Children`` rows of lanes
start .. start+7 as ``engine.render.spawn.spawn_lane`` does for each hit lane -- the mirror
direction and weight, and for transmissive materials the refraction by Snell's law or the total
internal reflection -- with the same float32 operations in the same order, so the rows the
scalar code writes get the same bits where a child is cast, and the three flags of every lane
(False without a hit). A block of eight lanes none of which casts a child leaves that child's
rows alone; elsewhere rows of children not cast get whatever the steps give. Only the lanes'
pixels are left to the caller, which adds them in lane order.

Why: per hit lane the spawn is three dot products, a division and a square root (refraction)
and up to 18 stores, scalar: most of ``gather_and_spawn``'s 15 ms in the kitchen-paper frame.
The per-lane arrays are f32[R,3] with 12-byte rows (the caller checks), f32[R], i32[R], bool[R];
the material tables reflectance f32[M,3], transmission and ior f32[M] are gathered per lane.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import I64, Lanes
from engine.core.offset import MIN_MAGNITUDE, OFFSET_SCALE

_MIN_WEIGHT = float(np.float32(1e-3))


@intrinsic
def spawn8(typingctx, hit, weight, point, magnitude, view, normal, facing, entering, material, reflectance,
           transmission, ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight,
           transmit_weight, enter, start):
    """Children rows of lanes start .. start+7 (see the module doc)."""
    arrays = (hit, weight, point, magnitude, view, normal, facing, entering, material, reflectance, transmission,
              ior, mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight, transmit_weight, enter)
    if not all(isinstance(a, types.Array) for a in arrays):
        raise TypingError("spawn8 takes arrays (and a flag and a lane)")
    if not isinstance(start, types.Integer):
        raise TypingError(f"start must be an integer, got {start}")
    sig = types.void(hit, weight, point, magnitude, view, normal, facing, entering, material, reflectance,
                     transmission, ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir,
                     reflect_weight, transmit_weight, enter, start)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        a = {name: lanes.array(t, v) for name, t, v in zip(
            ("hit", "weight", "point", "magnitude", "view", "normal", "facing", "entering", "material", "reflectance",
             "transmission", "ior"), signature.args[:12], args[:12])}
        out = {name: lanes.array(t, v) for name, t, v in zip(
            ("mirror", "total_internal", "refract", "reflect_dir", "refract_dir", "reflect_weight",
             "transmit_weight", "enter"), signature.args[13:21], args[13:21])}
        reflect_ = lanes.splat(context.cast(builder, args[12], signature.args[12], types.boolean))
        i = lanes.index(signature.args[21], args[21])
        hits = lanes.row(a["hit"], i, boolean=True)
        entering_ = lanes.row(a["entering"], i, boolean=True)
        m = lanes.where(hits, lanes.to_i64(lanes.row(a["material"], i)), 0)  # a valid row to gather
        d = lanes.rows3(a["view"], i)
        ns = lanes.rows3(a["normal"], i)
        ng = lanes.rows3(a["facing"], i)
        wt = lanes.rows3(a["weight"], i)

        def dot(p, q):
            return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]

        # Mirror direction about the shading normal; about the geometric one when that would
        # send the ray into the surface.
        cos_i = -dot(d, ns)
        about_ns = [d[k] + 2.0 * cos_i * ns[k] for k in range(3)]
        cos_g = -dot(d, ng)
        about_ng = [d[k] + 2.0 * cos_g * ng[k] for k in range(3)]
        into = dot(about_ns, ng) <= 0.0
        reflect_dir = tuple(lanes.where(into, about_ng[k], about_ns[k]) for k in range(3))
        reflectance = [lanes.gather(a["reflectance"], [m, k]) for k in range(3)]
        reflect_weight = tuple(wt[k] * reflectance[k] for k in range(3))
        strongest = lanes.max(lanes.max(lanes.max(lanes.splat(0.0), reflect_weight[0]), reflect_weight[1]),
                              reflect_weight[2])
        mirror = hits & reflect_ & (strongest > _MIN_WEIGHT)

        trans = lanes.gather(a["transmission"], m)
        heaviest = lanes.max(lanes.max(wt[0], wt[1]), wt[2])
        transmits = hits & (trans > 0.0) & (heaviest * trans > _MIN_WEIGHT)
        transmit_weight = tuple(wt[k] * trans for k in range(3))
        index = lanes.gather(a["ior"], m)
        eta = lanes.where(entering_, 1.0 / index, index)
        root = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
        total_internal = transmits & (root < 0.0)
        refracts = transmits & ~(root < 0.0)
        bend = eta * cos_i - lanes.sqrt(lanes.max(root, 0.0))
        bent = [eta * d[k] + bend * ns[k] for k in range(3)]
        straight = dot(bent, ng) >= 0.0  # grazing smooth-normal case: straight through
        refract_dir = tuple(lanes.where(straight, d[k], bent[k]) for k in range(3))
        step = OFFSET_SCALE * lanes.max(lanes.row(a["magnitude"], i), float(MIN_MAGNITUDE))
        p = lanes.rows3(a["point"], i)
        enter = tuple(p[k] + step * -ng[k] for k in range(3))

        # A child's rows mean something only where its flag is set (``Children``): they are
        # stored whole where some lane of the eight casts that child (masked rows of three floats
        # are read, selected and written back), and not at all where none does, as in most blocks
        # of a frame (no glass, no mirror). Kitchen primary batch, two threads, min of 41, three
        # alternating runs: 4.21 / 3.79 / 3.44 -> 2.08 / 1.97 / 2.20 ms.
        builder = lanes.builder
        for flags, rows in ((mirror | total_internal, (("reflect_dir", reflect_dir),)),
                            (mirror, (("reflect_weight", reflect_weight),)),
                            (total_internal | refracts, (("transmit_weight", transmit_weight),)),
                            (refracts, (("refract_dir", refract_dir), ("enter", enter)))):
            with builder.if_then(builder.icmp_unsigned("!=", lanes.bitmask(flags), ir.Constant(I64, 0))):
                for name, value in rows:
                    lanes.store_rows3(out[name], i, value)
        lanes.store_row(out["mirror"], i, mirror)
        lanes.store_row(out["total_internal"], i, total_internal)
        lanes.store_row(out["refract"], i, refracts)
        return context.get_dummy_value()

    return sig, codegen
