"""engine.render.spawn.gather_and_spawn: the eight-lane children step (``engine.render.spawn8``)
writes the bits of the lane-by-lane ``spawn_lane``, which runs where rows are not 12 contiguous
bytes, in every row the latter writes; and the light lands in the image in lane order either
way."""
from __future__ import annotations

import numpy as np
import pytest

from engine.render.spawn import CHILDREN_FIELDS, gather_and_spawn

R = 1000
#: Packets of 256, 4, 8, 252 and 480 lanes: blocks of eight and tails of four.
OFFSETS = np.array([0, 256, 260, 268, 520, 1000], np.int32)


def unit(v):
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def shading_lanes(seed):
    """Per-lane Surface rows and materials: mirrors, glass (entering and leaving, with total
    internal reflection), diffuse, weights under the cut-off, lanes without a hit."""
    rng = np.random.default_rng(seed)
    view = unit(rng.normal(size=(R, 3)))
    facing = unit(rng.normal(size=(R, 3)))
    facing = np.where((np.einsum("ij,ij->i", facing, view) > 0)[:, None], -facing, facing).astype(np.float32)
    lanes = {
        "pixel": rng.permutation(R).astype(np.int32),
        "weight": rng.uniform(0, 1, (R, 3)).astype(np.float32) * np.where(np.arange(R) % 10 == 0, 1e-4, 1)[:, None]
        .astype(np.float32),
        "hit": rng.random(R) < 0.85,
        "point": rng.normal(size=(R, 3)).astype(np.float32),
        "magnitude": np.abs(rng.normal(size=R)).astype(np.float32),
        "view": view,
        "normal": unit(facing + 0.4 * rng.normal(size=(R, 3))),
        "facing": facing,
        "entering": rng.random(R) < 0.5,
        "material": rng.integers(0, 4, R).astype(np.int32),
        "color": rng.uniform(0, 1, (R, 3)).astype(np.float32),
    }
    materials = (np.array([[0, 0, 0], [0.9, 0.9, 0.9], [0.1, 0.2, 0.3], [0, 0, 5e-4]], np.float32),
                 np.array([0, 0, 0.8, 0.9], np.float32), np.array([1, 1.5, 1.33, 2.4], np.float32))
    return lanes, materials


def run(lanes, materials, spawn, reflect, wide):
    """The image and the Children arrays (pre-filled, to see which rows are written); ``wide``
    False: every f32[R,3] array a view of an f32[R,4] block, so the lane-by-lane step runs."""
    def rows(a):
        if wide or a.ndim == 1:
            return a
        block = np.zeros((a.shape[0], 4), a.dtype)
        block[:, :3] = a
        return block[:, :3]

    children = []
    for tail, dtype in CHILDREN_FIELDS.values():
        children.append(rows(np.full((R,) + tail, True if dtype == np.bool_ else 7, dtype)))
    image = np.zeros((R, 3), np.float32)
    args = [rows(lanes[k]) for k in ("pixel", "weight", "hit", "point", "magnitude", "view", "normal", "facing",
                                     "entering", "material", "color")]
    gather_and_spawn(OFFSETS, *args, *materials, image, spawn, reflect, *children)
    return image, [np.ascontiguousarray(c) for c in children]


@pytest.mark.parametrize("spawn, reflect", [(True, True), (True, False), (False, True)])
def test_eight_lane_children_are_the_lane_by_lane_ones(spawn, reflect):
    lanes, materials = shading_lanes(2)
    image_8, children_8 = run(lanes, materials, spawn, reflect, wide=True)
    image_1, children_1 = run(lanes, materials, spawn, reflect, wide=False)
    assert np.array_equal(image_8, image_1)
    got, want = dict(zip(CHILDREN_FIELDS, children_8)), dict(zip(CHILDREN_FIELDS, children_1))
    hit = lanes["hit"]
    # The flags of every lane; each row where a child reads it (``Children``: a row means
    # something only where its flag is set, and the eight-lane step skips blocks that cast none).
    written = {"mirror": np.ones(R, bool), "total_internal": np.ones(R, bool), "refract": np.ones(R, bool),
               "reflect_dir": want["mirror"] | want["total_internal"], "reflect_weight": want["mirror"],
               "transmit_weight": want["total_internal"] | want["refract"],
               "refract_dir": want["refract"], "enter": want["refract"]}
    for name, rows in written.items():
        if spawn or name in ("mirror", "total_internal", "refract"):
            assert np.array_equal(got[name][rows].view(np.uint8), want[name][rows].view(np.uint8)), name
    mirror, total_internal, refract = children_8[:3]
    if spawn:  # the cases the lanes were made for all occur
        assert refract.sum() > 100 and total_internal.sum() > 50 and (mirror.sum() > 100) == reflect
    else:
        assert not (mirror.any() or total_internal.any() or refract.any())
    # Light in the image: weight x colour on every hit lane.
    expected = np.zeros((R, 3), np.float32)
    hit = lanes["hit"]
    expected[lanes["pixel"][hit]] = lanes["weight"][hit] * lanes["color"][hit]
    assert np.array_equal(image_8, expected)
