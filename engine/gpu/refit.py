"""Refit on the device: the uploaded tree's boxes recomputed from the moved triangles already in
device memory, for an animation's next frame (same topology, so the same node links and
primitive order).

The same computation as ``engine.core.bvh_refit`` (which the CPU frame uses), level by level
from the deepest: a leaf takes the bounds of its triangles' corners, an inner node the union of
its two children; then every box is widened by the builder's pad, ``BOX_PAD_SCALE`` times the
largest |coordinate| of any corner. Minima and maxima are exact in float32, so the device's boxes
equal the CPU refit's bit for bit (tested), whatever the thread order. The result is written in
the device layout (``DeviceBVH``: both children's boxes in the parent's row, the corners in leaf
order), so nothing crosses the bus but the moved triangles themselves.
"""
from __future__ import annotations

import numpy as np

from engine.core.bvh import BOX_PAD_SCALE
from engine.core.bvh_refit import refit_levels
from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.scene_upload import upload

cuda = require_cuda()


@cuda.jit
def _corners_and_largest(vec, prim, leaf_tris, largest):
    """leaf_tris[k, i] = corner k of triangle prim[i]; largest[0] = max |coordinate| (atomic)."""
    i = cuda.grid(1)
    if i >= prim.shape[0]:
        return
    p = prim[i]
    m = np.float32(0.0)
    for k in range(3):
        for a in range(3):
            x = vec[k, p, a]
            leaf_tris[k, i, a] = x
            m = max(m, abs(x))
    cuda.atomic.max(largest, 0, m)


@cuda.jit
def _level(level_nodes, start, end, links, leaf_tris, boxes):
    """Unpadded boxes (f32[N,6]: min xyz, max xyz) of the nodes level_nodes[start:end]."""
    j = start + cuda.grid(1)
    if j >= end:
        return
    node = level_nodes[j]
    first, n_prims = links[node, 0], links[node, 1]
    for a in range(3):
        if n_prims > 0:
            lo = np.float32(np.inf)
            hi = np.float32(-np.inf)
            for i in range(first, first + n_prims):
                lo = min(lo, leaf_tris[0, i, a], leaf_tris[1, i, a], leaf_tris[2, i, a])
                hi = max(hi, leaf_tris[0, i, a], leaf_tris[1, i, a], leaf_tris[2, i, a])
        else:
            lo = min(boxes[first, a], boxes[first + 1, a])
            hi = max(boxes[first, 3 + a], boxes[first + 1, 3 + a])
        boxes[node, a] = lo
        boxes[node, 3 + a] = hi


@cuda.jit
def _padded_table(boxes, links, largest, child_boxes, root_row):
    """The padded children's boxes of every inner node into its row, and the padded root."""
    node = cuda.grid(1)
    if node >= links.shape[0]:
        return
    pad = BOX_PAD_SCALE * largest[0]
    if node == 0:
        for a in range(3):
            root_row[0, a] = boxes[0, a] - pad
            root_row[0, 3 + a] = boxes[0, 3 + a] + pad
    if links[node, 1] > 0:
        return
    first = links[node, 0]
    for side in range(2):
        for a in range(3):
            child_boxes[node, 6 * side + a] = boxes[first + side, a] - pad
            child_boxes[node, 6 * side + 3 + a] = boxes[first + side, 3 + a] + pad


class DeviceRefit:
    """Refits one uploaded ``DeviceBVH`` (its topology fixed) from ``DeviceTriangles``."""

    def __init__(self, host_bvh, device_bvh):
        level_start, level_nodes = refit_levels(host_bvh.first, host_bvh.count)
        self.level_start = [int(x) for x in level_start]
        self.level_nodes = upload(level_nodes)
        self.bvh = device_bvh
        self.boxes = cuda.device_array((host_bvh.first.shape[0], 6), np.float32)
        self.largest = cuda.device_array(1, np.float32)

    def refit(self, device_tris) -> None:
        """Recompute the uploaded tree's boxes and leaf-order corners for ``device_tris``."""
        b = self.bvh
        self.largest.copy_to_device(np.zeros(1, np.float32))
        n_prim = b.prim.shape[0]
        _corners_and_largest[blocks(n_prim), BLOCK](device_tris.vec, b.prim, b.leaf_tris, self.largest)
        for level in range(len(self.level_start) - 2, -1, -1):
            start, end = self.level_start[level], self.level_start[level + 1]
            _level[blocks(end - start), BLOCK](self.level_nodes, start, end, b.links, b.leaf_tris, self.boxes)
        _padded_table[blocks(self.boxes.shape[0]), BLOCK](self.boxes, b.links, self.largest, b.child_boxes,
                                                          b.root_row)
