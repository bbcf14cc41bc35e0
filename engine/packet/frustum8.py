"""The apex frusta's passes over a packet's rays, eight rays at a time (LLVM vector IR through
``engine.core.lanes8``), for ``engine.packet.frustum_builders``.

A pinhole or point-light frustum (``apex_frustum``) looks at each live ray twice: once to grow
the extent of the vectors g from the apex (``grow_extent``) and to check the rays meet the apex,
once to bound the slopes of g along the dominant axis. The scalar builders gather g into a
float64 scratch between the passes; here each pass recomputes g from the rays, eight at a time:

- ``gather_blocks8(mode, org, dirs, tmin, tmax, r, n_blocks, ax, ay, az)`` for rays r .. r +
  8 n_blocks - 1, apex (ax, ay, az): (live rays, bits of lanes where a live ray misses the apex,
  extent lo x, y, z, hi x, y, z, sum x, y, z, and for POINTLIGHT the largest squared end-point
  spread, shortest and longest squared g, and largest origin coordinate). mode PINHOLE: g = the
  direction, the rays must leave the apex; POINTLIGHT: g = the segment start minus the light,
  the end points' spread measured.
- ``slopes_blocks8(mode, org, dirs, tmin, tmax, r, n_blocks, ax, ay, az, axis, sign)``: (lo u,
  hi u, lo v, hi v) of g's slopes u/w, v/w of the live rays along the dominant axis.

Each loops over the packet's blocks of eight itself (``Lanes.accumulate``), keeping its minima,
maxima and sums as vectors and reducing them to scalars once, after the last block: a horizontal
reduction is several shuffles, and reducing fifteen values per block of eight rays had cost
more than computing them (point-light frusta of the kitchen's camera shadow rays, 1 M rays, two
threads: 4.2 ms a batch against 2.0 ms for a pass that only reads the rays).

Each value is what the scalar code computes for that ray (the same float64 operations on the
same float32 inputs); minima and maxima over lanes are exact whatever the order. Sums are added
lane by lane across the blocks and then across the lanes, where the scalar pass adds ray after
ray, so a sum may differ in its last bits: the sums only choose between axes along which every
vector has one strict sign (``dominant_axis``), and any such axis gives a correct frustum.
Why: building frusta was 16 ms of a kitchen-paper frame on two threads (2.8 M rays), most of
it the scalar gathering pass.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import F64, I1, I32, I64, Lanes

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


class _Packet:
    """A packet's arrays (org, dirs, tmin, tmax), first ray r and block count n_blocks, taken
    from six consecutive intrinsic arguments starting at ``at``."""

    def __init__(self, lanes, signature, args, at):
        t = signature.args
        self.lanes = lanes
        self.org, self.dirs, self.tmin, self.tmax = (lanes.array(t[k], args[k]) for k in range(at, at + 4))
        self.first = lanes.index(t[at + 4], args[at + 4])
        self.n_blocks = lanes.index(t[at + 5], args[at + 5])

    def block(self, start):
        """(org x, y, z, dirs x, y, z, tmin, tmax) of rays start .. start+7 as vectors."""
        lanes = self.lanes
        return (lanes.rows3(self.org, start), lanes.rows3(self.dirs, start), lanes.row(self.tmin, start),
                lanes.row(self.tmax, start))


def _apex(lanes, signature, args):
    """(mode as i64, apex splats (f64)) of an apex intrinsic's arguments 0 and 7-9."""
    t = signature.args
    mode = lanes.context.cast(lanes.builder, args[0], t[0], types.int64)
    return mode, [lanes.scalar_arg(args[k], t[k], types.float64) for k in (7, 8, 9)]


def _along(lanes, w, offset, g):
    """Per lane the component of g (three vectors) along axis (w + offset) % 3, w an i32 splat."""
    k = w + offset
    k = lanes.where(k >= 3, k - 3, k)
    return lanes.where(k.eq(0), g[0], lanes.where(k.eq(1), g[1], g[2]))


def _g(lanes, mode, org, dirs, t_lo, apex):
    """The vectors g (float64): the direction (PINHOLE) or segment start - light (POINTLIGHT),
    as ``pinhole_frustum`` / ``pointlight_frustum`` compute them."""
    d64 = [lanes.to_f64(d) for d in dirs]
    start = [lanes.to_f64(org[a]) + lanes.to_f64(t_lo) * d64[a] - apex[a] for a in range(3)]
    pointlight = lanes.builder.icmp_signed("==", mode, ir.Constant(mode.type, POINTLIGHT))
    return [lanes.where(lanes.splat(pointlight), start[a], d64[a]) for a in range(3)]


@intrinsic
def gather_blocks8(typingctx, mode, org, dirs, tmin, tmax, r, n_blocks, ax, ay, az):
    """Rays r .. r + 8 n_blocks - 1, eight at a time: (live rays, foreign bits (non-zero when a
    live ray misses the apex), lo x, y, z, hi x, y, z, sum x, y, z, spread2, shortest2, reach2,
    scale) -- see the module doc; no live ray gives +-inf extents and 0 sums."""
    _typing(org, dirs, tmin, tmax, (mode, r, n_blocks, ax, ay, az))
    sig = types.Tuple((types.int64, types.int64) + (types.float64,) * 13)(mode, org, dirs, tmin, tmax, r, n_blocks,
                                                                           ax, ay, az)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        packet = _Packet(lanes, signature, args, 1)
        mode, apex = _apex(lanes, signature, args)

        def step(start, values):
            count, foreign, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, sum_x, sum_y, sum_z, spread2, shortest2, reach2, \
                scale = values
            org_, dirs_, t_lo, t_hi = packet.block(start)
            live = t_lo <= t_hi
            g = _g(lanes, mode, org_, dirs_, t_lo, apex)
            # PINHOLE: every live ray leaves the apex (``!=`` as Python compares: NaN differs).
            away = live & (lanes.to_f64(org_[0]).ne(apex[0]) | lanes.to_f64(org_[1]).ne(apex[1])
                           | lanes.to_f64(org_[2]).ne(apex[2]))
            # POINTLIGHT: the end points' spread around the light, g's squared lengths, the
            # origins' largest coordinate.
            d64 = [lanes.to_f64(d) for d in dirs_]
            end = [lanes.to_f64(org_[a]) + lanes.to_f64(t_hi) * d64[a] - apex[a] for a in range(3)]
            length2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
            magnitude = lanes.max(lanes.fabs(org_[0]), lanes.max(lanes.fabs(org_[1]), lanes.fabs(org_[2])))
            return [count + lanes.where(live, lanes.splat(1, I64), 0), foreign | away,
                    lanes.min(lo_x, lanes.where(live, g[0], _INF)), lanes.min(lo_y, lanes.where(live, g[1], _INF)),
                    lanes.min(lo_z, lanes.where(live, g[2], _INF)),
                    lanes.max(hi_x, lanes.where(live, g[0], -_INF)), lanes.max(hi_y, lanes.where(live, g[1], -_INF)),
                    lanes.max(hi_z, lanes.where(live, g[2], -_INF)),
                    sum_x + lanes.where(live, g[0], 0.0), sum_y + lanes.where(live, g[1], 0.0),
                    sum_z + lanes.where(live, g[2], 0.0),
                    lanes.max(spread2, lanes.where(live, end[0] * end[0] + end[1] * end[1] + end[2] * end[2], 0.0)),
                    lanes.min(shortest2, lanes.where(live, length2, _INF)),
                    lanes.max(reach2, lanes.where(live, length2, 0.0)),
                    lanes.max(scale, lanes.where(live, lanes.to_f64(magnitude), 0.0))]

        initial = [lanes.splat(0, I64), lanes.splat(False, I1)] + [
            lanes.splat(value, F64) for value in (_INF, _INF, _INF, -_INF, -_INF, -_INF, 0.0, 0.0, 0.0, 0.0, _INF, 0.0,
                                                  0.0)]
        final = lanes.accumulate(packet.first, packet.n_blocks, initial, step)
        count, foreign = final[0], final[1]
        reduce = [lanes.reduce_min] * 3 + [lanes.reduce_max] * 3 + [lanes.reduce_sum] * 3 + \
                 [lanes.reduce_max, lanes.reduce_min, lanes.reduce_max, lanes.reduce_max]
        values = [lanes.reduce_sum(count), lanes.bitmask(foreign)] + [r(v) for r, v in zip(reduce, final[2:])]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


@intrinsic
def slopes_blocks8(typingctx, mode, org, dirs, tmin, tmax, r, n_blocks, ax, ay, az, axis, sign):
    """Rays r .. r + 8 n_blocks - 1, eight at a time: (lo u, hi u, lo v, hi v) of the live rays'
    slopes g[u]/g[w], g[v]/g[w] along axis w (u, v the next two axes), each slope
    g[.] * (sign / g[w]) as ``apex_frustum`` takes it; +-inf without a live ray."""
    _typing(org, dirs, tmin, tmax, (mode, r, n_blocks, ax, ay, az, axis, sign))
    sig = types.UniTuple(types.float64, 4)(mode, org, dirs, tmin, tmax, r, n_blocks, ax, ay, az, axis, sign)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        packet = _Packet(lanes, signature, args, 1)
        mode, apex = _apex(lanes, signature, args)
        w = lanes.splat(context.cast(builder, args[10], signature.args[10], types.int32), I32)
        sign_ = lanes.scalar_arg(args[11], signature.args[11], types.float64)

        def step(start, values):
            lo_u, hi_u, lo_v, hi_v = values
            org_, dirs_, t_lo, t_hi = packet.block(start)
            live = t_lo <= t_hi
            g = _g(lanes, mode, org_, dirs_, t_lo, apex)
            inv_w = sign_ / _along(lanes, w, 0, g)
            su, sv = _along(lanes, w, 1, g) * inv_w, _along(lanes, w, 2, g) * inv_w
            return [lanes.min(lo_u, lanes.where(live, su, _INF)), lanes.max(hi_u, lanes.where(live, su, -_INF)),
                    lanes.min(lo_v, lanes.where(live, sv, _INF)), lanes.max(hi_v, lanes.where(live, sv, -_INF))]

        initial = [lanes.splat(value, F64) for value in (_INF, -_INF, _INF, -_INF)]
        lo_u, hi_u, lo_v, hi_v = lanes.accumulate(packet.first, packet.n_blocks, initial, step)
        values = [lanes.reduce_min(lo_u), lanes.reduce_max(hi_u), lanes.reduce_min(lo_v), lanes.reduce_max(hi_v)]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


def _starts(lanes, org, dirs, t_lo):
    """(directions, segment starts org + tmin dir), float64, as ``general_frustum`` gathers them."""
    d64 = [lanes.to_f64(d) for d in dirs]
    return d64, [lanes.to_f64(org[a]) + lanes.to_f64(t_lo) * d64[a] for a in range(3)]


@intrinsic
def slab_gather_blocks8(typingctx, org, dirs, tmin, tmax, r, n_blocks):
    """Rays r .. r + 8 n_blocks - 1, eight at a time, for a slab frustum: (live rays, the extent
    of their directions g as lo x, y, z, hi x, y, z, sum x, y, z, the bounds of their segment
    starts p as lo x, y, z, hi x, y, z, and the largest coordinate magnitude of a start); no
    live ray gives +-inf bounds and 0 sums and magnitude."""
    _typing(org, dirs, tmin, tmax, (r, n_blocks))
    sig = types.Tuple((types.int64,) + (types.float64,) * 16)(org, dirs, tmin, tmax, r, n_blocks)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        packet = _Packet(lanes, signature, args, 0)

        def step(start, values):
            count = values[0]
            org_, dirs_, t_lo, t_hi = packet.block(start)
            live = t_lo <= t_hi
            g, p = _starts(lanes, org_, dirs_, t_lo)
            lo = [lanes.min(values[1 + a], lanes.where(live, g[a], _INF)) for a in range(3)]
            hi = [lanes.max(values[4 + a], lanes.where(live, g[a], -_INF)) for a in range(3)]
            total = [values[7 + a] + lanes.where(live, g[a], 0.0) for a in range(3)]
            p_lo = [lanes.min(values[10 + a], lanes.where(live, p[a], _INF)) for a in range(3)]
            p_hi = [lanes.max(values[13 + a], lanes.where(live, p[a], -_INF)) for a in range(3)]
            magnitude = lanes.max(lanes.fabs(p[0]), lanes.max(lanes.fabs(p[1]), lanes.fabs(p[2])))
            scale = lanes.max(values[16], lanes.where(live, magnitude, 0.0))
            return [count + lanes.where(live, lanes.splat(1, I64), 0)] + lo + hi + total + p_lo + p_hi + [scale]

        bounds = (_INF,) * 3 + (-_INF,) * 3 + (0.0,) * 3 + (_INF,) * 3 + (-_INF,) * 3 + (0.0,)
        initial = [lanes.splat(0, I64)] + [lanes.splat(value, F64) for value in bounds]
        final = lanes.accumulate(packet.first, packet.n_blocks, initial, step)
        reduce = ([lanes.reduce_min] * 3 + [lanes.reduce_max] * 3 + [lanes.reduce_sum] * 3
                  + [lanes.reduce_min] * 3 + [lanes.reduce_max] * 4)
        values = [lanes.reduce_sum(final[0])] + [r(v) for r, v in zip(reduce, final[1:])]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


@intrinsic
def slab_rects_blocks8(typingctx, org, dirs, tmin, tmax, r, n_blocks, axis, sign, wn, wf):
    """Rays r .. r + 8 n_blocks - 1, eight at a time: the rectangles where the live rays cross the
    near plane w' = wn and the far plane w' = wf across ``axis`` (w' = sign * coordinate), as
    (u0, u1, v0, v1 near, u0, u1, v0, v1 far), and the largest squared ray length between the
    planes, computed as ``slab_frustum``'s loop computes them; +-inf and 0 without a live ray."""
    _typing(org, dirs, tmin, tmax, (r, n_blocks, axis, sign, wn, wf))
    sig = types.UniTuple(types.float64, 9)(org, dirs, tmin, tmax, r, n_blocks, axis, sign, wn, wf)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        packet = _Packet(lanes, signature, args, 0)
        t = signature.args
        w = lanes.splat(context.cast(builder, args[6], t[6], types.int32), I32)
        sign_, wn_, wf_ = (lanes.scalar_arg(args[k], t[k], types.float64) for k in (7, 8, 9))

        def step(start, values):
            org_, dirs_, t_lo, t_hi = packet.block(start)
            live = t_lo <= t_hi
            g, p = _starts(lanes, org_, dirs_, t_lo)
            w0 = sign_ * _along(lanes, w, 0, p)
            inv_w = sign_ / _along(lanes, w, 0, g)
            tn = (wn_ - w0) * inv_w
            tf = (wf_ - w0) * inv_w
            pu, pv, gu, gv = _along(lanes, w, 1, p), _along(lanes, w, 2, p), _along(lanes, w, 1, g), _along(lanes, w, 2, g)
            crossings = (pu + tn * gu, pv + tn * gv, pu + tf * gu, pv + tf * gv)  # un, vn, uf, vf
            out = []
            for k, crossing in enumerate(crossings):
                out.append(lanes.min(values[2 * k], lanes.where(live, crossing, _INF)))
                out.append(lanes.max(values[2 * k + 1], lanes.where(live, crossing, -_INF)))
            reach2 = (tf - tn) * (tf - tn) * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
            return out + [lanes.max(values[8], lanes.where(live, reach2, 0.0))]

        initial = [lanes.splat(value, F64) for value in (_INF, -_INF) * 4 + (0.0,)]
        final = lanes.accumulate(packet.first, packet.n_blocks, initial, step)
        values = [(lanes.reduce_min if k % 2 == 0 else lanes.reduce_max)(v) for k, v in enumerate(final[:8])]
        values.append(lanes.reduce_max(final[8]))
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen
