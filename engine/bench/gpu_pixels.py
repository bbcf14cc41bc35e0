"""Why a pixel of the GPU image differs from the CPU image: the first ray of that pixel whose
answer differs between the two renders.

``PixelRecorder`` is a renderer observer (optionally passing every batch on to another, such as
the audit's) that keeps, per ray kind, each ray's pixel, origin, direction and answer (closest
hit's triangle and t, or occlusion). ``explain(pixels, cpu, gpu)`` compares the two records
pixel by pixel, in ray-kind order, and names the first difference.
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np

KIND_ORDER = ("primary", "shadow", "reflection", "refraction")


class PixelRecorder:
    """Observer keeping {kind: [(pixel i32[R], org f32[R,3], dir f32[R,3], prim i32[R] | None,
    t f32[R] | None, occluded bool[R] | None)]} of the live rays of every cast batch."""

    def __init__(self, forward=None):
        self.forward = forward
        self.batches = defaultdict(list)

    def __call__(self, kind, query, rays, packets, answer):
        if self.forward is not None:
            self.forward(kind, query, rays, packets, answer)
        # Cast rays only: a shadow batch walked in its parent's lanes keeps dead lanes on pixels.
        live = (rays.pixel >= 0) & (rays.tmin <= rays.tmax)
        if query == "intersect":
            record = (rays.pixel[live], rays.org[live], rays.dir[live], answer.prim[live], answer.t[live], None)
        else:
            record = (rays.pixel[live], rays.org[live], rays.dir[live], None, None, np.asarray(answer)[live])
        self.batches[kind].append(tuple(np.array(a, copy=True) if a is not None else None for a in record))

    def by_pixel(self, pixels: set) -> dict:
        """{pixel: {kind: sorted list of ray tuples}} for the given pixels only."""
        out = defaultdict(lambda: defaultdict(list))
        wanted = np.array(sorted(pixels), np.int64)
        for kind, records in self.batches.items():
            for pixel, org, dirs, prim, t, occluded in records:
                for i in np.flatnonzero(np.isin(pixel, wanted)):
                    ray = (tuple(org[i].tolist()), tuple(dirs[i].tolist()))
                    answer = (int(prim[i]), float(t[i])) if prim is not None else bool(occluded[i])
                    out[int(pixel[i])][kind].append((ray, answer))
        for kinds in out.values():
            for rays in kinds.values():
                rays.sort(key=repr)
        return out


def explain(pixels: list, width: int, cpu: PixelRecorder, gpu: PixelRecorder) -> dict:
    """{pixel index: reason} for pixels given as (x, y) pairs: the first ray kind whose rays or
    answers differ between the CPU and GPU renders, else that the rays all agree (the difference
    is in the shading arithmetic or the order a pixel's contributions were summed)."""
    keys = {y * width + x for x, y in pixels}
    a, b = cpu.by_pixel(keys), gpu.by_pixel(keys)
    reasons = {}
    for key in keys:
        reasons[key] = "same rays and answers: shading arithmetic or summation order"
        for kind in KIND_ORDER:
            ra, rb = a[key][kind], b[key][kind]
            if [r for r, _ in ra] != [r for r, _ in rb]:
                reasons[key] = f"{kind} rays differ (origin or direction; {len(ra)} on the CPU, {len(rb)} on the GPU)"
                break
            if [ans for _, ans in ra] != [ans for _, ans in rb]:
                diff = next((x, y) for x, y in zip(ra, rb) if x[1] != y[1])
                reasons[key] = f"{kind} answers differ on the same ray: CPU {diff[0][1]}, GPU {diff[1][1]}"
                break
    return reasons
