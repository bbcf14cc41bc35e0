"""Exclusive prefix sums on the device: the stable compaction of every wavefront queue.

``exclusive_scan(values, n, out)`` writes out[i] = values[0] + ... + values[i-1] for i < n and
out[n] = the total, in three launches: each block scans its BLOCK items in shared memory and
keeps its sum; one block scans the block sums (looping over them); every item adds its block's
offset. A stream compacted through it keeps its order: the ray-space hierarchy's pixel-block
sort uses it (``engine.gpu.rayspace.hierarchy``). Where order does not matter, appending by an
atomic counter needs no scan: the frame's queues (``engine.gpu.frame``) and the ray-space
(node, triangle) streams (``engine.gpu.rayspace.stream``, one atomic per block over
``inclusive_in_block``).
"""
from __future__ import annotations

import numpy as np

from engine.gpu.device import BLOCK, blocks, require_cuda

cuda = require_cuda()


@cuda.jit(device=True)
def inclusive_in_block(shared, t):
    """shared[0:BLOCK] replaced by its inclusive prefix sums (Hillis-Steele: BLOCK is small,
    log2(BLOCK) steps); every thread of the block calls it with its index t."""
    step = 1
    while step < BLOCK:
        y = shared[t - step] if t >= step else 0
        cuda.syncthreads()
        shared[t] += y
        cuda.syncthreads()
        step *= 2


@cuda.jit
def _scan_blocks(values, n, out, block_sums):
    """Per block: out[i] = exclusive sum within the block; block_sums[b] = the block's total."""
    shared = cuda.shared.array(BLOCK, np.int32)
    t = cuda.threadIdx.x
    i = cuda.blockIdx.x * BLOCK + t
    x = values[i] if i < n else 0
    shared[t] = x
    cuda.syncthreads()
    inclusive_in_block(shared, t)
    if i < n:
        out[i] = shared[t] - x
    if t == BLOCK - 1:
        block_sums[cuda.blockIdx.x] = shared[t]


@cuda.jit
def _scan_sums(block_sums, count, total_out):
    """One block: block_sums[:count] replaced by their exclusive scan, in chunks of BLOCK;
    total_out[0] = the grand total."""
    shared = cuda.shared.array(BLOCK, np.int32)
    t = cuda.threadIdx.x
    carry = 0
    start = 0
    while start < count:
        i = start + t
        x = block_sums[i] if i < count else 0
        shared[t] = x
        cuda.syncthreads()
        inclusive_in_block(shared, t)
        if i < count:
            block_sums[i] = carry + shared[t] - x
        chunk_total = shared[BLOCK - 1]
        cuda.syncthreads()
        carry += chunk_total
        start += BLOCK
    if t == 0:
        total_out[0] = carry


@cuda.jit
def _add_offsets(out, n, block_sums, total_in):
    i = cuda.grid(1)
    if i < n:
        out[i] += block_sums[i // BLOCK]
    if i == 0:
        out[n] = total_in[0]


def _ordinary_launch(kernel, blocks: int, threads: int, *args) -> None:
    kernel[blocks, threads](*args)


class Scanner:
    """Reusable scratch for exclusive scans of up to ``capacity`` items (grows on demand).

    launch: how kernels are launched, ``launch(kernel, blocks, threads, *args)`` (an
    ``engine.gpu.launch.LaunchCache``, say); by default numba's ordinary launch."""

    def __init__(self, launch=None):
        self.capacity = 0
        self.block_sums = None
        self.total = cuda.device_array(1, np.int32)
        self.launch = launch if launch is not None else _ordinary_launch

    def exclusive_scan(self, values, n: int, out) -> int:
        """out[:n+1] = exclusive prefix sums of values[:n] (i32 device arrays; out holds n+1);
        returns the total (read back: the caller sizes the next launch with it)."""
        if n <= 0:
            out[0:1].copy_to_device(np.zeros(1, np.int32))
            return 0
        nb = blocks(n)
        if self.block_sums is None or self.block_sums.shape[0] < nb:
            drop_using = getattr(self.launch, "drop_using", None)
            if drop_using is not None and self.block_sums is not None:
                drop_using([self.block_sums])  # prepared launches hold the old block sums
            self.block_sums = cuda.device_array(nb, np.int32)
        self.launch(_scan_blocks, nb, BLOCK, values, n, out, self.block_sums)
        self.launch(_scan_sums, 1, BLOCK, self.block_sums, nb, self.total)
        self.launch(_add_offsets, nb, BLOCK, out, n, self.block_sums, self.total)
        return int(self.total.copy_to_host()[0])
