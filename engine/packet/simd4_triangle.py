"""The watertight triangle test on the four lanes of a 2x2 SIMD ray at once, as LLVM vector IR.

``intersect4(rf, ri, lane0, mask, leaf_tris, n_tris, v0, v1, v2, any_hit) -> (tests, died)``
tests the lanes lane0 .. lane0+3 of the packet-local rows (rf: f32[RF_ROWS, L], ri:
i32[RI_ROWS, L], the ``engine.packet.kernels`` layout) that ``mask`` (4 bits) selects and that
are live (TLO <= THI) against the triangles leaf_tris[:n_tris] (i32; corners v0, v1, v2:
f32[T, 3]), in that order, and updates each lane's THI and BEST_T/U/V/PRIM rows exactly as the
scalar loop "for each lane: for each triangle: ``intersect_triangle``, then ``closer``" does.
With ``any_hit`` a lane dies (THI = -inf) at its first hit. Returns (ray-triangle tests done,
lanes that died), counted as the scalar loop counts them. A triangle that no live lane sees
inside its edges costs no division and no update (the common case: a branch, not a select).

``intersect4x2(rf, ri, lane0, lane1, mask, ...)`` runs the same test on two SIMD rays at once (8
lanes: AVX2's width), mask bits 4-7 selecting lane1's lanes; the leaf loops pair their SIMD rays
with it.

Why it is bit-identical to ``engine.core.triangle.intersect_triangle``: each vector element goes
through the same IEEE operations in the same order (f32 translate and shear, the three edge
functions as f64 products and difference rounded once to f32, f32 det, scaled t, 1/det), with
the same ordered compares. The IR has plain fmul/fsub/fadd/fdiv with no fast-math or
``contract`` flags, so LLVM may neither fuse them into FMAs nor reassociate. Each lane reads
its own permutation (kx, ky, kz): a triangle's nine coordinates are loaded once and each lane
picks its components with selects. Lanes are independent, so one triangle against four lanes
then the next is the same as the scalar lane-major loop.

Numba has no SLP vectoriser (see ``engine.packet.simd4``), hence the hand-written IR.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

_F32 = ir.FloatType()
_F64 = ir.DoubleType()
_I1 = ir.IntType(1)
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_V4F = ir.VectorType(_F32, 4)
_V4I = ir.VectorType(_I32, 4)

#: Rows of the packet-local blocks this reads and writes (``engine.packet.kernels`` checks them).
ROWS_F = {"TLO": 6, "THI": 7, "SX": 8, "SY": 9, "SZ": 10, "OKX": 11, "OKY": 12, "OKZ": 13,
          "BEST_T": 14, "BEST_U": 15, "BEST_V": 16}
ROWS_I = {"KX": 0, "KY": 1, "KZ": 2, "BEST_PRIM": 3}


class _Width:
    """The vector types of one test of ``n_rays`` SIMD rays (4 n_rays lanes)."""

    def __init__(self, n_rays):
        self.n_rays = n_rays
        self.lanes = lanes = 4 * n_rays
        self.f = ir.VectorType(_F32, lanes)
        self.d = ir.VectorType(_F64, lanes)
        self.i = ir.VectorType(_I32, lanes)
        self.b = ir.VectorType(_I1, lanes)
        self.bits = ir.IntType(lanes)

    def splat(self, builder, scalar, vtype):
        """A vtype vector with every lane = scalar."""
        one = builder.insert_element(ir.Constant(vtype, ir.Undefined), scalar, ir.Constant(_I32, 0))
        return builder.shuffle_vector(one, ir.Constant(vtype, ir.Undefined),
                                      ir.Constant(ir.VectorType(_I32, self.lanes), [0] * self.lanes))

    def const(self, vtype, value):
        return ir.Constant(vtype, [value] * self.lanes)

    def any(self, builder, mask):
        return builder.icmp_unsigned("!=", builder.bitcast(mask, self.bits), ir.Constant(self.bits, 0))

    def popcount(self, builder, mask):
        name = f"llvm.ctpop.i{self.lanes}"
        ctpop = cgutils.get_or_insert_function(builder.module, ir.FunctionType(self.bits, [self.bits]), name)
        return builder.zext(builder.call(ctpop, [builder.bitcast(mask, self.bits)]), _I64)

    def edge(self, builder, ax, by, ay, bx):
        """f32(f64(ax) * f64(by) - f64(ay) * f64(bx)): the f32 products are exact in f64, so the
        one rounding is the subtraction's, as in the scalar kernel."""
        ext = [builder.fpext(x, self.d) for x in (ax, by, ay, bx)]
        return builder.fptrunc(builder.fsub(builder.fmul(ext[0], ext[1]), builder.fmul(ext[2], ext[3])), self.f)

    def load(self, builder, pointers):
        """The lanes at ``pointers`` (one <4 x T>* per SIMD ray) as one vector."""
        halves = [builder.load(p, align=4) for p in pointers]
        if len(halves) == 1:
            return halves[0]
        return builder.shuffle_vector(halves[0], halves[1], ir.Constant(ir.VectorType(_I32, 8), list(range(8))))

    def store(self, builder, value, pointers):
        """Store ``value``'s lanes back, four to each pointer."""
        if len(pointers) == 1:
            builder.store(value, pointers[0], align=4)
            return
        for k, p in enumerate(pointers):
            half = builder.shuffle_vector(value, ir.Constant(value.type, ir.Undefined),
                                          ir.Constant(_V4I, list(range(4 * k, 4 * k + 4))))
            builder.store(half, p, align=4)


def _row_ptr(builder, data, row_elems, row, offset, vtype):
    """Pointer to the 4 lanes data[row * row_elems + offset ...] as a vtype*."""
    index = builder.add(builder.mul(ir.Constant(_I64, row), row_elems), offset)
    return builder.bitcast(builder.gep(data, [index]), vtype.as_pointer())


def _check(value, dtype, ndim, what, any_layout=False):
    if not (isinstance(value, types.Array) and value.dtype == dtype and value.ndim == ndim
            and (any_layout or value.layout == "C")):
        layout = "" if any_layout else "C-contiguous "
        raise TypingError(f"{what} must be a {layout}{dtype} array of {ndim} dimension(s), got {value}")


def _typing(rf, ri, lanes, mask, leaf_tris, n_tris, v0, v1, v2, any_hit):
    _check(rf, types.float32, 2, "rf")
    _check(ri, types.int32, 2, "ri")
    _check(leaf_tris, types.int32, 1, "leaf_tris", any_layout=True)
    for v in (v0, v1, v2):
        _check(v, types.float32, 2, "v0, v1, v2", any_layout=True)
    for x in (*lanes, mask, n_tris):
        if not isinstance(x, types.Integer):
            raise TypingError(f"expected an integer, got {x}")
    if not isinstance(any_hit, types.Boolean):
        raise TypingError(f"any_hit must be a boolean, got {any_hit}")
    return types.UniTuple(types.int64, 2)(rf, ri, *lanes, mask, leaf_tris, n_tris, v0, v1, v2, any_hit)


@intrinsic
def intersect4(typingctx, rf, ri, lane0, mask, leaf_tris, n_tris, v0, v1, v2, any_hit):
    """(tests, died): the leaf's triangles against the selected live lanes; see the module doc."""
    return _typing(rf, ri, (lane0,), mask, leaf_tris, n_tris, v0, v1, v2, any_hit), _intersect_codegen(_Width(1))


@intrinsic
def intersect4x2(typingctx, rf, ri, lane0, lane1, mask, leaf_tris, n_tris, v0, v1, v2, any_hit):
    """``intersect4`` of two SIMD rays at once (lanes lane0 .. lane0+3 and lane1 .. lane1+3,
    anywhere in the packet), as one 8-lane test: ``mask`` bits 0-3 select lane0's lanes, bits
    4-7 lane1's; (tests, died) are the sums of the two SIMD rays'. Each lane's result is the
    4-wide test's, bit for bit: lanes never mix."""
    return (_typing(rf, ri, (lane0, lane1), mask, leaf_tris, n_tris, v0, v1, v2, any_hit),
            _intersect_codegen(_Width(2)))


def _intersect_codegen(w: _Width):
    """Codegen of the leaf test of ``w.n_rays`` SIMD rays (arguments as ``intersect4x2``'s, with
    as many lane offsets as SIMD rays)."""

    def codegen(context, builder, signature, args):
        s = signature.args
        k = w.n_rays
        a_rf, a_ri = args[0], args[1]
        a_lanes = args[2:2 + k]
        a_mask, a_tris, a_n, a_v0, a_v1, a_v2, a_any = args[2 + k:]
        s_rf, s_ri = s[0], s[1]
        s_lanes = s[2:2 + k]
        s_mask, s_tris, s_n, s_v0, s_v1, s_v2, s_any = s[2 + k:]
        rf_arr = context.make_array(s_rf)(context, builder, a_rf)
        ri_arr = context.make_array(s_ri)(context, builder, a_ri)
        tris_arr = context.make_array(s_tris)(context, builder, a_tris)
        verts = [context.make_array(t)(context, builder, a) for t, a in zip((s_v0, s_v1, s_v2), (a_v0, a_v1, a_v2))]
        four = ir.Constant(_I64, 4)
        rf_row = builder.udiv(builder.extract_value(rf_arr.strides, 0), four)
        ri_row = builder.udiv(builder.extract_value(ri_arr.strides, 0), four)
        lanes_ = [context.cast(builder, a, t, types.int64) for a, t in zip(a_lanes, s_lanes)]
        mask_ = context.cast(builder, a_mask, s_mask, types.int64)
        n_ = context.cast(builder, a_n, s_n, types.int64)
        any_hit_ = context.cast(builder, a_any, s_any, types.boolean)

        def fptr(name):
            return [_row_ptr(builder, rf_arr.data, rf_row, ROWS_F[name], o, _V4F) for o in lanes_]

        def iptr(name):
            return [_row_ptr(builder, ri_arr.data, ri_row, ROWS_I[name], o, _V4I) for o in lanes_]

        def load(ptrs):
            return w.load(builder, ptrs)

        # Loop invariants: the lanes' shear, origin and segment start, and which axis each picks.
        ok = [load(fptr(k)) for k in ("OKX", "OKY", "OKZ")]
        sx, sy, sz = (load(fptr(k)) for k in ("SX", "SY", "SZ"))
        tlo = load(fptr("TLO"))
        axes = []
        for name in ("KX", "KY", "KZ"):
            k = load(iptr(name))
            axes.append((builder.icmp_signed("==", k, w.const(w.i, 0)),
                         builder.icmp_signed("==", k, w.const(w.i, 1))))
        lane_bits = ir.Constant(ir.VectorType(_I64, w.lanes), [1 << b for b in range(w.lanes)])
        selected = builder.icmp_unsigned("!=", builder.and_(w.splat(builder, mask_, ir.VectorType(_I64, w.lanes)), lane_bits),
                                         ir.Constant(ir.VectorType(_I64, w.lanes), [0] * w.lanes))
        thi0 = load(fptr("THI"))
        # The scalar loop skips a lane that is not selected or not live (not TLO <= THI).
        active = builder.and_(selected, builder.fcmp_ordered("<=", tlo, thi0))

        # Loop-carried state; SROA turns these into registers.
        state = {}
        initial = {"thi": thi0, "best_t": load(fptr("BEST_T")), "best_u": load(fptr("BEST_U")),
                   "best_v": load(fptr("BEST_V")), "best_prim": load(iptr("BEST_PRIM")),
                   "alive": active, "tests": ir.Constant(_I64, 0), "died": ir.Constant(_I64, 0),
                   "j": ir.Constant(_I64, 0)}
        for name, value in initial.items():
            state[name] = cgutils.alloca_once(builder, value.type, name="tri4." + name)
            builder.store(value, state[name])

        header = builder.append_basic_block("tri4.header")
        body = builder.append_basic_block("tri4.body")
        done = builder.append_basic_block("tri4.done")
        builder.branch(header)

        builder.position_at_end(header)
        j = builder.load(state["j"])
        alive = builder.load(state["alive"])
        builder.cbranch(builder.and_(builder.icmp_signed("<", j, n_), w.any(builder, alive)), body, done)

        builder.position_at_end(body)
        tri32 = builder.load(cgutils.get_item_pointer(context, builder, s_tris, tris_arr, [j]))
        tri = builder.sext(tri32, _I64)
        # Corner coordinates, translated by each lane's own permuted origin.
        corners = []
        for arr, arr_type in zip(verts, (s_v0, s_v1, s_v2)):
            xyz = [w.splat(builder, builder.load(cgutils.get_item_pointer(context, builder, arr_type, arr,
                                                                          [tri, ir.Constant(_I64, c)])), w.f)
                   for c in range(3)]
            corner = []
            for (is0, is1), o in zip(axes, ok):
                picked = builder.select(is0, xyz[0], builder.select(is1, xyz[1], xyz[2]))
                corner.append(builder.fsub(picked, o))
            corners.append(corner)
        az_, bz_, cz_ = (corner[2] for corner in corners)
        eu, ev, ew, det, mixed, flat = _sheared_edges(builder, w, corners, sx, sy)
        # Most tests end here: no live lane sees the triangle's edges with one sign (or every
        # such lane sees it edge-on). Skipping the division and the update for them changes no
        # lane's result: those lanes' ``hit`` below would be false.
        candidate = builder.and_(alive, builder.not_(builder.or_(mixed, flat)))
        update = builder.append_basic_block("tri4.update")
        skip = builder.append_basic_block("tri4.skip")
        builder.cbranch(w.any(builder, candidate), update, skip)

        builder.position_at_end(skip)
        builder.store(builder.add(builder.load(state["tests"]), w.popcount(builder, alive)), state["tests"])
        builder.store(builder.add(j, ir.Constant(_I64, 1)), state["j"])
        builder.branch(header)

        builder.position_at_end(update)
        scaled_t = builder.fadd(builder.fadd(builder.fmul(eu, builder.fmul(sz, az_)),
                                             builder.fmul(ev, builder.fmul(sz, bz_))),
                                builder.fmul(ew, builder.fmul(sz, cz_)))
        rcp = builder.fdiv(w.const(w.f, 1.0), det)
        t = builder.fmul(scaled_t, rcp)
        thi = builder.load(state["thi"])
        inside = builder.and_(builder.fcmp_ordered(">=", t, tlo), builder.fcmp_ordered("<=", t, thi))
        hit = builder.and_(builder.and_(builder.not_(mixed), builder.not_(flat)), inside)
        # intersect_lanes' update: a finite hit that ``closer`` prefers (smaller t, then index).
        best_t = builder.load(state["best_t"])
        best_prim = builder.load(state["best_prim"])
        tri4 = w.splat(builder, tri32, w.i)
        closer = builder.or_(builder.fcmp_ordered("<", t, best_t),
                             builder.and_(builder.fcmp_ordered("==", t, best_t),
                                          builder.icmp_signed("<", tri4, best_prim)))
        finite = builder.fcmp_ordered("<", t, w.const(w.f, float("inf")))
        take = builder.and_(builder.and_(hit, alive), builder.and_(finite, closer))
        u = builder.fmul(ev, rcp)
        v = builder.fmul(ew, rcp)
        builder.store(builder.select(take, t, best_t), state["best_t"])
        builder.store(builder.select(take, tri4, best_prim), state["best_prim"])
        builder.store(builder.select(take, u, builder.load(state["best_u"])), state["best_u"])
        builder.store(builder.select(take, v, builder.load(state["best_v"])), state["best_v"])
        # Closest hit: the segment shrinks to t. Any hit: the lane dies.
        new_thi = builder.select(any_hit_, w.const(w.f, float("-inf")), t)
        builder.store(builder.select(take, new_thi, thi), state["thi"])
        dying = builder.and_(take, w.splat(builder, any_hit_, w.b))
        builder.store(builder.and_(alive, builder.not_(dying)), state["alive"])
        builder.store(builder.add(builder.load(state["tests"]), w.popcount(builder, alive)), state["tests"])
        builder.store(builder.add(builder.load(state["died"]), w.popcount(builder, dying)), state["died"])
        builder.store(builder.add(j, ir.Constant(_I64, 1)), state["j"])
        builder.branch(header)

        builder.position_at_end(done)
        # Unselected lanes get back the values just read.
        w.store(builder, builder.load(state["thi"]), fptr("THI"))
        for name in ("best_t", "best_u", "best_v"):
            w.store(builder, builder.load(state[name]), fptr(name.upper()))
        w.store(builder, builder.load(state["best_prim"]), iptr("BEST_PRIM"))
        return context.make_tuple(builder, signature.return_type,
                                  [builder.load(state["tests"]), builder.load(state["died"])])

    return codegen


def _sheared_edges(builder, w, corners, sx, sy):
    """The watertight test's 2D step on the translated, permuted corners [[ax, ay, az], [bx, by,
    bz], [cx, cy, cz]] (vectors of ``w``'s width): shear by sx, sy, then the edge functions.
    Returns (eu, ev, ew, det, mixed, flat): mixed, a lane sees edges of both signs; flat, det == 0
    (either way the lane misses). The same operations, in the same order, as
    ``engine.core.triangle.intersect_triangle``."""
    (ax_, ay_, az_), (bx_, by_, bz_), (cx_, cy_, cz_) = corners
    ax = builder.fsub(ax_, builder.fmul(sx, az_))
    ay = builder.fsub(ay_, builder.fmul(sy, az_))
    bx = builder.fsub(bx_, builder.fmul(sx, bz_))
    by = builder.fsub(by_, builder.fmul(sy, bz_))
    cx = builder.fsub(cx_, builder.fmul(sx, cz_))
    cy = builder.fsub(cy_, builder.fmul(sy, cz_))
    eu = w.edge(builder, cx, by, cy, bx)
    ev = w.edge(builder, ax, cy, ay, cx)
    ew = w.edge(builder, bx, ay, by, ax)
    zero = w.const(w.f, 0.0)

    def any_of(op):
        return builder.or_(builder.or_(builder.fcmp_ordered(op, eu, zero), builder.fcmp_ordered(op, ev, zero)),
                           builder.fcmp_ordered(op, ew, zero))

    mixed = builder.and_(any_of("<"), any_of(">"))
    det = builder.fadd(builder.fadd(eu, ev), ew)
    flat = builder.fcmp_ordered("==", det, zero)
    return eu, ev, ew, det, mixed, flat


@intrinsic
def triangles_block(typingctx, blocks, g, n, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax, answers):
    """One ray against the triangles in the first n (1..4) lanes of block g of ``blocks``
    (f32[G,R,4], C order, R >= 9: ``engine.query.leaf_blocks``). Returns the int64 mask of the
    lanes hit and stores each lane's ``engine.core.triangle.intersect_triangle`` answer, bit for
    bit, in answers (f32, C order): t in [0:4], u in [4:8], v in [8:12] (t = inf, u = v = 0 for a
    miss and for the lanes past n). A lane is in the mask when its t is finite. The ray comes as
    ``intersect_triangle`` takes it: its permuted origin okx, oky, okz, axes kx, ky, kz and shear
    sx, sy, sz, segment [tmin, tmax]. The lanes are triangles here, so the per-ray mesh queries
    test four in one go; each corner component is one <4 x float> load from the block's row
    3 * corner + axis, at an offset computed from the ray's permutation (the rows of (x, y, z)
    corners it replaced needed 36 scalar loads and inserts). The answers go to memory, not back
    as a tuple, so that a walk visits the hit lanes by the mask instead of indexing a tuple by a
    run-time lane (a jump table)."""
    _check(blocks, types.float32, 3, "blocks")
    _check(answers, types.float32, 1, "answers")
    for x in (g, n, kx, ky, kz):
        if not isinstance(x, types.Integer):
            raise TypingError(f"expected an integer, got {x}")
    for x in (okx, oky, okz, sx, sy, sz, tmin, tmax):
        if not isinstance(x, types.Float):
            raise TypingError(f"expected a float, got {x}")
    sig = types.int64(blocks, g, n, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax, answers)
    w = _Width(1)

    def codegen(context, builder, signature, args):
        s = signature.args
        array = context.make_array(s[0])(context, builder, args[0])
        block_elems = builder.udiv(builder.extract_value(array.strides, 0), ir.Constant(_I64, 4))
        block = builder.mul(context.cast(builder, args[1], s[1], types.int64), block_elems)
        n_ = context.cast(builder, args[2], s[2], types.int64)
        ok = [w.splat(builder, context.cast(builder, args[k], s[k], types.float32), w.f) for k in (3, 4, 5)]
        axes = [context.cast(builder, args[k], s[k], types.int64) for k in (6, 7, 8)]
        sx_, sy_, sz_ = (w.splat(builder, context.cast(builder, args[k], s[k], types.float32), w.f)
                         for k in (9, 10, 11))
        tlo = w.splat(builder, context.cast(builder, args[12], s[12], types.float32), w.f)
        thi = w.splat(builder, context.cast(builder, args[13], s[13], types.float32), w.f)

        def corner(c, axis):
            """<4 x float>: component ``axis`` (an i64 value) of corner c of the block's lanes."""
            index = builder.add(block, builder.add(ir.Constant(_I64, 12 * c), builder.mul(axis, ir.Constant(_I64, 4))))
            pointer = builder.bitcast(builder.gep(array.data, [index]), w.f.as_pointer())
            return builder.load(pointer, align=4)

        corners = [[builder.fsub(corner(c, axis), o) for axis, o in zip(axes, ok)] for c in range(3)]
        az_, bz_, cz_ = (corner_[2] for corner_ in corners)
        eu, ev, ew, det, mixed, flat = _sheared_edges(builder, w, corners, sx_, sy_)
        zero = w.const(w.f, 0.0)
        scaled_t = builder.fadd(builder.fadd(builder.fmul(eu, builder.fmul(sz_, az_)),
                                             builder.fmul(ev, builder.fmul(sz_, bz_))),
                                builder.fmul(ew, builder.fmul(sz_, cz_)))
        rcp = builder.fdiv(w.const(w.f, 1.0), det)
        t = builder.fmul(scaled_t, rcp)
        inside = builder.and_(builder.fcmp_ordered(">=", t, tlo), builder.fcmp_ordered("<=", t, thi))
        slots = ir.Constant(ir.VectorType(_I64, 4), [0, 1, 2, 3])
        present = builder.icmp_signed("<", slots, w.splat(builder, n_, ir.VectorType(_I64, 4)))
        hit = builder.and_(builder.and_(present, builder.not_(builder.or_(mixed, flat))), inside)
        out = builder.bitcast(context.make_array(s[14])(context, builder, args[14]).data, w.f.as_pointer())
        builder.store(builder.select(hit, t, w.const(w.f, float("inf"))), out, align=4)
        builder.store(builder.select(hit, builder.fmul(ev, rcp), zero), builder.gep(out, [ir.Constant(_I32, 1)]),
                      align=4)
        builder.store(builder.select(hit, builder.fmul(ew, rcp), zero), builder.gep(out, [ir.Constant(_I32, 2)]),
                      align=4)
        # The mask leaves out a t that overflowed to inf: such a lane answers as a miss.
        counted = builder.and_(hit, builder.fcmp_ordered("<", t, w.const(w.f, float("inf"))))
        return builder.zext(builder.bitcast(counted, ir.IntType(4)), _I64)

    return sig, codegen
