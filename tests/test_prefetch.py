"""``engine.core.prefetch``: ``prefetch_row`` is three cache-line prefetches of an array's row and
``prefetch_node`` four, with no effect on any value; the per-ray walk issues them for the children
it pushes."""
import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from engine.core.prefetch import LINES, NODE_LINES, prefetch_node, prefetch_row
from engine.query.walk import CLOSEST, new_stack, walk


def prefetch_every_row(rows):
    total = 0.0
    for r in range(rows.shape[0]):
        prefetch_row(rows, r)
        total += rows[r].ravel()[0]
    return total


def test_prefetch_changes_nothing_and_emits_three_prefetches_a_row():
    rows = np.arange(10 * 48, dtype=np.float32).reshape(10, 6, 8)
    before = rows.copy()
    fresh = njit(prefetch_every_row)
    assert fresh(rows) == pytest.approx(float(rows.reshape(10, -1)[:, 0].sum()))
    np.testing.assert_array_equal(rows, before)
    llvm = fresh.inspect_llvm(fresh.signatures[0])
    assert llvm.count("call void @llvm.prefetch") == LINES


def prefetch_one_node(rows, r):
    prefetch_node(rows, r)
    return rows[r, 0, 0]


def test_prefetch_node_changes_nothing_and_emits_four_prefetches():
    rows = np.arange(10 * 64, dtype=np.float32).reshape(10, 8, 8)
    before = rows.copy()
    fresh = njit(prefetch_one_node)
    assert [fresh(rows, r) for r in range(10)] == list(rows[:, 0, 0])
    np.testing.assert_array_equal(rows, before)
    assert fresh.inspect_llvm(fresh.signatures[0]).count("call void @llvm.prefetch") == NODE_LINES


def test_prefetch_refuses_a_strided_view():
    rows = np.zeros((10, 48), np.float32)
    with pytest.raises(TypingError, match="C-contiguous"):
        njit(prefetch_every_row)(rows[::2])


def one_walk(nodes, node_bits, block_tri, blocks):
    stack, stack_t, entries, answers = new_stack()
    empty_t, empty_i = np.empty(0, np.float32), np.empty(0, np.int32)
    return walk(nodes, node_bits, block_tri, blocks, np.float32(0), np.float32(0), np.float32(-2),
                np.float32(0), np.float32(0), np.float32(1), np.float32(0), np.float32(np.inf), CLOSEST, stack, stack_t,
                entries, answers, empty_t, empty_i, empty_t, empty_t, 0)


def test_the_walk_prefetches_the_rows_of_the_children_it_pushes():
    """A pushed inner node (NODE_LINES lines, the last at byte 192 of its row) or a pushed leaf's
    block (LINES): LLVM may sink the two branches' last prefetch into one call on a selected
    address, so the count is at least NODE_LINES."""
    import trimesh
    from engine.query.intersector import RayMeshIntersector
    s = RayMeshIntersector(trimesh.creation.icosphere(subdivisions=2))._structure()
    fresh = njit(one_walk)
    hit, t, tri, _, _ = fresh(s.nodes, s.node_bits, s.block_tri, s.blocks)
    assert hit == 1 and t == pytest.approx(1.5, abs=0.01)
    llvm = fresh.inspect_llvm(fresh.signatures[0])
    assert llvm.count("call void @llvm.prefetch") >= NODE_LINES
    assert f"i64 {(NODE_LINES - 1) * 64}" in llvm
