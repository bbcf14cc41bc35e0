"""engine.render.surface.shade_surface: the eight-lane surface step (``engine.render.surface8``)
writes the bits of the lane-by-lane ``fill_surface_lane`` (which runs where rows are not 12
contiguous bytes) in every row a Surface defines: hit points, offsets, normals (interpolated,
degenerate, absent), materials and texel rows (texture coordinates inside and outside [0, 1),
untextured materials, no UVs)."""
from __future__ import annotations

import numpy as np
import pytest

from engine.render.surface import SURFACE_FIELDS, eight_lanes_fit, new_surface, shade_surface
from engine.render.surface_record import RECORD_FIELDS, RECORD_WIDTH, surface_records

R = 1000
T = 50
#: Packets of 256, 4, 8, 252 and 480 lanes: blocks of eight and tails of four.
OFFSETS = np.array([0, 256, 260, 268, 520, 1000], np.int32)


def scene_and_hits(seed, with_normals, with_uvs):
    rng = np.random.default_rng(seed)
    corners = (rng.normal(size=(T, 3, 3)) * 5).astype(np.float32)
    normals = rng.normal(size=(T, 3, 3)).astype(np.float32) if with_normals else np.zeros((0, 3, 3), np.float32)
    if with_normals:
        normals[3] = 0.0  # degenerate: the geometric normal stands in
    uvs = (rng.normal(size=(T, 3, 2)) * 2).astype(np.float32) if with_uvs else np.zeros((0, 3, 2), np.float32)
    material = rng.integers(0, 3, T).astype(np.int32)
    if with_uvs:
        # Texture coordinates at the wrap's edges (``texel_at``): just below 0, exactly 1.
        tiny = np.float32(2.0 ** -30)
        uvs[5, 0] = (-tiny, tiny)   # s wraps up to 1.0 (column = width: wraps to 0), 1 - t rounds to 1.0
        uvs[6, 0] = (1.0, 1.0)
        material[5] = material[6] = 1
    return rng, corners, normals, uvs, material


def padded_rows(a):
    """``a`` as a view whose rows lie 8 bytes apart from each other (contiguous rows)."""
    block = np.zeros((a.shape[0], a[0].size + 2), a.dtype)
    block[:, :a[0].size] = a.reshape(a.shape[0], -1)
    return block[:, :a[0].size].reshape(a.shape)


def scattered_elements(a):
    """``a`` as a view whose rows are not contiguous (every element 8 bytes from the next)."""
    block = np.zeros(a.shape + (2,), a.dtype)
    block[..., 0] = a
    return block[..., 0]


def run(seed, with_normals, with_uvs, wide, triangle_rows=np.ascontiguousarray, records=None):
    """(image, {Surface field: array}) of one shade_surface call; ``records``: a function of the
    triangle arrays giving the surface records to pass (default ``surface_records``)."""
    rng, corners, normals, uvs, material = scene_and_hits(seed, with_normals, with_uvs)
    v0, v1, v2 = (np.ascontiguousarray(corners[:, k]) for k in range(3))
    ng = np.cross(v1 - v0, v2 - v0)
    ng = (ng / np.linalg.norm(ng, axis=1, keepdims=True)).astype(np.float32)
    v0, v1, v2, ng, normals, uvs = (triangle_rows(a) for a in (v0, v1, v2, ng, normals, uvs))
    corner_magnitude = np.abs(corners).max(axis=(1, 2)).astype(np.float32)
    dirs = rng.normal(size=(R, 3)).astype(np.float32)
    pixel = rng.permutation(R).astype(np.int32)
    pixel[::37] = -1  # padding lanes
    weight = rng.uniform(0, 1, (R, 3)).astype(np.float32)
    prim = rng.integers(-1, T, R).astype(np.int32)  # -1: a miss
    u = rng.uniform(0, 1, R).astype(np.float32)
    v = (rng.uniform(0, 1, R) * (1 - u)).astype(np.float32)
    prim[:16] = np.where(np.arange(16) % 2 == 0, 5, 6)  # at corner 0 (u = v = 0) of the edge cases
    u[:16] = v[:16] = 0.0
    pixel[:16] = np.abs(pixel[:16])
    ambient = rng.uniform(0, 1, (3, 3)).astype(np.float32)
    texture_layout = np.array([[-1, 0, 12], [0, 3, 5], [0, 4, 2]], np.int64)  # untextured, 3x4, 5x2
    texels = rng.integers(0, 256, (22, 3)).astype(np.uint8)
    palette = np.linspace(0, 1, 256).astype(np.float32)
    ambient_light = np.array([0.2, 0.3, 0.4], np.float32)
    background = np.array([0.5, 0.6, 0.7], np.float32)
    image = np.zeros((R, 3), np.float32)

    def rows(a):
        if wide or a.ndim != 2 or a.shape[1] != 3:
            return a
        block = np.zeros((a.shape[0], 4), a.dtype)
        block[:, :3] = a
        return block[:, :3]

    make_records = records or surface_records
    surface = new_surface(R, lambda name, r, tail, dtype: rows(np.full((r,) + tail, 3, dtype)))
    shade_surface(OFFSETS, rows(dirs), pixel, rows(weight), prim, u, v, v0, v1, v2, ng, normals, uvs, material,
                  corner_magnitude, make_records(v0, v1, v2, ng, normals, uvs, material, corner_magnitude),
                  ambient, texture_layout, texels, palette, ambient_light, background, image, *surface)
    return image, {name: np.ascontiguousarray(a) for name, a in zip(SURFACE_FIELDS, surface)}


def assert_same_surface(expected, got):
    """Two ``run`` results (image, surface) equal bit for bit: the image, ``hit`` and ``leave`` on
    every lane, the other rows where a Surface defines them (hit lanes)."""
    (image_1, surface_1), (image_2, surface_2) = expected, got
    assert np.array_equal(image_2, image_1)
    hit = surface_1["hit"]
    for name in SURFACE_FIELDS:
        rows = slice(None) if name in ("hit", "leave") else hit
        assert np.array_equal(surface_2[name][rows].view(np.uint8), surface_1[name][rows].view(np.uint8)), name


@pytest.mark.parametrize("with_normals, with_uvs", [(True, True), (False, True), (True, False), (False, False)])
def test_eight_lane_surface_is_the_lane_by_lane_one(with_normals, with_uvs):
    image_8, surface_8 = run(7, with_normals, with_uvs, wide=True)
    lane_by_lane = run(7, with_normals, with_uvs, wide=False)
    assert_same_surface(lane_by_lane, (image_8, surface_8))
    hit = lane_by_lane[1]["hit"]
    assert 0.8 < hit.mean() < 0.99
    rows = surface_8["texel_row"][hit]
    if with_uvs:  # textured and untextured lanes both occur, every row inside its texture
        assert (rows == -1).any() and (rows >= 0).any() and rows.max() < 22
    else:
        assert (rows == -1).all()
    assert (surface_8["leave"][~hit] == 0).all()


@pytest.mark.parametrize("triangle_rows", [padded_rows, scattered_elements])
def test_triangle_rows_apart_or_scattered_give_the_same_surface(triangle_rows):
    # The eight-lane step reads the triangles' surface records, made from the arrays whatever
    # their strides; the lane-by-lane tail reads the arrays at their own strides. Both give the
    # contiguous arrays' answer.
    assert_same_surface(run(7, True, True, wide=True), run(7, True, True, wide=True, triangle_rows=triangle_rows))


#: Catalogue scenes read from the shared scene folder (the others are procedural).
SCENES_FROM_FILES = {"cornell-box", "bunny-floor"}


@pytest.mark.parametrize("name", ["whitted", "cornell-box", "erw6", "bunny-floor"])
def test_scenes_without_corner_normals_or_uvs_take_the_eight_lane_step(name):
    """The default scene has no uvs, the Cornell box, ERW6 and the bunny floor neither corner
    normals nor uvs: arrays of shape (0, 3, k), whose strides numpy gives as 0. They are never
    read, and must not send the surface pass lane by lane and serial (as they did until session
    20: ERW6's pass took 17.8 ms a 1024x1024 frame instead of 5.8). Rows that are not 12
    contiguous bytes still do."""
    from conftest import needs_shared_scenes
    from scenes.catalog import load_named

    if name in SCENES_FROM_FILES:
        needs_shared_scenes()
    tris = load_named(name).triangles
    assert tris.normals.shape[0] == 0 or tris.uvs.shape[0] == 0
    lanes = new_surface(64)
    dirs = np.zeros((64, 3), np.float32)
    records = surface_records(tris.v0, tris.v1, tris.v2, tris.ng, tris.normals, tris.uvs, tris.material,
                              np.ones(len(tris.v0), np.float32))
    args = (records, len(tris.v0))
    assert eight_lanes_fit(dirs, lanes.point, lanes.view, lanes.normal, lanes.facing, lanes.leave, *args)
    apart = np.zeros((64, 4), np.float32)[:, :3]
    assert not eight_lanes_fit(apart, lanes.point, lanes.view, lanes.normal, lanes.facing, lanes.leave, *args)


def test_a_surface_record_holds_its_triangle_s_arrays():
    """Each field of a triangle's record (``RECORD_FIELDS``) is its row of the array it comes
    from, bit for bit; the material as int32 bits; absent corner normals and uvs as zeros."""
    _, corners, normals, uvs, material = scene_and_hits(3, True, True)
    v0, v1, v2 = (np.ascontiguousarray(corners[:, k]) for k in range(3))
    ng = np.ascontiguousarray(corners[:, 0] * 0.5)
    magnitude = np.abs(corners).max(axis=(1, 2)).astype(np.float32)
    records = surface_records(v0, v1, v2, ng, normals, uvs, material, magnitude)
    assert records.shape == (T, RECORD_WIDTH) and records.dtype == np.float32

    def field(name):
        first, n = RECORD_FIELDS[name]
        return records[:, first:first + n]

    for name, source in (("v0", v0), ("v1", v1), ("v2", v2), ("ng", ng), ("normals", normals), ("uvs", uvs),
                         ("magnitude", magnitude)):
        assert np.array_equal(field(name).view(np.uint32), source.reshape(T, -1).view(np.uint32)), name
    assert np.array_equal(field("material").view(np.int32)[:, 0], material)
    bare = surface_records(v0, v1, v2, ng, np.zeros((0, 3, 3), np.float32), np.zeros((0, 3, 2), np.float32),
                           material, magnitude)
    assert (bare[:, 12:27] == 0).all()  # no corner normals, no uvs: zeros
    with pytest.raises(ValueError, match="v2"):
        surface_records(v0, v1, v2[:-1], ng, normals, uvs, material, magnitude)
    with pytest.raises(ValueError, match="normals"):
        surface_records(v0, v1, v2, ng, normals[:-1], uvs, material, magnitude)


@pytest.mark.parametrize("bad_records", [
    lambda *arrays: surface_records(*arrays)[:-1],                           # one triangle short
    lambda *arrays: np.repeat(surface_records(*arrays), 2, axis=1)[:, ::2],  # rows not contiguous
])
def test_records_that_do_not_fit_the_triangles_send_the_pass_lane_by_lane(bad_records):
    # Records of other triangles, or in rows the step cannot load whole, are never read: the
    # pass goes lane by lane over the triangle arrays and gives the same surface.
    assert_same_surface(run(7, True, True, wide=True), run(7, True, True, wide=True, records=bad_records))
