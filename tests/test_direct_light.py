"""engine.render.direct_light against the numpy expressions of the shading it replaced."""
import numpy as np

from engine.core.triangle import safe_inverse
from engine.render.direct_light import SHADOW_TMAX_SCALE, add_light, add_light_in_place, light_directions


def unit(v):
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def test_light_directions_and_lit_mask():
    rng = np.random.default_rng(5)
    m = 5000
    leave = (rng.random((m, 3)) * 20 - 10).astype(np.float32)
    ns, ng = unit(rng.normal(size=(m, 3))), unit(rng.normal(size=(m, 3)))
    light = np.array([1.5, 7.0, -2.0], np.float32)
    leave[0] = light  # a hit at the light: zero distance must not divide by zero
    l, dist, ndotl, lit = np.empty_like(leave), np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, bool)
    shadow_tmax, inv = np.empty(m, np.float32), np.empty_like(leave)
    hit = rng.random(m) < 0.9
    hit[0] = True
    lit_lanes = light_directions(hit, leave, ns, ng, light, l, dist, ndotl, lit, shadow_tmax, inv)
    assert not lit[~hit].any()  # lanes without a hit cast no shadow ray
    assert lit_lanes == np.count_nonzero(lit)
    # Every lane is a ray the walk can load: unlit lanes dead, lanes without a hit along +z.
    assert np.array_equal(inv, safe_inverse(l))
    assert (shadow_tmax[~lit] == -np.inf).all() and (l[~hit] == [0, 0, 1]).all()
    assert (shadow_tmax[lit] >= 0).all()
    ns, ng, leave, l, dist, ndotl, lit, shadow_tmax = (a[hit] for a in (ns, ng, leave, l, dist, ndotl, lit, shadow_tmax))
    to = light - leave
    ref_dist = np.linalg.norm(to, axis=1)
    ref_l = to / np.maximum(ref_dist, 1e-30)[:, None]
    np.testing.assert_allclose(dist, ref_dist, rtol=1e-6)
    np.testing.assert_allclose(l, ref_l, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(ndotl, np.einsum("ij,ij->i", ns, ref_l), atol=1e-6)
    ref_lit = (np.einsum("ij,ij->i", ns, ref_l) > 0) & (np.einsum("ij,ij->i", ng, ref_l) > 0)
    assert np.array_equal(lit, ref_lit) and 0.1 < lit.mean() < 0.5
    assert np.array_equal(shadow_tmax[lit], (dist * SHADOW_TMAX_SCALE)[lit])
    assert (shadow_tmax < dist)[lit & (dist > 0)].all()
    assert dist[0] == 0 and not lit[0] and np.isfinite(l[0]).all()


def shading_lanes(rng, m, k):
    """(color f32[m,3], the rest of add_light's arguments after ``occluded``) for m random lanes
    and k materials."""
    ns, l, view = unit(rng.normal(size=(m, 3))), unit(rng.normal(size=(m, 3))), unit(rng.normal(size=(m, 3)))
    ndotl = np.einsum("ij,ij->i", ns, l).astype(np.float32)
    mat = rng.integers(0, k, m).astype(np.int32)
    diffuse, specular = rng.random((k, 3)).astype(np.float32), rng.random((k, 3)).astype(np.float32)
    shininess = (rng.random(k) * 60).astype(np.float32)
    texel = rng.random((m, 3)).astype(np.float32)
    lc = rng.random(3).astype(np.float32)
    color = rng.random((m, 3)).astype(np.float32)
    return color, (ns, l, ndotl, view, mat, diffuse, specular, shininess, texel, lc)


def _light_directions_arrays(m, padded):
    """Answer arrays for light_directions, pre-filled with 5 (to see which lanes are written);
    ``padded``: the f32[m,3] ones as views of f32[m,4] blocks (rows not 12 contiguous bytes)."""
    def rows3():
        block = np.full((m, 4 if padded else 3), 5, np.float32)
        return block[:, :3]
    return (rows3(), np.full(m, 5, np.float32), np.full(m, 5, np.float32), np.full(m, True),
            np.full(m, 5, np.float32), rows3())


def test_light_directions_eight_lanes_at_a_time_write_the_bits_of_the_lane_by_lane_loop():
    """The eight-lane step (``engine.render.light8``) against the per-lane loop, which runs where
    the rows are not 12 contiguous bytes: every array, every bit, including the lanes left alone
    (dist and ndotl without a hit), a hit at the light, NaN coordinates and a tail of 1003 % 8."""
    rng = np.random.default_rng(11)
    m = 1003
    leave = (rng.normal(size=(m, 3)) * 4).astype(np.float32)
    ns, ng = unit(rng.normal(size=(m, 3))), unit(rng.normal(size=(m, 3)))
    light = np.array([1.0, 2.0, 3.0], np.float32)
    leave[5] = light
    leave[9, 1] = np.nan
    hit = rng.random(m) < 0.8
    hit[5] = hit[9] = True
    wide = _light_directions_arrays(m, padded=False)
    narrow = _light_directions_arrays(m, padded=True)
    pad = [np.pad(a, ((0, 0), (0, 1)))[:, :3] for a in (leave, ns, ng)]
    count_wide = light_directions(hit, leave, ns, ng, light, *wide)
    count_narrow = light_directions(hit, *pad, light, *narrow)
    assert count_wide == count_narrow == np.count_nonzero(wide[3])
    for a, b in zip(wide, narrow):
        assert np.array_equal(np.ascontiguousarray(a).view(np.uint8), np.ascontiguousarray(b).view(np.uint8))
    assert (wide[1][~hit] == 5).all()  # dist is not written without a hit


def test_add_light_is_diffuse_plus_phong_on_visible_hits_only():
    rng = np.random.default_rng(6)
    m, k = 4000, 7
    color, args = shading_lanes(rng, m, k)
    ns, l, ndotl, view, mat, diffuse, specular, shininess, texel, lc = args
    before = color.copy()
    # Shadow rays name their lanes (-1: padding); only the unoccluded ones add light.
    lane = np.full(m // 2 + 8, -1, np.int64)
    lane[: m // 2] = rng.choice(m, m // 2, replace=False)
    occluded = rng.random(lane.size) < 0.3
    add_light(color, lane, occluded, *args)
    v = np.sort(lane[(lane >= 0) & ~occluded])
    r = 2 * ndotl[v, None] * ns[v] - l[v]
    spec = np.maximum(np.einsum("ij,ij->i", r, -view[v]), 0) ** shininess[mat[v]]
    expected = before.copy()
    expected[v] += lc * (diffuse[mat[v]] * texel[v] * ndotl[v, None] + specular[mat[v]] * spec[:, None])
    np.testing.assert_allclose(color, expected, rtol=1e-5, atol=1e-6)
    hidden = np.setdiff1d(np.arange(m), v)
    assert np.array_equal(color[hidden], before[hidden])


def test_add_light_in_place_is_add_light_over_the_lit_lanes():
    """Shadow rays walked in their own lanes add exactly what the same rays add when compacted."""
    rng = np.random.default_rng(7)
    m = 3000
    color, args = shading_lanes(rng, m, 5)
    lit = rng.random(m) < 0.7
    occluded = rng.random(m) < 0.4  # answers of every lane's ray; the unlit ones were dead
    in_place, compacted = color.copy(), color.copy()
    add_light_in_place(in_place, lit, occluded, *args)
    lane = np.flatnonzero(lit)
    add_light(compacted, lane, occluded[lane], *args)
    assert np.array_equal(in_place, compacted)
    assert np.array_equal(in_place[~lit | occluded], color[~lit | occluded])
    assert not np.array_equal(in_place[lit & ~occluded], color[lit & ~occluded])


def test_lanes_away_from_the_highlight_add_no_specular_unless_the_exponent_is_zero():
    """Where the mirrored light direction points away from the eye the highlight base is 0:
    0 ** s adds no specular for s > 0 (the step skips its pow there), and 0 ** 0 = 1 adds it
    whole."""
    rng = np.random.default_rng(8)
    m = 64
    color, args = shading_lanes(rng, m, 2)
    ns, l, ndotl, view, mat, diffuse, specular, shininess, texel, lc = args
    r = 2 * ndotl[:, None] * ns - l
    view[:] = unit(r)  # -(r . view) < 0: the highlight base is max(., 0) = 0 on every lane
    shininess[:] = (0.0, 7.5)
    mat[:] = np.arange(m) % 2
    before = color.copy()
    add_light_in_place(color, np.ones(m, bool), np.zeros(m, bool), *args)
    zero_exponent = (mat == 0)[:, None]
    expected = before + lc * (diffuse[mat] * texel * ndotl[:, None] + np.where(zero_exponent, specular[mat], 0))
    np.testing.assert_allclose(color, expected, rtol=1e-6, atol=1e-7)
    assert not np.allclose(color[mat == 0], (before + lc * diffuse[mat] * texel * ndotl[:, None])[mat == 0])
