"""The apex frusta's passes over a packet's rays, eight rays at a time (LLVM vector IR through
``engine.core.lanes8``), for ``engine.packet.frustum_builders``.

A pinhole or point-light frustum (``apex_frustum``) looks at each live ray twice: once to grow
the extent of the vectors g from the apex (``grow_extent``) and to check the rays meet the apex,
once to bound the slopes of g along the dominant axis. The scalar builders gather g into a
float64 scratch between the passes; here each pass recomputes g from the rays, eight at a time:

- ``gather8(mode, org, dirs, tmin, tmax, r, ax, ay, az)`` for rays r .. r+7, apex (ax, ay, az):
  (live mask, mask of live rays that miss the apex, extent lo x, y, z, hi x, y, z, sum x, y, z,
  and for POINTLIGHT the largest squared end-point spread, shortest and longest squared g, and
  largest origin coordinate). mode PINHOLE: g = the direction, the rays must leave the apex;
  POINTLIGHT: g = the segment start minus the light, the end points' spread measured.
- ``slopes8(mode, org, dirs, tmin, tmax, r, ax, ay, az, axis, sign)``: (lo u, hi u, lo v, hi v)
  of g's slopes u/w, v/w of the live rays along the dominant axis.

Each value is what the scalar code computes for that ray (the same float64 operations on the
same float32 inputs); minima and maxima over lanes are exact whatever the order. Sums are added
lane by lane within the eight and then block by block, where the scalar pass adds ray after ray,
so a sum may differ in its last bits: the sums only choose between axes along which every vector
has one strict sign (``dominant_axis``), and any such axis gives a correct frustum.
Why: building frusta was 16 ms of a kitchen-paper frame on two threads (2.8 M rays), most of
it the scalar gathering pass.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import I32, Lanes

#: The builders these passes serve (engine.packet.frustum_builders numbers them the same).
PINHOLE, POINTLIGHT = 0, 1
_INF = float("inf")


def _typing(org, dirs, tmin, tmax, scalars):
    for value, what in ((org, "org"), (dirs, "dirs")):
        if not (isinstance(value, types.Array) and value.dtype == types.float32 and value.ndim == 2):
            raise TypingError(f"{what} must be an f32[R,3] array, got {value}")
    for value, what in ((tmin, "tmin"), (tmax, "tmax")):
        if not (isinstance(value, types.Array) and value.dtype == types.float32 and value.ndim == 1):
            raise TypingError(f"{what} must be an f32[R] array, got {value}")
    for value in scalars:
        if not isinstance(value, (types.Integer, types.Float)):
            raise TypingError(f"expected a number, got {value}")


def _rays(lanes, signature, args):
    """(mode, org, dirs, tmin, tmax rows, apex splats) from the shared leading arguments."""
    t = signature.args
    mode = lanes.context.cast(lanes.builder, args[0], t[0], types.int64)
    org = lanes.rows3(lanes.array(t[1], args[1]), lanes.index(t[5], args[5]))
    start = lanes.index(t[5], args[5])
    dirs = lanes.rows3(lanes.array(t[2], args[2]), start)
    t_lo = lanes.row(lanes.array(t[3], args[3]), start)
    t_hi = lanes.row(lanes.array(t[4], args[4]), start)
    apex = [lanes.scalar_arg(args[k], t[k], types.float64) for k in (6, 7, 8)]
    return mode, org, dirs, t_lo, t_hi, apex


def _g(lanes, mode, org, dirs, t_lo, apex):
    """The vectors g (float64): the direction (PINHOLE) or segment start - light (POINTLIGHT),
    as ``pinhole_frustum`` / ``pointlight_frustum`` compute them."""
    d64 = [lanes.to_f64(d) for d in dirs]
    start = [lanes.to_f64(org[a]) + lanes.to_f64(t_lo) * d64[a] - apex[a] for a in range(3)]
    pointlight = lanes.builder.icmp_signed("==", mode, ir.Constant(mode.type, POINTLIGHT))
    return [lanes.where(lanes.splat(pointlight), start[a], d64[a]) for a in range(3)]


@intrinsic
def gather8(typingctx, mode, org, dirs, tmin, tmax, r, ax, ay, az):
    """Rays r .. r+7: (live bits, foreign bits, lo x, y, z, hi x, y, z, sum x, y, z, spread2,
    shortest2, reach2, scale) -- see the module doc; empty lanes give +-inf extents, 0 sums."""
    _typing(org, dirs, tmin, tmax, (mode, r, ax, ay, az))
    sig = types.Tuple((types.int64, types.int64) + (types.float64,) * 13)(mode, org, dirs, tmin, tmax, r, ax, ay, az)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        mode_, org_, dirs_, t_lo, t_hi, apex = _rays(lanes, signature, args)
        live = t_lo <= t_hi
        g = _g(lanes, mode_, org_, dirs_, t_lo, apex)
        # PINHOLE: every live ray leaves the apex (``!=`` as Python compares: NaN differs).
        foreign = live & (lanes.to_f64(org_[0]).ne(apex[0]) | lanes.to_f64(org_[1]).ne(apex[1])
                          | lanes.to_f64(org_[2]).ne(apex[2]))
        lo = [lanes.reduce_min(lanes.where(live, g[a], _INF)) for a in range(3)]
        hi = [lanes.reduce_max(lanes.where(live, g[a], -_INF)) for a in range(3)]
        total = [lanes.reduce_sum(lanes.where(live, g[a], 0.0)) for a in range(3)]
        # POINTLIGHT: the end points' spread around the light, g's squared lengths, the origins'
        # largest coordinate.
        d64 = [lanes.to_f64(d) for d in dirs_]
        end = [lanes.to_f64(org_[a]) + lanes.to_f64(t_hi) * d64[a] - apex[a] for a in range(3)]
        spread2 = lanes.reduce_max(lanes.where(live, end[0] * end[0] + end[1] * end[1] + end[2] * end[2], 0.0))
        length2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
        shortest2 = lanes.reduce_min(lanes.where(live, length2, _INF))
        reach2 = lanes.reduce_max(lanes.where(live, length2, 0.0))
        magnitude = lanes.max(lanes.fabs(org_[0]), lanes.max(lanes.fabs(org_[1]), lanes.fabs(org_[2])))
        scale = lanes.reduce_max(lanes.where(live, lanes.to_f64(magnitude), 0.0))
        values = [lanes.bitmask(live), lanes.bitmask(foreign)] + lo + hi + total + [spread2, shortest2, reach2, scale]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


@intrinsic
def slopes8(typingctx, mode, org, dirs, tmin, tmax, r, ax, ay, az, axis, sign):
    """Rays r .. r+7: (lo u, hi u, lo v, hi v) of the live rays' slopes g[u]/g[w], g[v]/g[w]
    along axis w (u, v the next two axes), each slope g[.] * (sign / g[w]) as ``apex_frustum``
    takes it; +-inf without a live ray."""
    _typing(org, dirs, tmin, tmax, (mode, r, ax, ay, az, axis, sign))
    sig = types.UniTuple(types.float64, 4)(mode, org, dirs, tmin, tmax, r, ax, ay, az, axis, sign)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        mode_, org_, dirs_, t_lo, t_hi, apex = _rays(lanes, signature, args)
        live = t_lo <= t_hi
        g = _g(lanes, mode_, org_, dirs_, t_lo, apex)
        w = lanes.splat(context.cast(builder, args[9], signature.args[9], types.int32), I32)
        sign_ = lanes.scalar_arg(args[10], signature.args[10], types.float64)

        def component(offset):  # g along axis (w + offset) % 3
            k = w + offset
            k = lanes.where(k >= 3, k - 3, k)
            return lanes.where(k.eq(0), g[0], lanes.where(k.eq(1), g[1], g[2]))

        inv_w = sign_ / component(0)
        su, sv = component(1) * inv_w, component(2) * inv_w
        values = [lanes.reduce_min(lanes.where(live, su, _INF)), lanes.reduce_max(lanes.where(live, su, -_INF)),
                  lanes.reduce_min(lanes.where(live, sv, _INF)), lanes.reduce_max(lanes.where(live, sv, -_INF))]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen
