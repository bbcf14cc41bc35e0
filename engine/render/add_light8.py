"""``add_light_in_place``'s per-lane step eight lanes at a time (LLVM vector IR, ``engine.core.lanes8``).

``add_light8(color, lit, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess,
texel, light_color, start)`` adds one light to lanes start .. start+7 as
``engine.render.direct_light.add_light_lane`` does to each lane that is lit and not occluded:
the diffuse term and the Phong highlight, ``max(-(r . view), 0) ** shininess`` with r the light
direction mirrored about the shading normal. The same float32 operations in the same order, so
the same bits; the power is the scalar step's own call (``llvm.pow.f32``), made lane by lane and
only where the scalar step makes it (not for a base of 0 with a positive exponent). Lanes that
add nothing keep their colour; a block where no lane adds anything is not touched.

Why: the scalar loop branches per lane and issues its products one by one: 5.2 ms of the
kitchen-paper frame on two threads. Kitchen primary batch, two threads, min of 41, three
alternating runs: 3.59 / 3.65 / 3.67 -> 3.03 / 2.90 / 2.77 ms. Arrays: color, ns, to_light, view, texel f32[R,3] with
12-byte rows; lit, occluded bool[R]; ndotl f32[R]; mat i32[R]; diffuse, specular f32[K,3] with
contiguous rows; shininess f32[K]; light_color f32[3] (the caller checks the rows).
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from engine.core.lanes8 import F32, I1, I32, I64, Lanes, V, check_arguments

_NAMES = ("color", "lit", "occluded", "ns", "to_light", "ndotl", "view", "mat", "diffuse", "specular", "shininess",
          "texel", "light_color", "start")


@intrinsic
def add_light8(typingctx, color, lit, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel,
               light_color, start):
    """Lanes start .. start+7 of ``add_light_in_place`` (see the module doc)."""
    args_ = (color, lit, occluded, ns, to_light, ndotl, view, mat, diffuse, specular, shininess, texel, light_color,
             start)
    check_arguments(_NAMES, args_, {"start": types.Integer})
    sig = types.void(*args_)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        a = {}
        for name, t, value in zip(_NAMES, signature.args, args):
            a[name] = lanes.index(t, value) if name == "start" else lanes.array(t, value)
        i = a["start"]
        adds = lanes.row(a["lit"], i, boolean=True) & ~lanes.row(a["occluded"], i, boolean=True)
        with builder.if_then(builder.icmp_unsigned("!=", lanes.bitmask(adds), ir.Constant(I64, 0))):
            cos_s = lanes.row(a["ndotl"], i)
            ns = lanes.rows3(a["ns"], i)
            to_light = lanes.rows3(a["to_light"], i)
            view = lanes.rows3(a["view"], i)
            r = [2.0 * cos_s * ns[k] - to_light[k] for k in range(3)]
            highlight = lanes.max(-(r[0] * view[0] + r[1] * view[1] + r[2] * view[2]), 0.0)
            k = lanes.where(adds, lanes.to_i64(lanes.row(a["mat"], i)), 0)  # a valid row on every lane
            exponent = lanes.gather(a["shininess"], k)
            spec = _powers(lanes, builder, adds & ~(highlight.eq(0.0) & (exponent > 0.0)), highlight, exponent)
            diffuse = lanes.gather_rows(a["diffuse"], k, 3)
            specular = lanes.gather_rows(a["specular"], k, 3)
            texel = lanes.rows3(a["texel"], i)
            color = lanes.rows3(a["color"], i)
            light = [lanes.splat(builder.load(builder.gep(a["light_color"].data, [ir.Constant(I64, c)])))
                     for c in range(3)]
            lanes.store_rows3(a["color"], i, [color[c] + light[c] * (diffuse[c] * texel[c] * cos_s
                                                                     + specular[c] * spec) for c in range(3)],
                              mask=adds)
        return context.get_dummy_value()

    return sig, codegen


def _powers(lanes: Lanes, builder, wanted: V, base: V, exponent: V) -> V:
    """base ** exponent on the lanes ``wanted`` sets, 0 on the others: one ``llvm.pow.f32`` call
    per wanted lane, the scalar step's own call, so the same bits."""
    pow_f32 = cgutils.get_or_insert_function(builder.module, ir.FunctionType(F32, [F32, F32]), "llvm.pow.f32")
    slot = cgutils.alloca_once_value(builder, lanes.splat(0.0).value)
    for j in range(lanes.width):
        lane = ir.Constant(I32, j)
        flag = builder.extract_element(wanted.value, lane)
        with builder.if_then(builder.icmp_unsigned("!=", flag, ir.Constant(I1, 0))):
            value = builder.call(pow_f32, [builder.extract_element(base.value, lane),
                                           builder.extract_element(exponent.value, lane)])
            builder.store(builder.insert_element(builder.load(slot), value, lane), slot)
    return V(lanes, builder.load(slot))
