"""Mitsuba 3 as the GPU yardstick (engine.bench.mitsuba_yardstick): on the same 200 rays over
the whitted scene, Mitsuba's closest hits (triangle and distance) and occlusion answers are
Embree's (validation.oracle), ties apart; a scene whose triangles are numbered differently is
caught; the timing helper reports what it measured. Each variant runs where it can: cuda_ad_rgb
on a GPU, llvm_ad_rgb where Dr.Jit finds libLLVM, scalar_rgb anywhere Mitsuba imports; the
others skip with the reason."""
import numpy as np
import pytest

pytest.importorskip("mitsuba")

from engine.bench.mitsuba_yardstick import (MitsubaScene, MitsubaUnavailable, load_mitsuba,  # noqa: E402
                                            mitsuba_available, time_queries)
from engine.core.errors import ConfigError  # noqa: E402
from engine.core.triangle import safe_inverse  # noqa: E402
from engine.core.types import RayBatch  # noqa: E402
from scenes.catalog import load_named  # noqa: E402
from validation.oracle import EmbreeOracle  # noqa: E402

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
RAYS = 200
#: At most this many rays may disagree on the triangle while agreeing on the distance (a ray
#: through a shared edge or vertex: either triangle is a right answer) ...
MAX_TIES = 3
#: ... and at most this many may disagree on hit / miss or occlusion (a ray grazing an edge,
#: decided differently by Embree's robust test and the backend inside Mitsuba).
MAX_GRAZING = 2
T_RTOL = 1e-4


@pytest.fixture(scope="module")
def whitted():
    return load_named("whitted").triangles


@pytest.fixture(scope="module")
def rays(whitted):
    return ray_set(whitted, RAYS, seed=11)


def ray_set(tris, n, seed):
    """RayBatch of n rays over tris: most aimed at a random triangle's centroid from around the
    scene (so they hit), some in random directions (many miss); a fifth start past their
    origin (tmin > 0), a third stop short (finite tmax), a few are dead lanes (tmax < tmin)."""
    rng = np.random.default_rng(seed)
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1).astype(np.float64)
    lo, hi = corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)
    org = rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo), size=(n, 3))
    target = corners[rng.integers(0, len(corners), n)].mean(axis=1)
    dirs = (target - org) * rng.uniform(0.5, 2.0, size=(n, 1))
    wander = rng.random(n) < 0.2
    dirs[wander] = rng.normal(size=(wander.sum(), 3))
    reach = np.linalg.norm(target - org, axis=1) / np.linalg.norm(dirs, axis=1)
    tmin = np.where(rng.random(n) < 0.2, rng.uniform(0.0, 0.5, n) * reach, 0.0)
    tmax = np.where(rng.random(n) < 0.33, tmin + rng.uniform(0.3, 1.5, n) * reach, np.inf)
    dead = rng.random(n) < 0.03
    tmax[dead] = tmin[dead] - 1
    org, dirs = org.astype(np.float32), dirs.astype(np.float32)
    return RayBatch(org, dirs, safe_inverse(dirs), tmin.astype(np.float32), tmax.astype(np.float32),
                    np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), "reflection")


def scene_for(variant, tris, order=None):
    """MitsubaScene over tris (triangles permuted by ``order`` when given), or a skip saying why."""
    reason = mitsuba_available(variant)
    if reason:
        pytest.skip(reason)
    v0, v1, v2 = tris.v0, tris.v1, tris.v2
    if order is not None:
        v0, v1, v2 = v0[order], v1[order], v2[order]
    return MitsubaScene(v0, v1, v2, variant)


def compare_closest(t, prim, ref_t, ref_prim):
    """(grazing, ties, wrong) ray lists: grazing = hit / miss disagree; ties = both hit at the
    same distance (T_RTOL) on different triangles; wrong = both hit at different distances."""
    hit, ref_hit = prim >= 0, ref_prim >= 0
    grazing = np.flatnonzero(hit != ref_hit).tolist()
    both = hit & ref_hit
    close = np.zeros_like(both)
    close[both] = np.abs(t[both] - ref_t[both]) <= T_RTOL * np.abs(ref_t[both])
    ties = np.flatnonzero(both & close & (prim != ref_prim)).tolist()
    wrong = np.flatnonzero(both & ~close).tolist()
    return grazing, ties, wrong


@pytest.mark.parametrize("variant", VARIANTS)
def test_closest_hits_are_embrees(variant, whitted, rays):
    scene = scene_for(variant, whitted)
    t, prim = scene.closest(rays.org, rays.dir, rays.tmin, rays.tmax)
    assert t.dtype == np.float32 and prim.dtype == np.int32 and t.shape == prim.shape == (RAYS,)
    ref = EmbreeOracle(whitted).intersect(rays)
    assert (ref.prim >= 0).sum() > 100 and (ref.prim < 0).sum() > 20  # both answers are exercised
    grazing, ties, wrong = compare_closest(t, prim, ref.t, ref.prim)
    for i in ties:
        print(f"{variant}: tie on ray {i}: mitsuba {prim[i]} at {t[i]!r}, embree {ref.prim[i]} at {ref.t[i]!r}")
    assert not wrong, [(i, t[i], ref.t[i], prim[i], ref.prim[i]) for i in wrong]
    assert len(grazing) <= MAX_GRAZING, [(i, prim[i], ref.prim[i]) for i in grazing]
    assert len(ties) <= MAX_TIES
    dead = ~(rays.tmin <= rays.tmax)
    assert dead.any() and (prim[dead] == -1).all() and np.isinf(t[dead]).all()


@pytest.mark.parametrize("variant", VARIANTS)
def test_occlusion_is_embrees(variant, whitted, rays):
    scene = scene_for(variant, whitted)
    occluded = scene.occluded(rays.org, rays.dir, rays.tmin, rays.tmax)
    ref = EmbreeOracle(whitted).occluded(rays)
    assert ref.sum() > 60 and (~ref).sum() > 40
    differ = np.flatnonzero(occluded != ref).tolist()
    assert len(differ) <= MAX_GRAZING, differ
    assert not occluded[~(rays.tmin <= rays.tmax)].any()


def test_a_misnumbered_scene_is_caught(whitted, rays):
    """The comparison can fail: Mitsuba over the same triangles in reverse order hits the same
    surfaces at the same distances, but every triangle index is wrong."""
    variant = next((v for v in VARIANTS if mitsuba_available(v) is None), None)
    if variant is None:
        pytest.skip("no Mitsuba variant runs here")
    order = np.arange(len(whitted.v0))[::-1]
    t, prim = scene_for(variant, whitted, order).closest(rays.org, rays.dir, rays.tmin, rays.tmax)
    ref = EmbreeOracle(whitted).intersect(rays)
    grazing, ties, wrong = compare_closest(t, prim, ref.t, ref.prim)
    assert len(ties) > MAX_TIES  # what test_closest_hits_are_embrees would reject


def test_timing_reports_what_it_measured(whitted, rays):
    variant = next((v for v in VARIANTS if mitsuba_available(v) is None), None)
    if variant is None:
        pytest.skip("no Mitsuba variant runs here")
    scene = scene_for(variant, whitted)
    for query in ("closest", "occluded"):
        report = time_queries(scene, rays.org, rays.dir, rays.tmin, rays.tmax, query, repeats=3)
        assert report["rays"] == RAYS and report["query"] == query and len(report["seconds"]) == 3
        assert report["median_seconds"] == sorted(report["seconds"])[1]
        assert report["grays_per_s"] == pytest.approx(RAYS / report["median_seconds"] / 1e9)
    with pytest.raises(ConfigError, match="query"):
        time_queries(scene, rays.org, rays.dir, rays.tmin, rays.tmax, "nearest")
    with pytest.raises(ConfigError, match="repeats"):
        time_queries(scene, rays.org, rays.dir, rays.tmin, rays.tmax, "closest", repeats=0)
    with pytest.raises(ConfigError, match="shape"):
        scene.closest(rays.org[:, :2], rays.dir, rays.tmin, rays.tmax)
    with pytest.raises(ConfigError, match="ray count"):
        scene.occluded(rays.org, rays.dir[:-1], rays.tmin, rays.tmax)


def test_an_unknown_variant_is_one_line():
    reason = mitsuba_available("no_such_variant")
    assert reason and "\n" not in reason and "no_such_variant" in reason
    with pytest.raises(MitsubaUnavailable, match="no variant"):
        load_mitsuba("no_such_variant")
