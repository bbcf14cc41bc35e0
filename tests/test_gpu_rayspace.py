"""The device rayspace traversal (``engine.gpu.rayspace``) on numba's CUDA simulator: exactly the
CPU's hits (brute force, ``single``, the CPU ``rayspace`` plugin; Embree as a yardstick) on a
small Whitted scene's camera, reflection/refraction and shadow rays of a 12 x 12 image.

The simulator runs in a child process (tests/gpu_sim_rayspace_check.py, through
``tests.cudasim.simulated``) with NUMBA_ENABLE_CUDASIM=1 in its environment only: this process
keeps numba's CPU JIT for the references. All cases run in one child, and each test checks one
case.
"""
from __future__ import annotations

import json
from pathlib import Path

import numba
import numpy as np
import pytest
from numba import njit

from brute_force import brute_force
from cudasim import simulated
from engine.core.bvh import build_bvh
from engine.core.offset import offset_origin
from engine.core.triangle import intersect_triangle, ray_shear, safe_inverse
from engine.core.types import Packets, RayBatch, Triangles, empty_hits, new_stats
from engine.packet.layout import make_batch
from engine.rayspace.direction_grid import direction_grid_pixels
from engine.rayspace.light_grid import light_grid_pixels, rank_pixel
from engine.render.camera import camera_rays
from engine.render.plugins import make_traversal
from scenes.catalog import load_named
from traversals.rayspace import RaySpaceTraversal

pytest.importorskip("numba_cuda")

SIZE = 12
PACKET = 8          # 12 x 12 in 8 x 8 packets: the batches carry dead padding lanes
DUPLICATES = 4      # floor triangles repeated at the end of the list: exact ties in t
SMALL_BUDGET = 300  # pairs: forces several triangle batches (and a retry) on the shadow rays
FIRST_DUPLICATE = 2
SCENE = {"checks": 2, "subdivisions": 0}
ELSEWHERE = (4.3, 7.6, 5.2)  # near the light (4, 8, 5), but not the point the shadow rays aim at
ELSEWHERE_RAYS = 40  # of the shadow batch: the rest are rows past n
GARBAGE = 5         # rows past n in the secondary queue: never read, never written


# -- the scene and the rays ----------------------------------------------------------------

def tiny_whitted() -> Triangles:
    """The built-in Whitted scene at its coarsest (2 x 2 checks, icosahedra: 48 triangles) plus
    DUPLICATES of its floor triangles appended, whose hits tie exactly with the originals'."""
    tris = load_named("whitted", SCENE).triangles
    dup = np.arange(DUPLICATES) + FIRST_DUPLICATE
    return Triangles(*(np.concatenate([a, a[dup]]) if a.shape[0] else a for a in tris))


def unit(v):
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def plain_batch(kind, org, d, tmin, tmax, pixel) -> RayBatch:
    """A RayBatch in the given order (no packet layout: several rays may share a pixel)."""
    org, d = np.ascontiguousarray(org, np.float32), np.ascontiguousarray(d, np.float32)
    return RayBatch(org, d, safe_inverse(d), np.asarray(tmin, np.float32), np.asarray(tmax, np.float32),
                    np.asarray(pixel, np.int32), np.ones((len(org), 3), np.float32), kind)


class Rays:
    """Camera rays of the scene (packet order), their hits by brute force, and the secondary
    queues cast from those hits."""

    def __init__(self):
        scene = load_named("whitted", SCENE)
        self.light = np.asarray(scene.lights[0].position, np.float32)
        self.tris = tiny_whitted()
        org, d = camera_rays(scene, SIZE, SIZE)
        count = SIZE * SIZE
        self.primary, self.packets = make_batch("primary", org, d, np.zeros(count), np.full(count, np.inf),
                                                np.arange(count, dtype=np.int32), np.ones((count, 3)), SIZE, SIZE,
                                                PACKET)
        t, prim = reference(self.primary, self.tris)
        hit = np.flatnonzero(prim >= 0)
        d = unit(self.primary.dir[hit])
        point = (self.primary.org[hit] + t[hit, None] * self.primary.dir[hit]).astype(np.float32)
        ng = self.tris.ng[prim[hit]]
        ng = np.where((np.einsum("ij,ij->i", ng, d) < 0)[:, None], ng, -ng).astype(np.float32)
        self.point, self.ng, self.d, self.pixel = point, ng, d, self.primary.pixel[hit]

    def secondary(self) -> RayBatch:
        """Reflection and refraction rays of every hit in one queue (pixels shared by two rays),
        three of them made dead (tmax < tmin), then GARBAGE rows past n."""
        refl = unit(self.d - 2 * np.einsum("ij,ij->i", self.d, self.ng)[:, None] * self.ng)
        eta = np.float32(1 / 1.5)
        cos_i = -np.einsum("ij,ij->i", self.d, self.ng)
        k = np.maximum(1 - eta * eta * (1 - cos_i * cos_i), 0)
        refr = unit(eta * self.d + (eta * cos_i - np.sqrt(k))[:, None] * self.ng)
        org = np.concatenate([offset_origin(self.point, self.ng), offset_origin(self.point, -self.ng)])
        d = np.concatenate([refl, refr])
        m = len(org)
        tmin, tmax = np.zeros(m, np.float32), np.full(m, np.inf, np.float32)
        tmin[[1, 7, m - 2]] = 2.0
        tmax[[1, 7, m - 2]] = 1.0
        pixel = np.concatenate([self.pixel, self.pixel])
        # Rays past n that would hit (copies of the first rays), on a pixel off the screen.
        org = np.concatenate([org, org[:GARBAGE]])
        d = np.concatenate([d, d[:GARBAGE]])
        tmin = np.concatenate([tmin, np.zeros(GARBAGE, np.float32)])
        tmax = np.concatenate([tmax, np.full(GARBAGE, np.inf, np.float32)])
        pixel = np.concatenate([pixel, np.full(GARBAGE, SIZE * SIZE + 3, np.int32)])
        return plain_batch("reflection", org, d, tmin, tmax, pixel)

    def shadow(self):
        """(RayBatch, Packets) of rays from the offset hit points towards the light, stopping
        short of it, as the Whitted loop casts them."""
        org = offset_origin(self.point, self.ng)
        to = self.light - org
        dist = np.linalg.norm(to, axis=1)
        return make_batch("shadow", org, unit(to), np.zeros(len(org)), dist * np.float32(1 - 1e-4), self.pixel,
                          np.ones((len(org), 3)), SIZE, SIZE, PACKET)


def unbounded_some(rays: RayBatch) -> RayBatch:
    """The batch with every fifth ray made unbounded (tmax = inf): no far end to reverse from."""
    tmax = rays.tmax.copy()
    tmax[::5] = np.where(rays.tmin[::5] <= tmax[::5], np.float32(np.inf), tmax[::5])
    return rays._replace(tmax=tmax)


def crowded(rays: RayBatch) -> RayBatch:
    """The queue with every ray on one of the four pixels of the first 2x2 block: a level-1
    node with more children than a pair's 63-bit survivor mask holds."""
    return rays._replace(pixel=np.where(rays.pixel < SIZE * SIZE, (rays.pixel % 2) + SIZE * ((rays.pixel // 7) % 2),
                                        rays.pixel).astype(np.int32))


def one_direction(rays: RayBatch) -> RayBatch:
    """The queue with every ray leaving in ray 0's direction: on the direction grid all live rays
    share one key, so the device's fill puts them in its slots in the atomics' order and only the
    rank count restores the CPU's stable order."""
    dirs = np.repeat(rays.dir[:1], len(rays.dir), axis=0)
    return rays._replace(dir=dirs, inv_dir=safe_inverse(dirs))


def reference(rays: RayBatch, tris: Triangles, n=None):
    """(t f32[n], prim i32[n]): the shared kernel over every triangle (tests/brute_force.py)."""
    n = rays.org.shape[0] if n is None else n
    t, prim = np.empty(n, np.float32), np.empty(n, np.int32)
    brute_force(rays.org[:n], rays.dir[:n], rays.tmin[:n], rays.tmax[:n], tris.v0, tris.v1, tris.v2, t, prim)
    return t, prim


@njit(cache=True)
def _barycentrics(org, dirs, tmin, tmax, v0, v1, v2, prim, u, v):
    """u, v of each ray's hit triangle prim[r] (>= 0) by the shared kernel."""
    for r in range(prim.shape[0]):
        if prim[r] >= 0:
            kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            _, u[r], v[r] = intersect_triangle(org[r, kx], org[r, ky], org[r, kz], kx, ky, kz, sx, sy, sz, tmin[r],
                                               tmax[r], v0, v1, v2, prim[r])


def barycentrics(rays, tris, prim):
    u, v = np.zeros(len(prim), np.float32), np.zeros(len(prim), np.float32)
    n = len(prim)
    _barycentrics(rays.org[:n], rays.dir[:n], rays.tmin[:n], rays.tmax[:n], tris.v0, tris.v1, tris.v2, prim, u, v)
    return u, v


# -- one simulator run for every case ------------------------------------------------------

def _case(cases: dict, name: str, rays: RayBatch, query: str, n: int, light=None, budget=1 << 22,
          shadow_grid="light", secondary=False, secondary_grid="direction", again=False) -> None:
    for key, value in (("org", rays.org), ("dir", rays.dir), ("tmin", rays.tmin), ("tmax", rays.tmax),
                       ("pixel", rays.pixel)):
        cases[f"{name}_{key}"] = np.ascontiguousarray(value)
    spec = {"query": query, "n": n, "width": SIZE, "height": SIZE, "pair_budget": budget,
            "light": None if light is None else [float(x) for x in light], "shadow_grid": shadow_grid,
            "secondary": secondary, "secondary_grid": secondary_grid, "again": again}
    cases[f"{name}_spec"] = np.array(json.dumps(spec))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(Rays, answers): the GPU answers of every case, from one simulator child process."""
    rays = Rays()
    secondary = rays.secondary()
    shadow, shadow_packets = rays.shadow()
    cases = {f"tri_{field}": np.ascontiguousarray(a) for field, a in zip(Triangles._fields, rays.tris)}
    _case(cases, "primary", rays.primary, "closest", len(rays.primary.org))
    _case(cases, "secondary", secondary, "closest", len(secondary.org) - GARBAGE)
    _case(cases, "secondary_direction", secondary, "closest", len(secondary.org) - GARBAGE, secondary=True,
          again=True)
    _case(cases, "secondary_pixel_grid", secondary, "closest", len(secondary.org) - GARBAGE, secondary=True,
          secondary_grid="pixel")
    _case(cases, "shadow_reversed", shadow, "occluded", len(shadow.org), light=rays.light, again=True)
    _case(cases, "shadow_pixel_grid", shadow, "occluded", len(shadow.org), light=rays.light, shadow_grid="pixel")
    _case(cases, "shadow_forward", shadow, "occluded", len(shadow.org))
    _case(cases, "shadow_elsewhere", unbounded_some(shadow), "occluded", ELSEWHERE_RAYS, light=ELSEWHERE)
    _case(cases, "crowded", crowded(secondary), "closest", len(secondary.org) - GARBAGE)
    _case(cases, "one_direction", one_direction(secondary), "closest", len(secondary.org) - GARBAGE, secondary=True)
    _case(cases, "batches", shadow, "closest", len(shadow.org), light=rays.light, budget=SMALL_BUDGET)
    _case(cases, "too_small", rays.primary, "closest", len(rays.primary.org), budget=1)
    count = len(rays.primary.org)
    _case(cases, "all_dead", rays.primary._replace(tmax=np.full(count, -1, np.float32)), "closest", count)
    _case(cases, "off_screen", rays.primary._replace(pixel=rays.primary.pixel + 1), "closest", count)
    folder = tmp_path_factory.mktemp("gpu_rayspace")
    np.savez(folder / "cases.npz", **cases)
    done = simulated("-m", "tests.gpu_sim_rayspace_check", str(folder / "cases.npz"), str(folder / "out.npz"))
    assert done.returncode == 0, done.stderr[-4000:]
    out = dict(np.load(folder / "out.npz"))
    answers = {key: out[key] for key in out if not key.endswith("_report")}
    for key in out:
        if key.endswith("_report"):
            answers[key] = json.loads(str(out[key]))
    return rays, answers, {"secondary": secondary, "shadow": shadow, "shadow_packets": shadow_packets}


def ok(answers, name) -> dict:
    report = answers[f"{name}_report"]
    assert "error" not in report, report["error"]
    return report["stats"]


def assert_closest(answers, name, rays, tris, n):
    t, prim = reference(rays, tris, n)
    got_t, got_prim = answers[f"{name}_t"], answers[f"{name}_prim"]
    assert np.array_equal(got_prim[:n], prim), np.flatnonzero(got_prim[:n] != prim)
    assert np.array_equal(got_t[:n].view(np.uint32), t.view(np.uint32))  # bit for bit (inf on a miss)
    u, v = barycentrics(rays, tris, prim)
    assert np.array_equal(answers[f"{name}_u"][:n], u) and np.array_equal(answers[f"{name}_v"][:n], v)
    return t, prim


# -- the tests -----------------------------------------------------------------------------

def test_camera_rays_match_brute_force_single_and_cpu_rayspace(run):
    rays, answers, _ = run
    batch, tris = rays.primary, rays.tris
    ok(answers, "primary")
    t, prim = assert_closest(answers, "primary", batch, tris, len(batch.org))
    assert (prim >= 0).sum() > 50
    bvh = build_bvh(tris)
    for name in ("single", "rayspace"):
        hits = empty_hits(len(batch.org))
        make_traversal(name).intersect(bvh, tris, batch, rays.packets, None, hits, None)
        assert np.array_equal(hits.prim, answers["primary_prim"]) and np.array_equal(hits.t, answers["primary_t"])
        assert np.array_equal(hits.u, answers["primary_u"]) and np.array_equal(hits.v, answers["primary_v"])
    # Embree (its own intersection): the same hit or miss everywhere, the same triangle up to ties.
    hits = empty_hits(len(batch.org))
    make_traversal("embree").intersect(bvh, tris, batch, rays.packets, None, hits, None)
    assert np.array_equal(hits.prim >= 0, prim >= 0)
    assert np.mean(hits.prim[prim >= 0] == prim[prim >= 0]) > 0.95


def test_ties_go_to_the_smaller_index(run):
    rays, answers, _ = run
    t, prim = reference(rays.primary, rays.tris)
    first_copy = rays.tris.v0.shape[0] - DUPLICATES
    originals = np.arange(DUPLICATES) + FIRST_DUPLICATE
    tied = np.isin(prim, originals)
    assert tied.any(), "no camera ray reaches a duplicated triangle: the tie is not tested"
    assert not (answers["primary_prim"] >= first_copy).any()


def test_stats_per_level_like_the_cpu_plugin(run):
    rays, answers, _ = run
    stats = ok(answers, "primary")
    live = int(((rays.primary.pixel >= 0) & (rays.primary.tmin <= rays.primary.tmax)).sum())
    levels = stats["levels"]
    assert levels == 4 and stats["rays"] == live and stats["batches"] == 1 and stats["retries"] == 0
    assert stats["pairs_before"][levels] == stats["pairs_after"][levels] == rays.tris.v0.shape[0]
    for level in range(levels):
        assert 0 < stats["pairs_after"][level] <= stats["pairs_before"][level]
        assert stats["cone_sphere_tests"][level] <= stats["pairs_before"][level]
    assert stats["candidates"] == stats["pairs_after"][0]
    assert stats["candidates_per_ray"] == pytest.approx(stats["candidates"] / live)
    # The same hierarchy as the CPU's (same math, same slot order), so about the same streams;
    # equal unless a last-bit difference in the libraries' sin/cos moves a cone edge.
    cpu = new_stats(numba.get_num_threads())
    make_traversal("rayspace").intersect(None, rays.tris, rays.primary, rays.packets, None,
                                         empty_hits(len(rays.primary.org)), cpu)
    mine = cpu.extra["rayspace"]
    for key in ("pairs_before", "pairs_after", "cone_sphere_tests"):
        assert np.allclose(stats[key], mine[key], rtol=0.01), (key, stats[key], mine[key])


def test_secondary_queue_with_shared_pixels_dead_rays_and_rows_past_n(run):
    rays, answers, extra = run
    batch = extra["secondary"]
    n = len(batch.org) - GARBAGE
    t, prim = assert_closest(answers, "secondary", batch, rays.tris, n)
    assert (prim >= 0).sum() > 20
    assert (prim[[1, 7, n - 2]] == -1).all() and np.isinf(t[[1, 7, n - 2]]).all()
    assert (answers["secondary_prim"][n:] == -7).all() and (answers["secondary_t"][n:] == -7).all()
    stats = ok(answers, "secondary")
    assert stats["rays"] == n - 3
    hits = empty_hits(n)
    part = RayBatch(*(a[:n] if isinstance(a, np.ndarray) else a for a in batch))
    make_traversal("rayspace").intersect(None, rays.tris, part, Packets(np.array([0, n], np.int32), 1, SIZE, SIZE),
                                         None, hits, None)
    assert np.array_equal(hits.prim, answers["secondary_prim"][:n])


def test_secondary_rays_on_the_direction_grid(run):
    """Reflection rays placed by screen tile and direction (secondary=True): the CPU's pixels
    (the same twinned key), the same answers, rows past n untouched; without secondary=True or
    with secondary_grid = "pixel" the queue keeps its pixels."""
    rays, answers, extra = run
    batch = extra["secondary"]
    n = len(batch.org) - GARBAGE
    part = RayBatch(*(a[:n] if isinstance(a, np.ndarray) else a for a in batch))
    cpu_pixels, side = direction_grid_pixels(part.dir, part.tmin, part.tmax, part.pixel, SIZE, SIZE)
    assert np.array_equal(answers["secondary_direction_grid_pixel"], cpu_pixels)
    assert (cpu_pixels >= 0).sum() == n - 3 and side * side >= n - 3
    for name in ("secondary_direction", "secondary_pixel_grid"):
        assert_closest(answers, name, batch, rays.tris, n)
        assert (answers[f"{name}_prim"][n:] == -7).all()
    assert "secondary_grid_pixel" not in answers and "secondary_pixel_grid_grid_pixel" not in answers
    cpu = new_stats(numba.get_num_threads())
    make_traversal("rayspace").intersect(None, rays.tris, part,
                                         Packets(np.array([0, n], np.int32), 1, SIZE, SIZE), None, empty_hits(n), cpu)
    stats = ok(answers, "secondary_direction")
    for key in ("pairs_before", "pairs_after", "cone_sphere_tests"):
        assert np.allclose(stats[key], cpu.extra["rayspace"][key], rtol=0.01), (key, stats[key])


def test_one_direction_cell_keeps_the_cpus_ray_order(run):
    """Every live ray in one direction-grid key: the device ranks them as the CPU's stable sort
    does (a pixel each, in ray order), whatever order its atomics filled the key's slots in."""
    rays, answers, extra = run
    batch = one_direction(extra["secondary"])
    n = len(batch.org) - GARBAGE
    part = RayBatch(*(a[:n] if isinstance(a, np.ndarray) else a for a in batch))
    cpu_pixels, side = direction_grid_pixels(part.dir, part.tmin, part.tmax, part.pixel, SIZE, SIZE)
    live = cpu_pixels >= 0
    assert live.sum() > 60  # several of the simulator's 32-thread blocks fill the one key
    assert np.array_equal(cpu_pixels[live], [rank_pixel(k, side) for k in range(live.sum())])
    assert np.array_equal(answers["one_direction_grid_pixel"], cpu_pixels)
    assert_closest(answers, "one_direction", batch, rays.tris, n)


@pytest.mark.parametrize("name", ["secondary_direction", "shadow_reversed"])
def test_the_same_call_again_replays_every_launch(run, name):
    """A second call over the same queue (as the next frame of a static view makes) finds every
    kernel launch prepared: the scratch hands out the same views, so no launch goes through
    numba's argument conversion again; and it answers exactly as the first."""
    rays, answers, extra = run
    assert "error" not in answers[f"{name}_report"], answers[f"{name}_report"]
    again = answers[f"{name}_report"]["again"]
    assert again["first_misses"] > 10 and again["hits"] == again["first_misses"] and again["misses"] == 0
    keys = ("t", "prim", "u", "v") if name == "secondary_direction" else ("occluded",)
    for key in keys:
        assert np.array_equal(answers[f"{name}_again_{key}"], answers[f"{name}_{key}"])


def test_a_block_of_more_rays_than_the_survivor_mask_holds(run):
    """Over 63 rays in one 2x2 block: survivors past the mask's bits are found by re-testing."""
    rays, answers, extra = run
    batch = crowded(extra["secondary"])
    n = len(batch.org) - GARBAGE
    live = (batch.tmin[:n] <= batch.tmax[:n])
    assert live.sum() > 63 and set(np.unique(batch.pixel[:n])) == {0, 1, SIZE, SIZE + 1}
    assert ok(answers, "crowded")["rays"] == live.sum()
    assert_closest(answers, "crowded", batch, rays.tris, n)


@pytest.mark.parametrize("name", ["shadow_reversed", "shadow_pixel_grid", "shadow_forward", "shadow_elsewhere"])
def test_shadow_rays_occlusion(run, name):
    """Reversed from the light (grouped by direction from it, or by pixel), forward, or reversed
    from a wrong point with some rays unbounded (those stay forward): the same answers, since
    any leaf that holds its segment is exact and the grouping only decides what is tested."""
    rays, answers, extra = run
    batch = unbounded_some(extra["shadow"]) if name == "shadow_elsewhere" else extra["shadow"]
    n = ELSEWHERE_RAYS if name == "shadow_elsewhere" else len(batch.org)
    stats = ok(answers, name)
    _, prim = reference(batch, rays.tris, n)
    got = answers[f"{name}_occluded"]
    assert set(np.unique(got[:n])) <= {0, 1} and (got[n:] == 7).all()  # rows past n untouched
    assert np.array_equal(got[:n].astype(bool), prim >= 0)
    assert 0 < (prim >= 0).sum() < (batch.pixel[:n] >= 0).sum()  # some lit, some in shadow
    assert stats["reversed_batches"] == (name != "shadow_forward")


def test_light_grid_pixels_and_streams_are_the_cpu_plugins(run):
    """The device places every shadow ray on the light grid's cell the CPU computes (the same
    twinned math), and the stream then tests what the CPU plugin tests; the pixel grid tests
    other pairs (so the option reaches the device)."""
    rays, answers, extra = run
    batch = extra["shadow"]
    n = len(batch.org)
    cpu_pixels, side = light_grid_pixels(batch.dir, batch.tmin, batch.tmax, batch.pixel, SIZE, SIZE)
    assert np.array_equal(answers["shadow_reversed_grid_pixel"], cpu_pixels)
    live = cpu_pixels >= 0
    assert side * side >= live.sum() > side * side // 4
    # The k-th ray of the sorted order at Morton position k: one ray a pixel, four a block.
    assert np.array_equal(np.sort(cpu_pixels[live]), np.sort([rank_pixel(k, side) for k in range(live.sum())]))
    assert "shadow_pixel_grid_grid_pixel" not in answers
    light, pixel = ok(answers, "shadow_reversed"), ok(answers, "shadow_pixel_grid")
    cpu = new_stats(numba.get_num_threads())
    RaySpaceTraversal().occluded(None, rays.tris, batch, extra["shadow_packets"], None, np.zeros(n, np.bool_), cpu)
    for key in ("pairs_before", "pairs_after", "cone_sphere_tests"):
        assert np.allclose(light[key], cpu.extra["rayspace"][key], rtol=0.01), (key, light[key])
    assert light["cone_sphere_tests"] != pixel["cone_sphere_tests"]


def test_small_pair_budget_batches_triangles(run):
    """Batches merged by the tie rule, a retry after an overflow: the CPU plugin's policy."""
    rays, answers, extra = run
    batch = extra["shadow"]
    stats = ok(answers, "batches")
    assert stats["batches"] > 1 and stats["retries"] >= 1 and stats["peak_pairs"] <= SMALL_BUDGET
    assert stats["pairs_before"][stats["levels"]] > rays.tris.v0.shape[0]  # retried triangles count again
    assert_closest(answers, "batches", batch, rays.tris, len(batch.org))
    cpu = new_stats(numba.get_num_threads())
    RaySpaceTraversal(pair_budget=SMALL_BUDGET).intersect(None, rays.tris, batch, extra["shadow_packets"], None,
                                                          empty_hits(len(batch.org)), cpu)
    assert (stats["batches"], stats["retries"]) == (cpu.extra["rayspace"]["batches"], cpu.extra["rayspace"]["retries"])


def test_budget_too_small_for_one_triangle_names_the_need(run):
    _, answers, _ = run
    error = answers["too_small_report"].get("error", "")
    assert error.startswith("ConfigError: options.rayspace: pair_budget = 1 is too small"), error
    assert "raise pair_budget to at least" in error


def test_all_dead_rays_miss_and_a_pixel_off_screen_is_refused(run):
    _, answers, _ = run
    stats = ok(answers, "all_dead")
    assert stats["rays"] == 0 and stats["candidates"] == 0
    assert (answers["all_dead_prim"] == -1).all() and np.isinf(answers["all_dead_t"]).all()
    error = answers["off_screen_report"].get("error", "")
    assert error == f"ValueError: ray pixel {SIZE * SIZE} is outside the {SIZE}x{SIZE} screen grid", error
