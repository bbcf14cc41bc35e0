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

from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import I32, Lanes

#: Rows of the packet-local blocks this writes (``engine.packet.kernels`` asserts its layout).
ROWS_F = {"OX": 0, "OY": 1, "OZ": 2, "IX": 3, "IY": 4, "IZ": 5, "TLO": 6, "THI": 7, "SX": 8, "SY": 9, "SZ": 10,
          "OKX": 11, "OKY": 12, "OKZ": 13, "BEST_T": 14, "BEST_U": 15, "BEST_V": 16}
ROWS_I = {"KX": 0, "KY": 1, "KZ": 2, "BEST_PRIM": 3}


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
        lanes = Lanes(context, builder)
        org_a, inv_a, dirs_a, tmin_a, tmax_a = (lanes.array(signature.args[k], args[k]) for k in range(5))
        rf_a, ri_a = lanes.array(signature.args[6], args[6]), lanes.array(signature.args[7], args[7])
        row = lanes.index(signature.args[5], args[5])
        lane = lanes.index(signature.args[8], args[8])

        def store_f(name, value):
            lanes.store_at(rf_a, lanes.row_start(rf_a, ROWS_F[name], lane), value)

        def store_i(name, value):
            lanes.store_at(ri_a, lanes.row_start(ri_a, ROWS_I[name], lane), value)

        def axis(k):
            return lanes.splat(k, I32)

        ox, oy, oz = lanes.rows3(org_a, row)
        ix, iy, iz = lanes.rows3(inv_a, row)
        dx, dy, dz = lanes.rows3(dirs_a, row)
        t_lo, t_hi = lanes.row(tmin_a, row), lanes.row(tmax_a, row)
        live = t_lo <= t_hi

        # ray_shear, lane by lane: kz the dominant axis (x before y before z on ties), kx, ky
        # the next two, swapped when d[kz] < 0.
        ax, ay, az = lanes.fabs(dx), lanes.fabs(dy), lanes.fabs(dz)
        x_wins = (ax >= ay) & (ax >= az)
        y_wins = ay >= az

        def by_winner(if_x, if_y, otherwise):
            return lanes.where(x_wins, if_x, lanes.where(y_wins, if_y, otherwise))

        def pick(k, x, y, z):  # x, y or z by axis k, as ``dx if k == 0 else (dy if k == 1 else dz)``
            return lanes.where(k.eq(0), x, lanes.where(k.eq(1), y, z))

        kz = by_winner(axis(0), axis(1), axis(2))
        after = by_winner(axis(1), axis(2), axis(0))
        after2 = by_winner(axis(2), axis(0), axis(1))
        dkz = by_winner(dx, dy, dz)
        negative = dkz < 0.0
        kx = lanes.where(negative, after2, after)
        ky = lanes.where(negative, after, after2)
        sx = pick(kx, dx, dy, dz) / dkz
        sy = pick(ky, dx, dy, dz) / dkz
        sz = 1.0 / dkz

        # A dead lane: the empty segment, axes 0, 1, 2 and zero shear and origin.
        for name, value in (("OX", ox), ("OY", oy), ("OZ", oz), ("IX", ix), ("IY", iy), ("IZ", iz)):
            store_f(name, value)
        store_f("TLO", lanes.where(live, t_lo, float("inf")))
        store_f("THI", lanes.where(live, t_hi, float("-inf")))
        store_f("SX", lanes.where(live, sx, 0.0))
        store_f("SY", lanes.where(live, sy, 0.0))
        store_f("SZ", lanes.where(live, sz, 0.0))
        store_f("OKX", lanes.where(live, pick(kx, ox, oy, oz), 0.0))
        store_f("OKY", lanes.where(live, pick(ky, ox, oy, oz), 0.0))
        store_f("OKZ", lanes.where(live, pick(kz, ox, oy, oz), 0.0))
        store_f("BEST_T", lanes.splat(float("inf")))
        store_f("BEST_U", lanes.splat(0.0))
        store_f("BEST_V", lanes.splat(0.0))
        store_i("KX", lanes.where(live, kx, 0))
        store_i("KY", lanes.where(live, ky, 1))
        store_i("KZ", lanes.where(live, kz, 2))
        store_i("BEST_PRIM", lanes.splat(-1, I32))
        return lanes.bitmask(live)

    return sig, codegen
