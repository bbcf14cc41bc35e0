"""Eight lanes at a time in LLVM vector IR, for the codegen of numba intrinsics that do per-lane
work (shading, ray loading) on eight consecutive lanes of a batch.

numba builds its pipeline without LLVM's SLP vectoriser and its loop vectoriser gives up on
these loops (many arrays that might alias, rows of three floats), so per-lane kernels stay
scalar: a division, a square root and a dozen scalar stores per lane. An intrinsic's codegen
can emit the vector operations itself. ``Lanes`` wraps an llvmlite builder so that codegen reads
like the scalar numba code it replaces:

    lanes = Lanes(context, builder)
    x, y, z = lanes.rows3(leave_array, start)          # f32[R,3]: rows start .. start+7
    length = lanes.sqrt(x * x + y * y + z * z)
    lanes.store_rows3(to_light_array, start, (x / length, y / length, z / length), mask=hit)

Values are ``V`` (one <8 x T> vector); + - * / and the comparisons act lane by lane, a Python
number on either side is splatted to the other side's type, and comparisons are *ordered* (a NaN
lane compares False), as numba's scalar compares are. ``lanes.max``/``lanes.min`` are numba's
float max/min (``b > a ? b : a``), not IEEE maxNum. Nothing here is fast-math: no contraction into
fused multiply-adds, no reassociation, so each lane computes exactly what the scalar code does,
bit for bit. Arrays are numba array structs (``context.make_array``) passed as (type, value).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.core.errors import TypingError

WIDTH = 8
F32 = ir.FloatType()
F64 = ir.DoubleType()
I1 = ir.IntType(1)
I8 = ir.IntType(8)
I32 = ir.IntType(32)
I64 = ir.IntType(64)

_LLVM_OF = {types.float32: F32, types.float64: F64, types.int32: I32, types.int64: I64, types.boolean: I8,
            types.uint8: I8}


def _suffix(t):
    """LLVM's name of a scalar type in intrinsic names."""
    return {id(F32): "f32", id(F64): "f64", id(I32): "i32", id(I64): "i64", id(I8): "i8", id(I1): "i1"}[id(t)]


class V:
    """One vector of WIDTH lanes, with lane-wise operators (see the module doc)."""

    __slots__ = ("lanes", "value")

    def __init__(self, lanes: "Lanes", value):
        self.lanes, self.value = lanes, value

    @property
    def element(self):
        return self.value.type.element

    def _other(self, other):
        return other.value if isinstance(other, V) else self.lanes.splat(other, self.element).value

    def _float(self):
        return isinstance(self.element, (ir.FloatType, ir.DoubleType))

    def _arith(self, op_float, op_int, other, reverse=False):
        a, b = self.value, self._other(other)
        if reverse:
            a, b = b, a
        b_ = self.lanes.builder
        return V(self.lanes, getattr(b_, op_float if self._float() else op_int)(a, b))

    def __add__(self, o): return self._arith("fadd", "add", o)
    def __radd__(self, o): return self._arith("fadd", "add", o, True)
    def __sub__(self, o): return self._arith("fsub", "sub", o)
    def __rsub__(self, o): return self._arith("fsub", "sub", o, True)
    def __mul__(self, o): return self._arith("fmul", "mul", o)
    def __rmul__(self, o): return self._arith("fmul", "mul", o, True)
    def __truediv__(self, o): return self._arith("fdiv", "sdiv", o)
    def __rtruediv__(self, o): return self._arith("fdiv", "sdiv", o, True)

    def __neg__(self):
        return V(self.lanes, self.lanes.builder.fneg(self.value)) if self._float() else 0 - self

    def _compare(self, op, other):
        b_ = self.lanes.builder
        if self._float():
            return V(self.lanes, b_.fcmp_ordered(op, self.value, self._other(other)))
        return V(self.lanes, b_.icmp_signed(op, self.value, self._other(other)))

    def __lt__(self, o): return self._compare("<", o)
    def __le__(self, o): return self._compare("<=", o)
    def __gt__(self, o): return self._compare(">", o)
    def __ge__(self, o): return self._compare(">=", o)
    def eq(self, o): return self._compare("==", o)

    def ne(self, o):
        """Python's != : True where either side is NaN (unordered), unlike the others."""
        if not self._float():
            return self._compare("!=", o)
        return V(self.lanes, self.lanes.builder.fcmp_unordered("!=", self.value, self._other(o)))

    def __and__(self, o): return V(self.lanes, self.lanes.builder.and_(self.value, self._other(o)))
    def __or__(self, o): return V(self.lanes, self.lanes.builder.or_(self.value, self._other(o)))
    def __invert__(self): return V(self.lanes, self.lanes.builder.not_(self.value))


class Lanes:
    """Vector codegen over WIDTH lanes for one intrinsic's ``codegen(context, builder, ...)``."""

    def __init__(self, context, builder, width: int = WIDTH):
        self.context, self.builder, self.width = context, builder, width

    # -- values ---------------------------------------------------------------------------
    def vector_type(self, element):
        return ir.VectorType(element, self.width)

    def splat(self, value, element=F32) -> V:
        if isinstance(value, V):
            return value
        if isinstance(value, (int, float, bool, np.number, np.bool_)):
            value = value.item() if isinstance(value, (np.number, np.bool_)) else value
            return V(self, ir.Constant(self.vector_type(element), [value] * self.width))
        # a scalar llvm value: insert, then broadcast
        vector = self.vector_type(value.type)
        one = self.builder.insert_element(ir.Constant(vector, ir.Undefined), value, ir.Constant(I32, 0))
        return V(self, self.builder.shuffle_vector(one, ir.Constant(vector, ir.Undefined),
                                                   ir.Constant(self.vector_type(I32), [0] * self.width)))

    def scalar_arg(self, value, numba_type, as_type=types.float32) -> V:
        """A numba scalar argument, cast to ``as_type`` and splatted."""
        cast = self.context.cast(self.builder, value, numba_type, as_type)
        return self.splat(cast)

    def where(self, mask: V, a, b) -> V:
        """Per lane a where mask else b (either may be a Python number)."""
        ref = a if isinstance(a, V) else b
        a_ = a.value if isinstance(a, V) else self.splat(a, ref.element).value
        b_ = b.value if isinstance(b, V) else self.splat(b, ref.element).value
        return V(self, self.builder.select(mask.value, a_, b_))

    def max(self, a: V, b) -> V:
        """numba's max(a, b) for floats: b > a ? b : a (ordered)."""
        b = b if isinstance(b, V) else self.splat(b, a.element)
        return self.where(b > a, b, a)

    def min(self, a: V, b) -> V:
        """numba's min(a, b) for floats: b < a ? b : a (ordered)."""
        b = b if isinstance(b, V) else self.splat(b, a.element)
        return self.where(b < a, b, a)

    def _halves(self, v: V, reduce):
        """v's lanes combined pairwise down to one scalar: lane k with lane k + half, halving."""
        value, width = v.value, self.width
        while width > 1:
            half = width // 2
            low = self.builder.shuffle_vector(value, value, ir.Constant(ir.VectorType(I32, half), list(range(half))))
            high = self.builder.shuffle_vector(value, value,
                                               ir.Constant(ir.VectorType(I32, half), list(range(half, width))))
            value = reduce(V(self, low), V(self, high)).value
            width = half
        return self.builder.extract_element(value, ir.Constant(I32, 0))

    def reduce_min(self, v: V):
        """The smallest lane of v, by numba's min taken pairwise (what survives of NaN lanes is
        not defined: callers rule NaN out otherwise)."""
        return self._halves(v, self.min)

    def reduce_max(self, v: V):
        """The largest lane of v, by numba's max taken pairwise (NaN: as ``reduce_min``)."""
        return self._halves(v, self.max)

    def reduce_sum(self, v: V):
        """The sum of v's lanes, added pairwise (lane k + lane k + half, halving)."""
        return self._halves(v, lambda a, b: a + b)

    def _unary(self, name, v: V) -> V:
        vector = v.value.type
        fn = cgutils.get_or_insert_function(self.builder.module, ir.FunctionType(vector, [vector]),
                                            f"llvm.{name}.v{self.width}{_suffix(vector.element)}")
        return V(self, self.builder.call(fn, [v.value]))

    def sqrt(self, v: V) -> V:
        return self._unary("sqrt", v)

    def fabs(self, v: V) -> V:
        return self._unary("fabs", v)

    def floor(self, v: V) -> V:
        return self._unary("floor", v)

    def copysign(self, magnitude: V, sign: V) -> V:
        vector = magnitude.value.type
        fn = cgutils.get_or_insert_function(self.builder.module, ir.FunctionType(vector, [vector, vector]),
                                            f"llvm.copysign.v{self.width}{_suffix(vector.element)}")
        return V(self, self.builder.call(fn, [magnitude.value, sign.value]))

    def to_f64(self, v: V) -> V:
        return V(self, self.builder.fpext(v.value, self.vector_type(F64)))

    def to_f32(self, v: V) -> V:
        return V(self, self.builder.fptrunc(v.value, self.vector_type(F32)))

    def to_i64(self, v: V) -> V:
        """Float to integer, truncating (numba's int() of a float)."""
        if isinstance(v.element, (ir.FloatType, ir.DoubleType)):
            return V(self, self.builder.fptosi(v.value, self.vector_type(I64)))
        if v.element == I64:
            return v
        return V(self, self.builder.sext(v.value, self.vector_type(I64)))

    def to_i32(self, v: V) -> V:
        """An i64 vector truncated to i32 (numba's store of an int64 into an int32 array)."""
        return V(self, self.builder.trunc(v.value, self.vector_type(I32)))

    def to_f32_from_int(self, v: V) -> V:
        return V(self, self.builder.sitofp(v.value, self.vector_type(F32)))

    def accumulate(self, start, n_blocks, initial: list, step) -> list:
        """Vectors carried through a loop over ``n_blocks`` (i64) blocks of WIDTH lanes from lane
        ``start`` (i64): ``step(first, values)`` gets each block's first lane (i64) and the
        current values (list of V) and returns the next ones; gives the values after the last
        block (``initial`` when there is none). The values stay vectors across blocks, so a
        caller that wants scalars reduces once at the end, not once a block (a horizontal
        reduction is several shuffles). They live in stack slots that LLVM promotes to registers."""
        b = self.builder
        slots = [cgutils.alloca_once_value(b, v.value) for v in initial]
        with cgutils.for_range(b, n_blocks) as loop:
            first = b.add(start, b.mul(loop.index, ir.Constant(I64, self.width)))
            values = step(first, [V(self, b.load(slot)) for slot in slots])
            for slot, value in zip(slots, values):
                b.store(value.value, slot)
        return [V(self, b.load(slot)) for slot in slots]

    def bitmask(self, mask: V):
        """An i64 with bit k set when lane k of ``mask`` is set."""
        return self.builder.zext(self.builder.bitcast(mask.value, ir.IntType(self.width)), I64)

    # -- memory -------------------------------------------------------------------------
    def array(self, numba_type, value):
        """The array struct of a numba array argument."""
        return self.context.make_array(numba_type)(self.context, self.builder, value)

    def index(self, numba_type, value):
        """A numba integer argument as i64."""
        return self.context.cast(self.builder, value, numba_type, types.int64)

    def _pointer(self, array, element_index, vector_type):
        return self.builder.bitcast(self.builder.gep(array.data, [element_index]), vector_type.as_pointer())

    def row(self, array, start, boolean: bool = False) -> V:
        """Elements start .. start+WIDTH-1 of a contiguous 1-D array; ``boolean``: a numba bool
        array (bytes 0/1), read as an i1 mask."""
        element = array.data.type.pointee
        value = self.builder.load(self._pointer(array, start, self.vector_type(element)), align=1)
        if boolean:
            return V(self, self.builder.icmp_unsigned("!=", value, ir.Constant(value.type, [0] * self.width)))
        return V(self, value)

    def row_start(self, array, row, column):
        """Element index of [row, column] of a C-contiguous 2-D array (i64)."""
        element = array.data.type.pointee
        size = ir.Constant(I64, self._element_size(element))
        elements = self.builder.udiv(self.builder.extract_value(array.strides, 0), size)
        return self.builder.add(self.builder.mul(ir.Constant(I64, row), elements), column)

    @staticmethod
    def _element_size(element):
        return 8 if element == F64 or element == I64 else (1 if element == I8 else 4)

    def gather(self, array, indices) -> V:
        """Per lane the element of ``array`` at ``indices`` (one per axis: an i64 vector of valid
        indices, or a Python int for all lanes; a single V for a 1-D array): one scalar load per
        lane."""
        if not isinstance(indices, (list, tuple)):
            indices = [indices]
        element = array.data.type.pointee
        size = ir.Constant(I64, self._element_size(element))
        offset = None
        for axis, index in enumerate(indices):
            stride = self.splat(self.builder.udiv(self.builder.extract_value(array.strides, axis), size))
            term = (index if isinstance(index, V) else self.splat(index, I64)) * stride
            offset = term if offset is None else offset + term
        result = ir.Constant(self.vector_type(element), ir.Undefined)
        for k in range(self.width):
            lane = ir.Constant(I32, k)
            address = self.builder.gep(array.data, [self.builder.extract_element(offset.value, lane)])
            result = self.builder.insert_element(result, self.builder.load(address), lane)
        return V(self, result)

    def gather_rows(self, array, row: V, n: int) -> list:
        """The first ``n`` elements (n at most a row's length) of row ``row`` (an i64 vector of
        valid row indices) of an array whose rows (everything past the first axis) are
        contiguous, as n vectors: element
        j of every lane's row in vector j. One n-element load per lane, then shuffles: a
        ``gather`` per element extracts the lane's index and inserts one scalar each time, three
        instructions an element (the surface pass spent three quarters of its code on them)."""
        return self._deal(self._row_pieces(array, self.row_starts(array, row), 0, n), n)

    def gather_record(self, array, starts: list, fields: dict) -> dict:
        """{name: n vectors} of fields of the lanes' rows of an f32[N, C] array with contiguous
        rows, ``starts`` being the rows' starts (``row_starts``) and ``fields`` giving each name
        its (first column, n): ``gather_rows`` of several arrays in one, each lane's row start
        computed once for all the fields, however many calls read them. A field of int32 bits
        stored in the floats comes as floats: bitcast it (``as_i32``)."""
        return {name: self._deal(self._row_pieces(array, starts, column, n), n) for name, (column, n) in fields.items()}

    def as_i32(self, v: V) -> V:
        """The bits of a float vector as int32 lanes."""
        return V(self, self.builder.bitcast(v.value, self.vector_type(I32)))

    def row_starts(self, array, row: V) -> list:
        """Each lane's element index of the start of its row ``row`` (an i64 vector of valid row
        indices) of an array: a list of WIDTH i64 values."""
        b = self.builder
        element = array.data.type.pointee
        row_elements = b.udiv(b.extract_value(array.strides, 0), ir.Constant(I64, self._element_size(element)))
        return [b.mul(b.extract_element(row.value, ir.Constant(I32, k)), row_elements) for k in range(self.width)]

    def _row_pieces(self, array, starts: list, column: int, n: int) -> list:
        """Per lane the n elements from ``column`` of its row: one <n> load each."""
        b = self.builder
        piece = ir.VectorType(array.data.type.pointee, n)
        return [b.load(self._pointer(array, b.add(start, ir.Constant(I64, column)), piece), align=4)
                for start in starts]

    def _deal(self, pieces: list, n: int) -> list:
        """The lanes' <n> pieces as n vectors (element j of every lane's piece in vector j):
        concatenated pairwise into one <width * n> block, then dealt out by shuffles."""
        b = self.builder
        while len(pieces) > 1:
            size = pieces[0].type.count
            both = ir.Constant(ir.VectorType(I32, 2 * size), list(range(2 * size)))
            pieces = [b.shuffle_vector(pieces[i], pieces[i + 1], both) for i in range(0, len(pieces), 2)]
        block = pieces[0]
        undefined = ir.Constant(block.type, ir.Undefined)
        return [V(self, b.shuffle_vector(block, undefined,
                                         ir.Constant(self.vector_type(I32), [n * k + j for k in range(self.width)])))
                for j in range(n)]

    def choose(self, flag, then_values, else_values) -> list:
        """Run ``then_values()`` or ``else_values()`` (each returning a list of V) as the scalar
        i1 ``flag`` says, in a real branch (so a side may read what the other may not, such as
        an empty array), and give the chosen list."""
        b = self.builder
        with b.if_else(flag) as (then, otherwise):
            with then:
                a = then_values()
                then_block = b.block
            with otherwise:
                c = else_values()
                else_block = b.block
        merged = []
        for x, y in zip(a, c):
            phi = b.phi(x.value.type)
            phi.add_incoming(x.value, then_block)
            phi.add_incoming(y.value, else_block)
            merged.append(V(self, phi))
        return merged

    def rows3(self, array, start):
        """The x, y, z vectors of rows start .. start+WIDTH-1 of an f32[R,3] array whose rows are
        12 contiguous bytes."""
        w = self.width
        block_type = ir.VectorType(array.data.type.pointee, 3 * w)
        first = self.builder.mul(start, ir.Constant(I64, 3))
        block = self.builder.load(self._pointer(array, first, block_type), align=4)
        undefined = ir.Constant(block_type, ir.Undefined)
        return tuple(V(self, self.builder.shuffle_vector(block, undefined,
                                                         ir.Constant(self.vector_type(I32), [3 * k + a for k in range(w)])))
                     for a in range(3))

    def _masked_store(self, value, pointer, mask):
        vector = value.type
        fn = cgutils.get_or_insert_function(
            self.builder.module,
            ir.FunctionType(ir.VoidType(), [vector, pointer.type, I32, mask.type]),
            f"llvm.masked.store.v{vector.count}{_suffix(vector.element)}.p0v{vector.count}{_suffix(vector.element)}")
        self.builder.call(fn, [value, pointer, ir.Constant(I32, 4), mask])

    def store_at(self, array, element_index, v: V):
        """Store v at elements element_index .. +WIDTH-1 of the array's data (contiguous)."""
        self.builder.store(v.value, self._pointer(array, element_index, v.value.type), align=4)

    def store_row(self, array, start, v: V, mask: V | None = None):
        """Store v into elements start .. start+WIDTH-1 of a contiguous 1-D array (booleans as
        0/1 bytes); with ``mask``, only the lanes it sets."""
        element = array.data.type.pointee
        value = v.value
        if value.type.element == I1:
            value = self.builder.zext(value, self.vector_type(element))
        pointer = self._pointer(array, start, self.vector_type(element))
        if mask is None:
            self.builder.store(value, pointer, align=1)
        else:
            self._masked_store(value, pointer, mask.value)

    def store_rows3(self, array, start, xyz, mask: V | None = None):
        """Store the x, y, z vectors into rows start .. start+WIDTH-1 of an f32[R,3] array with
        12-byte rows; with ``mask``, only the rows of the lanes it sets (the others are read and
        written back unchanged: no other thread may write these rows meanwhile)."""
        w = self.width
        b = self.builder
        pair_type = self.vector_type(F32)
        xy = b.shuffle_vector(xyz[0].value, xyz[1].value, ir.Constant(ir.VectorType(I32, 2 * w), list(range(2 * w))))
        z_wide = b.shuffle_vector(xyz[2].value, ir.Constant(pair_type, ir.Undefined),
                                  ir.Constant(ir.VectorType(I32, 2 * w), list(range(w)) + [w] * w))
        # xy holds x0..x7 y0..y7; z_wide holds z0..z7 then padding: interleave x_k y_k z_k.
        order = []
        for k in range(w):
            order += [k, w + k, 2 * w + k]
        block = b.shuffle_vector(xy, z_wide, ir.Constant(ir.VectorType(I32, 3 * w), order))
        pointer = self._pointer(array, b.mul(start, ir.Constant(I64, 3)), ir.VectorType(F32, 3 * w))
        if mask is None:
            b.store(block, pointer, align=4)
            return
        # Read, select, write: a masked store of 24 floats is split by LLVM into per-element
        # branches (gather_and_spawn 15 -> 50 ms). The rows belong to the caller's thread.
        triple = b.shuffle_vector(mask.value, ir.Constant(mask.value.type, ir.Undefined),
                                  ir.Constant(ir.VectorType(I32, 3 * w), [k // 3 for k in range(3 * w)]))
        b.store(b.select(triple, block, b.load(pointer, align=4)), pointer, align=4)


def check_arguments(names, values, scalars=None) -> None:
    """An intrinsic's typing check: each value is a numba array, except those whose name
    ``scalars`` maps to a numba type class (``types.Integer``, ``types.Float``,
    ``types.Boolean``); a TypingError names the first that is not."""
    scalars = scalars or {}
    for name, value in zip(names, values):
        expected = scalars.get(name, types.Array)
        if not isinstance(value, expected):
            what = {types.Array: "an array", types.Integer: "an integer", types.Float: "a float",
                    types.Boolean: "a boolean"}.get(expected, expected.__name__)
            raise TypingError(f"{name} must be {what}, got {value}")


@njit(cache=True, inline="always")
def rows_of_three(a):
    """Whether f32[R,3] ``a`` has rows of 12 contiguous bytes (what ``Lanes.rows3`` reads)."""
    return a.shape[1] == 3 and a.strides[1] == 4 and a.strides[0] == 12


@njit(cache=True, inline="always")
def rows_contiguous(a):
    """Whether each row of ``a`` (everything past its first axis) is contiguous in C order, as
    ``Lanes.gather_rows`` reads it (the rows themselves may lie any distance apart)."""
    expected = a.itemsize
    for axis in range(a.ndim - 1, 0, -1):
        if a.strides[axis] != expected:
            return False
        expected *= a.shape[axis]
    return True


@njit(cache=True, inline="always")
def bit_count8(mask):
    """How many of the low eight bits of ``mask`` are set."""
    count = 0
    for k in range(8):
        count += (mask >> k) & 1
    return count
