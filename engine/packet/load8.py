"""Eight rays into a packet's local rows at once, written directly as LLVM vector IR (a numba
intrinsic, as ``engine.packet.simd4`` does for the slab and triangle tests).

``load_rays8(org, inv, dirs, tmin, tmax, r, rf, ri, i)`` is ``engine.packet.kernels.load_packet``'s
per-ray step for rays r .. r+7 of the batch into lanes i .. i+7: it copies the origin and inverse
direction, sets the live segment, the watertight test's axis permutation, shear and permuted
origin (``engine.core.triangle.ray_shear``) and the empty best hit, and returns the 8-bit mask of
the live lanes (tmin <= tmax). Per lane it is exactly the scalar step -- the same compares
(ordered, so a NaN segment is dead), the same selects of the dominant axis, the same IEEE
divisions -- so every row holds the same bits either way (tested against the scalar step).

Why: loading a packet was 19% of the kitchen's shadow walk (perf samples over the walk's code)
and about 9 ns a ray on one core over a whole frame: per ray, 21 scalar stores into as many
rows, 3 scalar divisions and branches on the dominant axis. Eight rays take 21 vector stores,
3 vector divisions and no branch.

The batch arrays are read as rows of three floats (org, inv, dirs: f32[R,3] whose rows are 12
contiguous bytes; the caller checks the strides) and tmin, tmax as f32[R]; rf f32[RF_ROWS, L]
and ri i32[RI_ROWS, L] are the packet-local rows in the layout of ``engine.packet.kernels``.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

#: Rows of the packet-local blocks this writes (``engine.packet.kernels`` asserts its layout).
ROWS_F = {"OX": 0, "OY": 1, "OZ": 2, "IX": 3, "IY": 4, "IZ": 5, "TLO": 6, "THI": 7, "SX": 8, "SY": 9, "SZ": 10,
          "OKX": 11, "OKY": 12, "OKZ": 13, "BEST_T": 14, "BEST_U": 15, "BEST_V": 16}
ROWS_I = {"KX": 0, "KY": 1, "KZ": 2, "BEST_PRIM": 3}

_W = 8
_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_VF = ir.VectorType(_F32, _W)
_VI = ir.VectorType(_I32, _W)


def _f32_splat(value):
    return ir.Constant(_VF, [value] * _W)


def _i32_splat(value):
    return ir.Constant(_VI, [value] * _W)


def _xyz(builder, data, row):
    """The x, y and z <8 x float> of rows row .. row+7 of an f32[R,3] array with 12-byte rows."""
    start = builder.gep(data, [builder.mul(row, ir.Constant(_I64, 3))])
    block = builder.load(builder.bitcast(start, ir.VectorType(_F32, 3 * _W).as_pointer()), align=4)
    undefined = ir.Constant(ir.VectorType(_F32, 3 * _W), ir.Undefined)
    return [builder.shuffle_vector(block, undefined, ir.Constant(_VI, [3 * k + a for k in range(_W)]))
            for a in range(3)]


def _vector_at(builder, data, index, vector_type):
    """Load or store address: element ``index`` of ``data`` viewed as a pointer to vector_type."""
    return builder.bitcast(builder.gep(data, [index]), vector_type.as_pointer())


def _pick(builder, axis, x, y, z):
    """Per lane x, y or z for axis 0, 1 or 2 (<8 x i32>), as ``dx if k == 0 else (dy if k == 1
    else dz)``."""
    is0 = builder.icmp_signed("==", axis, _i32_splat(0))
    is1 = builder.icmp_signed("==", axis, _i32_splat(1))
    return builder.select(is0, x, builder.select(is1, y, z))


def _check_array(value, ndim, dtype, what):
    if not (isinstance(value, types.Array) and value.dtype == dtype and value.ndim == ndim):
        raise TypingError(f"{what} must be a {dtype} array of {ndim} dimension(s), got {value}")


@intrinsic
def load_rays8(typingctx, org, inv, dirs, tmin, tmax, r, rf, ri, i):
    """Rays r .. r+7 into lanes i .. i+7 of rf and ri; returns the mask of live lanes (int64)."""
    for value, what in ((org, "org"), (inv, "inv"), (dirs, "dirs")):
        _check_array(value, 2, types.float32, what)
    for value, what in ((tmin, "tmin"), (tmax, "tmax")):
        _check_array(value, 1, types.float32, what)
    _check_array(rf, 2, types.float32, "rf")
    _check_array(ri, 2, types.int32, "ri")
    for value, what in ((r, "r"), (i, "i")):
        if not isinstance(value, types.Integer):
            raise TypingError(f"{what} must be an integer, got {value}")
    sig = types.int64(org, inv, dirs, tmin, tmax, r, rf, ri, i)

    def codegen(context, builder, signature, args):
        arrays = [context.make_array(signature.args[k])(context, builder, args[k]) for k in (0, 1, 2, 3, 4, 6, 7)]
        org_a, inv_a, dirs_a, tmin_a, tmax_a, rf_a, ri_a = arrays
        row = context.cast(builder, args[5], signature.args[5], types.int64)
        lane = context.cast(builder, args[8], signature.args[8], types.int64)
        four = ir.Constant(_I64, 4)
        rf_elems = builder.udiv(builder.extract_value(rf_a.strides, 0), four)
        ri_elems = builder.udiv(builder.extract_value(ri_a.strides, 0), four)

        def store_f(name, value):
            index = builder.add(builder.mul(ir.Constant(_I64, ROWS_F[name]), rf_elems), lane)
            builder.store(value, _vector_at(builder, rf_a.data, index, _VF), align=4)

        def store_i(name, value):
            index = builder.add(builder.mul(ir.Constant(_I64, ROWS_I[name]), ri_elems), lane)
            builder.store(value, _vector_at(builder, ri_a.data, index, _VI), align=4)

        ox, oy, oz = _xyz(builder, org_a.data, row)
        ix, iy, iz = _xyz(builder, inv_a.data, row)
        dx, dy, dz = _xyz(builder, dirs_a.data, row)
        t_lo = builder.load(_vector_at(builder, tmin_a.data, row, _VF), align=4)
        t_hi = builder.load(_vector_at(builder, tmax_a.data, row, _VF), align=4)
        live = builder.fcmp_ordered("<=", t_lo, t_hi)

        # ray_shear, lane by lane: kz the dominant axis (x before y before z on ties), kx, ky
        # the next two, swapped when d[kz] < 0.
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_VF, [_VF]), "llvm.fabs.v8f32")
        ax, ay, az = (builder.call(fabs, [d]) for d in (dx, dy, dz))
        x_wins = builder.and_(builder.fcmp_ordered(">=", ax, ay), builder.fcmp_ordered(">=", ax, az))
        y_wins = builder.fcmp_ordered(">=", ay, az)

        def by_winner(if_x, if_y, otherwise):
            return builder.select(x_wins, if_x, builder.select(y_wins, if_y, otherwise))

        kz = by_winner(_i32_splat(0), _i32_splat(1), _i32_splat(2))
        after = by_winner(_i32_splat(1), _i32_splat(2), _i32_splat(0))
        after2 = by_winner(_i32_splat(2), _i32_splat(0), _i32_splat(1))
        dkz = by_winner(dx, dy, dz)
        negative = builder.fcmp_ordered("<", dkz, _f32_splat(0.0))
        kx = builder.select(negative, after2, after)
        ky = builder.select(negative, after, after2)
        sx = builder.fdiv(_pick(builder, kx, dx, dy, dz), dkz)
        sy = builder.fdiv(_pick(builder, ky, dx, dy, dz), dkz)
        sz = builder.fdiv(_f32_splat(1.0), dkz)

        # A dead lane: the empty segment, axes 0, 1, 2 and zero shear and origin.
        zero = _f32_splat(0.0)

        def live_or(value, dead):
            return builder.select(live, value, dead)

        for name, value in (("OX", ox), ("OY", oy), ("OZ", oz), ("IX", ix), ("IY", iy), ("IZ", iz)):
            store_f(name, value)
        store_f("TLO", live_or(t_lo, _f32_splat(float("inf"))))
        store_f("THI", live_or(t_hi, _f32_splat(float("-inf"))))
        store_f("SX", live_or(sx, zero))
        store_f("SY", live_or(sy, zero))
        store_f("SZ", live_or(sz, zero))
        store_f("OKX", live_or(_pick(builder, kx, ox, oy, oz), zero))
        store_f("OKY", live_or(_pick(builder, ky, ox, oy, oz), zero))
        store_f("OKZ", live_or(_pick(builder, kz, ox, oy, oz), zero))
        store_f("BEST_T", _f32_splat(float("inf")))
        store_f("BEST_U", zero)
        store_f("BEST_V", zero)
        store_i("KX", live_or(kx, _i32_splat(0)))
        store_i("KY", live_or(ky, _i32_splat(1)))
        store_i("KZ", live_or(kz, _i32_splat(2)))
        store_i("BEST_PRIM", _i32_splat(-1))
        return builder.zext(builder.bitcast(live, ir.IntType(_W)), _I64)

    return sig, codegen
