"""``engine.query.wide.pack_nodes``: the 8-wide tree's boxes, children and sizes in one row per
node, each node four whole cache lines."""
from __future__ import annotations

import numpy as np
import pytest

from engine.core.bvh import build_bvh
from engine.query.wide import CHILD_ROW, SIZE_ROW, collapse, pack_nodes
from scenes.catalog import load_named


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_packed_nodes_hold_the_boxes_children_and_sizes_on_cache_lines(leaf_size):
    tris = load_named("whitted", {"checks": 4, "subdivisions": 1}).triangles
    bvh = build_bvh(tris, leaf_size=leaf_size)
    box, child, size = collapse(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    for _ in range(4):  # numpy hands out buffers at 16-byte offsets: every try starts on a line
        nodes = pack_nodes(box, child, size)
        assert nodes.shape == (len(box), 8, 8) and nodes.dtype == np.float32 and nodes.flags.c_contiguous
        assert nodes.ctypes.data % 64 == 0 and nodes.strides[0] == 256
        bits = nodes.view(np.int32)
        np.testing.assert_array_equal(nodes[:, :6, :].view(np.uint32), box.view(np.uint32))  # NaN slots too
        np.testing.assert_array_equal(bits[:, CHILD_ROW, :], child)
        np.testing.assert_array_equal(bits[:, SIZE_ROW, :], size)
