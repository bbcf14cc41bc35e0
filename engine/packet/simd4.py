"""Four-wide SIMD kernels written directly as LLVM vector IR (numba intrinsics).

Numba builds its LLVM pipeline without the SLP vectoriser (``NUMBA_SLP_VECTORIZE`` defaults to
0) and fully unrolls a fixed 4-iteration loop before the loop vectoriser could see it, so the
4-lane loops of a 2x2 SIMD ray stay scalar code however they are written. These intrinsics
emit the <4 x float> operations themselves, as the paper's SSE code does:

- ``slab4(rf, lane0, b0x, b0y, b0z, b1x, b1y, b1z)``: the ray-box test of the 2x2 SIMD ray whose
  lanes are columns lane0 .. lane0+3 of the packet-local rows rf (f32[rows, L], C order, rows
  OX, OY, OZ, IX, IY, IZ, TLO, THI = 0..7 as in ``engine.packet.kernels``) against the box
  (b0, b1). Returns the 4-bit mask of the lanes that hit. Every operation, operand order and
  compare matches ``engine.core.triangle.slab_test`` (numba's min/max are selects on ordered
  compares), so each lane's answer is exactly slab_test's.
- ``slab4x2(rf, lane0, lane1, ...)``: the same test of two SIMD rays at once, as one <8 x float>
  test (AVX2 has 8 float lanes): an 8-bit mask, lane0's lanes in the low 4 bits.
- ``slab1x8(box, node, ox, ..., t_hi, entries)``: one ray against the eight child boxes of a node
  of the mesh queries' 8-wide tree (``engine.query.wide``), as one <8 x float> test: the mask of
  the children hit, their eight entry distances (inf: missed) stored in ``entries``.
- ``planes4_box(fr, b0x, ..., b1z)`` / ``planes4_triangle(fr, ax, ..., cz)``: a box / triangle
  against the four planes of a packet frustum stored in SoA order (fr: f32[16] = nx[4], ny[4],
  nz[4], d[4]); True when it lies wholly outside one of them. Same arithmetic as the scalar
  reference in ``engine.packet.frustum_cull``.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.triangle import SLAB_SLACK

_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_V4 = ir.VectorType(_F32, 4)
_ZERO4 = ir.Constant(ir.VectorType(_I32, 4), [0, 0, 0, 0])

#: Rows of the packet-local float block that ``slab4`` reads (engine.packet.kernels layout).
_ROW_OX, _ROW_OY, _ROW_OZ, _ROW_IX, _ROW_IY, _ROW_IZ, _ROW_TLO, _ROW_THI = range(8)


def _min(builder, a, b):
    """numba's min(a, b) for floats: b < a ? b : a."""
    return builder.select(builder.fcmp_ordered("<", b, a), b, a)


def _max(builder, a, b):
    """numba's max(a, b) for floats: b > a ? b : a."""
    return builder.select(builder.fcmp_ordered(">", b, a), b, a)


def _float32_args(context, builder, sig, args, first):
    return [context.cast(builder, a, t, types.float32) for a, t in zip(args[first:], sig.args[first:])]


def _vector_row(builder, data, row_elems, row, offset):
    """Load <4 x float> from data[row * row_elems + offset] (data: float*)."""
    index = builder.add(builder.mul(ir.Constant(_I64, row), row_elems), offset)
    ptr = builder.gep(data, [index])
    return builder.load(builder.bitcast(ptr, _V4.as_pointer()), align=4)


def _check_f32_array(value, ndim, what):
    if not (isinstance(value, types.Array) and value.dtype == types.float32 and value.ndim == ndim
            and value.layout == "C"):
        raise TypingError(f"{what} must be a C-contiguous float32 array of {ndim} dimension(s), got {value}")


def _check_scalars(values):
    for v in values:
        if not isinstance(v, (types.Float, types.Integer)):
            raise TypingError(f"expected a number, got {v}")


def _concat(builder, halves):
    """One vector of the lanes of ``halves`` (<4 x T> each), in order."""
    if len(halves) == 1:
        return halves[0]
    return builder.shuffle_vector(halves[0], halves[1], ir.Constant(ir.VectorType(_I32, 8), list(range(8))))


def _splat_n(builder, scalar, width):
    """<width x float> with every lane = scalar."""
    vector = ir.VectorType(_F32, width)
    one = builder.insert_element(ir.Constant(vector, ir.Undefined), scalar, ir.Constant(_I32, 0))
    return builder.shuffle_vector(one, ir.Constant(vector, ir.Undefined),
                                  ir.Constant(ir.VectorType(_I32, width), [0] * width))


def _fabs_n(builder, v, width):
    vector = ir.VectorType(_F32, width)
    fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vector, [vector]), f"llvm.fabs.v{width}f32")
    return builder.call(fabs, [v])


def _slab_codegen(n_rays):
    """Codegen of the slab test of ``n_rays`` SIMD rays (args: rf, n_rays lane offsets, box)."""
    width = 4 * n_rays

    def codegen(context, builder, signature, args):
        arr = context.make_array(signature.args[0])(context, builder, args[0])
        itemsize = ir.Constant(_I64, 4)
        row_elems = builder.udiv(builder.extract_value(arr.strides, 0), itemsize)
        offsets = [context.cast(builder, args[1 + k], signature.args[1 + k], types.int64) for k in range(n_rays)]

        def row(k):
            return _concat(builder, [_vector_row(builder, arr.data, row_elems, k, o) for o in offsets])

        box = _float32_args(context, builder, signature, args, 1 + n_rays)
        lo = [_splat_n(builder, v, width) for v in box[:3]]
        hi = [_splat_n(builder, v, width) for v in box[3:]]
        origin = [row(_ROW_OX), row(_ROW_OY), row(_ROW_OZ)]
        inverse = [row(_ROW_IX), row(_ROW_IY), row(_ROW_IZ)]
        tn = tf = None
        for axis in range(3):
            t0 = builder.fmul(builder.fsub(lo[axis], origin[axis]), inverse[axis])
            t1 = builder.fmul(builder.fsub(hi[axis], origin[axis]), inverse[axis])
            near, far = _min(builder, t0, t1), _max(builder, t0, t1)
            tn = near if tn is None else _max(builder, tn, near)
            tf = far if tf is None else _min(builder, tf, far)
        slack = _splat_n(builder, ir.Constant(_F32, float(SLAB_SLACK)), width)
        tn = _max(builder, builder.fsub(tn, builder.fmul(_fabs_n(builder, tn, width), slack)), row(_ROW_TLO))
        tf = _min(builder, builder.fadd(tf, builder.fmul(_fabs_n(builder, tf, width), slack)), row(_ROW_THI))
        hit = builder.fcmp_ordered("<=", tn, tf)
        return builder.zext(builder.bitcast(hit, ir.IntType(width)), _I64)

    return codegen


@intrinsic
def slab4(typingctx, rf, lane0, b0x, b0y, b0z, b1x, b1y, b1z):
    """4-bit mask of the lanes lane0 .. lane0+3 of rf whose segment meets the box (b0, b1)."""
    _check_f32_array(rf, 2, "rf")
    if not isinstance(lane0, types.Integer):
        raise TypingError(f"lane0 must be an integer, got {lane0}")
    _check_scalars((b0x, b0y, b0z, b1x, b1y, b1z))
    return types.int64(rf, lane0, b0x, b0y, b0z, b1x, b1y, b1z), _slab_codegen(1)


@intrinsic
def slab4x2(typingctx, rf, lane0, lane1, b0x, b0y, b0z, b1x, b1y, b1z):
    """``slab4`` of two SIMD rays (lanes lane0 .. lane0+3 and lane1 .. lane1+3, anywhere in the
    packet) in one 8-wide test: bits 0-3 are lane0's mask, bits 4-7 lane1's. AVX2 holds 8 float
    lanes, so two SIMD rays cost about what one does."""
    _check_f32_array(rf, 2, "rf")
    for lane in (lane0, lane1):
        if not isinstance(lane, types.Integer):
            raise TypingError(f"lane0, lane1 must be integers, got {lane}")
    _check_scalars((b0x, b0y, b0z, b1x, b1y, b1z))
    return types.int64(rf, lane0, lane1, b0x, b0y, b0z, b1x, b1y, b1z), _slab_codegen(2)


def _f32_inf_vector(width):
    return ir.Constant(ir.VectorType(_F32, width), [float("inf")] * width)


@intrinsic
def slab1x8(typingctx, box, node, ox, oy, oz, ix, iy, iz, t_lo, t_hi, entries):
    """One ray against the eight child boxes of a node of the mesh queries' 8-wide tree
    (box: f32[W,R,8], R >= 6, C order, rows lo x, y, z then hi x, y, z first: the packed nodes of
    ``engine.query.wide``; node: its row), as one <8 x float> test (this machine's AVX2 width). Returns the int64 mask (bit s set
    when child s is hit) and stores the eight entry distances in entries[0:8] (f32, C order),
    each the child's ``engine.core.triangle.slab_test`` answer (inf: missed), the same
    operations in the same order, lane by lane. A slot whose box is NaN is never hit.

    The entries go to memory as one vector store rather than back as a tuple: a walk reads the
    entry of a slot it picks at run time, and numba compiles ``tuple[s]`` into a jump table, one
    indirect branch per child pushed (bunny, incoherent rays: 9% of the walk)."""
    _check_f32_array(box, 3, "box")
    _check_f32_array(entries, 1, "entries")
    if not isinstance(node, types.Integer):
        raise TypingError(f"node must be an integer, got {node}")
    _check_scalars((ox, oy, oz, ix, iy, iz, t_lo, t_hi))
    sig = types.int64(box, node, ox, oy, oz, ix, iy, iz, t_lo, t_hi, entries)
    width = 8
    vector = ir.VectorType(_F32, width)

    def codegen(context, builder, signature, args):
        arr = context.make_array(signature.args[0])(context, builder, args[0])
        node_ = context.cast(builder, args[1], signature.args[1], types.int64)
        node_elems = builder.udiv(builder.extract_value(arr.strides, 0), ir.Constant(_I64, 4))

        def row(k):
            index = builder.add(builder.mul(node_, node_elems), ir.Constant(_I64, k * width))
            return builder.load(builder.bitcast(builder.gep(arr.data, [index]), vector.as_pointer()), align=4)

        ray = [_splat_n(builder, v, width) for v in _float32_args(context, builder, signature, args[:10], 2)]
        origin, inverse, (segment_lo, segment_hi) = ray[0:3], ray[3:6], ray[6:8]
        tn = tf = None
        for axis in range(3):
            t0 = builder.fmul(builder.fsub(row(axis), origin[axis]), inverse[axis])
            t1 = builder.fmul(builder.fsub(row(3 + axis), origin[axis]), inverse[axis])
            near, far = _min(builder, t0, t1), _max(builder, t0, t1)
            tn = near if tn is None else _max(builder, tn, near)
            tf = far if tf is None else _min(builder, tf, far)
        slack = _splat_n(builder, ir.Constant(_F32, float(SLAB_SLACK)), width)
        tn = _max(builder, builder.fsub(tn, builder.fmul(_fabs_n(builder, tn, width), slack)), segment_lo)
        tf = _min(builder, builder.fadd(tf, builder.fmul(_fabs_n(builder, tf, width), slack)), segment_hi)
        # NaN (an empty slot) fails the ordered compare: a miss.
        hit = builder.fcmp_ordered("<=", tn, tf)
        out = context.make_array(signature.args[10])(context, builder, args[10])
        builder.store(builder.select(hit, tn, _f32_inf_vector(width)), builder.bitcast(out.data, vector.as_pointer()),
                      align=4)
        return builder.zext(builder.bitcast(hit, ir.IntType(width)), _I64)

    return sig, codegen


def _plane_vectors(context, builder, fr_type, fr_value):
    """(nx, ny, nz, d) <4 x float> from the SoA frustum fr: f32[16]."""
    arr = context.make_array(fr_type)(context, builder, fr_value)
    rows = ir.Constant(_I64, 4)
    return [_vector_row(builder, arr.data, rows, k, ir.Constant(_I64, 0)) for k in range(4)]


def _any_negative(builder, v):
    """True when some lane of v is < 0."""
    below = builder.fcmp_ordered("<", v, ir.Constant(_V4, [0.0] * 4))
    return builder.icmp_unsigned("!=", builder.bitcast(below, ir.IntType(4)), ir.Constant(ir.IntType(4), 0))


@intrinsic
def planes4_box(typingctx, fr, b0x, b0y, b0z, b1x, b1y, b1z):
    """True when the box (b0, b1) is outside one of the four SoA planes in fr (f32[16])."""
    _check_f32_array(fr, 1, "fr")
    _check_scalars((b0x, b0y, b0z, b1x, b1y, b1z))
    sig = types.boolean(fr, b0x, b0y, b0z, b1x, b1y, b1z)

    def codegen(context, builder, signature, args):
        nx, ny, nz, d = _plane_vectors(context, builder, signature.args[0], args[0])
        b = [_splat_n(builder, v, 4) for v in _float32_args(context, builder, signature, args, 1)]
        total = None
        for axis, n in enumerate((nx, ny, nz)):
            # The corner farthest along n: per axis the larger of the two products.
            term = _max(builder, builder.fmul(n, b[axis]), builder.fmul(n, b[axis + 3]))
            total = term if total is None else builder.fadd(total, term)
        return _any_negative(builder, builder.fadd(total, d))

    return sig, codegen


@intrinsic
def planes4_triangle(typingctx, fr, ax, ay, az, bx, by, bz, cx, cy, cz):
    """True when the triangle (a, b, c) is outside one of the four SoA planes in fr (f32[16])."""
    _check_f32_array(fr, 1, "fr")
    _check_scalars((ax, ay, az, bx, by, bz, cx, cy, cz))
    sig = types.boolean(fr, ax, ay, az, bx, by, bz, cx, cy, cz)

    def codegen(context, builder, signature, args):
        nx, ny, nz, d = _plane_vectors(context, builder, signature.args[0], args[0])
        coords = [_splat_n(builder, v, 4) for v in _float32_args(context, builder, signature, args, 1)]
        farthest = None
        for corner in range(3):
            x, y, z = coords[3 * corner: 3 * corner + 3]
            s = builder.fadd(builder.fadd(builder.fmul(nx, x), builder.fmul(ny, y)), builder.fmul(nz, z))
            farthest = s if farthest is None else _max(builder, farthest, s)
        return _any_negative(builder, builder.fadd(farthest, d))

    return sig, codegen

