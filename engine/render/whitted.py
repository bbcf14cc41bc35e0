"""The Whitted loop: the only shading code. Every traversal variant renders through it.

Wavefront by depth:

1. primary rays in packet order -> closest hits;
2. for every point light a shadow batch in the same ancestral packet order -> occlusion;
3. local Phong (ambient, diffuse with textures, specular) into the image;
4. a reflection batch (reflectance > 0; total internal reflection joins it) and a refraction
   batch (transmission > 0, Snell), kept in ancestral packet order, dead rays compacted out;
5. repeat from 2 with the secondary batches, up to ``max_depth`` generations (mirror
   reflections only off hits of depth < ``max_reflection_depth``).

The traversal and frustum for each ray kind come from the config (new plugin instances per
renderer, ``engine.render.plugins``); every batch is cast through ``engine.render.tracer``,
which times and counts it. Shading is vectorised numpy over a whole batch; the hot loops are
the traversals' numba kernels.

A traversal plugin may define ``prepare(tris) -> seconds`` to build its own structure before
timing starts. ``observer(kind, query, rays, packets, answer)`` is called after every cast batch
(query "intersect" with Hits, or "occluded" with bool[R]); the audit and the benchmark use it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from engine.core.bvh import build_bvh, scene_bounds
from engine.render.config import Config
from engine.render.plugins import configured
from engine.render.tracer import Tally, Tracer
from engine.render.direct_light import add_light, light_directions
from engine.core.offset import coordinate_magnitude, hit_points, offset_origin, triangle_magnitudes
from engine.packet.layout import gather_batch, make_batch, packet_order
from engine.core.scene import Scene
from engine.core.types import RAY_KINDS, Hits, RayBatch, empty_hits, new_stats, stats_by_depth, stats_totals

SHADOW_TMAX_SCALE = np.float32(1.0 - 1e-4)  # stop shadow rays just short of the light
MIN_WEIGHT = np.float32(1e-3)               # rays carrying less are not worth casting
WARM_UP_SIZE = 32                           # pixels a side of the compile-absorbing warm-up frame


@dataclass
class RenderResult:
    """One render's image and measurements.

    image: f32[H,W,3] linear RGB. seconds: {"bvh", "trace": {kind: s}, "shade", "total",
    "plugin_build": {plugin: s}}. rays: {kind: live rays cast}. counters: {"ray_aabb" |
    "ray_tri" | "nodes": {kind: n}} and counters_by_depth (the same per BVH depth, lists), empty
    unless the render counted. extra: {kind: plugin statistics}. ``engine.render.report``
    turns it into the ``--stats`` document.
    """

    image: np.ndarray
    seconds: dict
    rays: dict
    counters: dict
    counters_by_depth: dict
    extra: dict = field(default_factory=dict)

    def mrays_per_s(self) -> dict:
        return {k: (self.rays[k] / self.seconds["trace"][k] / 1e6 if self.seconds["trace"][k] > 0 else 0.0)
                for k in RAY_KINDS}


class MaterialTable:
    """The scene's materials as arrays indexed by material id (M materials).

    ambient, diffuse, specular, reflectance: f32[M,3]; shininess, transmission, ior: f32[M];
    texture: list of f32[H,W,3] or None.
    """

    def __init__(self, materials):
        self.ambient = np.array([m.ambient for m in materials], np.float32).reshape(-1, 3)
        self.diffuse = np.array([m.diffuse for m in materials], np.float32).reshape(-1, 3)
        self.specular = np.array([m.specular for m in materials], np.float32).reshape(-1, 3)
        self.reflectance = np.array([m.reflectance for m in materials], np.float32).reshape(-1, 3)
        self.shininess = np.array([m.shininess for m in materials], np.float32)
        self.transmission = np.array([m.transmission for m in materials], np.float32)
        self.ior = np.array([m.ior if m.ior > 0 else 1.0 for m in materials], np.float32)
        self.texture = [m.texture for m in materials]


def camera_rays(scene: Scene, width: int, height: int):
    """(org f32[W*H,3], dir f32[W*H,3] unit): one ray through each pixel centre, row-major."""
    eye, forward, right, up = scene.camera.basis()
    half_h = math.tan(math.radians(scene.camera.fov) / 2)
    half_w = half_h * width / height
    ys, xs = np.mgrid[0:height, 0:width]
    px = ((xs + 0.5) / width * 2 - 1) * half_w
    py = (1 - (ys + 0.5) / height * 2) * half_h
    d = forward + px[..., None] * right + py[..., None] * up
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3).astype(np.float32)
    return np.tile(eye.astype(np.float32), (width * height, 1)), d


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel, wrapping: texture f32[H,W,3], uv f32[M,2] -> f32[M,3]."""
    h, w = texture.shape[:2]
    x = np.floor((uv[:, 0] % 1.0) * w).astype(np.int64) % w
    y = np.floor((1.0 - uv[:, 1] % 1.0) * h).astype(np.int64) % h
    return texture[y, x]


def _summarise_stats(per_kind: dict) -> tuple[dict, dict, dict]:
    """{kind: Stats} of a counting render -> (counters {name: {kind: n}}, per-depth counters
    {name: {kind: [n per BVH depth]}}, plugin extras {kind: stats.extra})."""
    counters, by_depth, extra = {}, {}, {}
    for kind, stats in per_kind.items():
        for name, value in stats_totals(stats).items():
            counters.setdefault(name, dict.fromkeys(RAY_KINDS, 0))[kind] = value
        for name, values in stats_by_depth(stats).items():
            by_depth.setdefault(name, {k: [] for k in RAY_KINDS})[kind] = list(values)
        if stats.extra:
            extra[kind] = stats.extra
    return counters, by_depth, extra


class WhittedRenderer:
    """Renders one scene with one config. Build once, ``render()`` as often as wanted."""

    def __init__(self, scene: Scene, config: Config, *, observer=None, count: bool = False):
        self.scene = scene
        self.config = config
        self.observer = observer
        self.count = count
        self.threads = config.render.threads or numba.config.NUMBA_NUM_THREADS
        numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        self.traversal, self.frustum = configured(config)
        self.materials = MaterialTable(scene.materials)
        self.tris = scene.triangles
        self.bvh = build_bvh(self.tris, leaf_size=config.render.leaf_size, bins=config.render.bins)
        self.bounds = scene_bounds(self.bvh)
        self.corner_magnitude = triangle_magnitudes(self.tris)  # for secondary-ray offsets
        self.tracer = Tracer(self.bvh, self.tris, self.bounds, self.traversal, self.frustum)
        # Plugins with their own acceleration structure (Embree) build it now, outside the
        # timed trace, and report the build time.
        self.prepare_seconds = self.tracer.prepare()

    def _trace(self, kind, rays, packets, query, tally):
        answer = self.tracer.trace(kind, query, rays, packets, tally)
        if self.observer is not None:
            self.observer(kind, query, rays, packets, answer)
        return answer

    # -- the loop ------------------------------------------------------------------------
    def warm_up(self) -> float:
        """Compile (or load from numba's disk cache) the kernels this config uses, by one small
        render (WARM_UP_SIZE square, at least two packets a side) that no observer sees; returns
        its seconds, which ``packetrt render`` reports as ``seconds.compile``. A kernel only
        reached by rays the small image does not cast still compiles in the first frame."""
        side = max(WARM_UP_SIZE, 2 * self.config.render.packet)
        observer, self.observer = self.observer, None
        start = time.perf_counter()
        try:
            self.render(size=(side, side))
        finally:
            self.observer = observer
        return time.perf_counter() - start

    def render(self, size: tuple | None = None) -> RenderResult:
        """One frame; ``size`` (width, height) overrides the config's image size."""
        cfg = self.config.render
        width, height = size or (cfg.width, cfg.height)
        n = cfg.packet
        tally = Tally(count=self.count)
        start = time.perf_counter()
        image = np.zeros((width * height, 3), np.float32)
        org, dirs = camera_rays(self.scene, width, height)
        pixel = np.arange(width * height, dtype=np.int32)
        weight = np.ones((width * height, 3), np.float32)
        batches = [make_batch("primary", org, dirs, np.zeros(len(pixel)), np.full(len(pixel), np.inf),
                              pixel, weight, width, height, n)]
        shade_seconds = 0.0
        for depth in range(cfg.max_depth + 1):
            children = {"reflection": [], "refraction": []}
            for rays, packets in batches:
                if rays.org.shape[0] == 0:
                    continue
                hits = self._trace(rays.kind, rays, packets, "intersect", tally)
                shade_start = time.perf_counter()
                trace_before = sum(tally.seconds.values())
                spawned = self._shade(rays, packets, hits, image, depth < cfg.max_depth, tally,
                                      reflect=depth < cfg.max_reflection_depth)
                shade_seconds += time.perf_counter() - shade_start - (sum(tally.seconds.values()) - trace_before)
                for kind, parts in spawned.items():
                    children[kind].append(parts)
            batches = []
            for kind in ("reflection", "refraction"):
                parts = [p for p in children[kind] if len(p[0])]
                if parts:
                    cat = [np.concatenate([p[i] for p in parts]) for i in range(4)]
                    o, d, pix, w = cat
                    batches.append(make_batch(kind, o, d, np.zeros(len(pix)), np.full(len(pix), np.inf),
                                              pix, w, width, height, n))
            if not batches:
                break
        total = time.perf_counter() - start
        counters, by_depth, extra = _summarise_stats(tally.stats)
        seconds = {"bvh": self.bvh.build_seconds, "trace": tally.seconds, "shade": shade_seconds, "total": total,
                   "plugin_build": self.prepare_seconds}
        return RenderResult(image.reshape(height, width, 3), seconds, tally.rays, counters, by_depth, extra)

    def with_counters(self, result: RenderResult) -> RenderResult:
        """``result`` with counters and plugin statistics from a second, counting render (so the
        timed render does not pay for counting)."""
        count, self.count = self.count, True
        try:
            counted = self.render()
        finally:
            self.count = count
        result.counters, result.counters_by_depth, result.extra = counted.counters, counted.counters_by_depth, counted.extra
        return result

    def _shade(self, rays: RayBatch, packets, hits: Hits, image, spawn: bool, tally, reflect: bool = True) -> dict:
        """Add this batch's direct light and background to ``image``; return its children as
        {"reflection": (org, dir, pixel, weight), "refraction": (...)}. ``reflect`` False: no
        mirror reflections (total internal reflection still continues a refraction path)."""
        m, tris, scene = self.materials, self.tris, self.scene
        live = rays.pixel >= 0
        miss = live & (hits.prim < 0)
        bg = np.asarray(scene.background, np.float32)
        np.add.at(image, rays.pixel[miss], rays.weight[miss] * bg)
        idx = np.flatnonzero(live & (hits.prim >= 0))
        empty = (np.zeros((0, 3), np.float32),) * 2 + (np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
        if idx.size == 0:
            return {"reflection": empty, "refraction": empty}
        prim = hits.prim[idx]
        d = rays.dir[idx]
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        u, v = hits.u[idx][:, None], hits.v[idx][:, None]
        p = hit_points(tris, prim, hits.u[idx], hits.v[idx])
        magnitude = coordinate_magnitude(tris, prim, p, self.corner_magnitude)
        ng = tris.ng[prim]
        entering = np.einsum("ij,ij->i", ng, d) < 0
        ng_ff = np.where(entering[:, None], ng, -ng)  # geometric normal facing the ray
        if tris.normals.shape[0]:
            c = tris.normals[prim]
            ns = (1 - u - v) * c[:, 0] + u * c[:, 1] + v * c[:, 2]
            length = np.linalg.norm(ns, axis=1, keepdims=True)
            ns = np.where(length > 0, ns / np.where(length > 0, length, 1), ng)
            ns = np.where((np.einsum("ij,ij->i", ns, ng_ff) < 0)[:, None], -ns, ns)
        else:
            ns = ng_ff
        mat = tris.material[prim]
        weight = rays.weight[idx]
        pixel = rays.pixel[idx]

        texel = np.ones((idx.size, 3), np.float32)
        if tris.uvs.shape[0]:
            for mid in np.unique(mat):
                tex = m.texture[mid]
                if tex is None:
                    continue
                sel = mat == mid
                c = tris.uvs[prim[sel]]
                uv = (1 - u[sel] - v[sel]) * c[:, 0] + u[sel] * c[:, 1] + v[sel] * c[:, 2]
                texel[sel] = sample_texture(tex, uv)

        color = np.asarray(scene.ambient_light, np.float32) * m.ambient[mat] * texel
        leave = offset_origin(p, ng_ff, magnitude)
        width, height, n = self.config.render.width, self.config.render.height, self.config.render.packet
        ns = np.ascontiguousarray(ns, np.float32)
        ng_ff = np.ascontiguousarray(ng_ff, np.float32)
        leave = np.ascontiguousarray(leave, np.float32)
        view = np.ascontiguousarray(d, np.float32)
        l = np.empty_like(leave)
        dist = np.empty(idx.size, np.float32)
        ndotl = np.empty(idx.size, np.float32)
        lit = np.empty(idx.size, np.bool_)
        shadow_tmin = np.zeros(idx.size, np.float32)
        shadow_weight = np.ones((idx.size, 3), np.float32)
        for light in scene.lights:
            light_directions(leave, ns, ng_ff, np.asarray(light.position, np.float32), l, dist, ndotl, lit)
            cand = np.flatnonzero(lit)
            if cand.size == 0:
                continue
            gather, shadow_packets = packet_order(pixel[cand], width, height, n)
            # Lanes index the batch's hits directly (cand[gather]): no intermediate copies.
            shadow = gather_batch("shadow", np.where(gather >= 0, cand[np.maximum(gather, 0)], -1), leave, l,
                                  shadow_tmin, dist * SHADOW_TMAX_SCALE, pixel, shadow_weight)
            occluded = self._trace("shadow", shadow, shadow_packets, "occluded", tally)
            visible = cand[gather[(gather >= 0) & ~occluded]]
            add_light(color, visible, ns, l, ndotl, view, mat, m.diffuse, m.specular, m.shininess, texel,
                      np.asarray(light.color, np.float32))
        np.add.at(image, pixel, weight * color)
        if not spawn:
            return {"reflection": empty, "refraction": empty}

        # Reflection about the shading normal; fall back to the geometric one when the
        # interpolated normal would send the ray into the surface.
        cos_i = -np.einsum("ij,ij->i", d, ns)
        refl = d + 2 * cos_i[:, None] * ns
        bad = np.einsum("ij,ij->i", refl, ng_ff) <= 0
        cos_g = -np.einsum("ij,ij->i", d, ng_ff)
        refl[bad] = d[bad] + 2 * cos_g[bad, None] * ng_ff[bad]
        refl_w = weight * m.reflectance[mat]
        want_refl = (refl_w.max(axis=1) > MIN_WEIGHT) & reflect

        trans = m.transmission[mat]
        want_trans = (trans > 0) & (weight.max(axis=1) * trans > MIN_WEIGHT)
        eta = np.where(entering, 1.0 / m.ior[mat], m.ior[mat]).astype(np.float32)
        k = 1 - eta * eta * (1 - cos_i * cos_i)
        tir = want_trans & (k < 0)
        ok = want_trans & ~tir
        refr = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * ns
        refr_bad = ok & (np.einsum("ij,ij->i", refr, ng_ff) >= 0)
        refr[refr_bad] = d[refr_bad]  # grazing smooth-normal case: continue straight through
        trans_w = weight * trans[:, None]
        enter = offset_origin(p, -ng_ff, magnitude)

        r_sel = np.flatnonzero(want_refl)
        t_sel = np.flatnonzero(tir)
        o_sel = np.flatnonzero(ok)
        reflection = (np.concatenate([leave[r_sel], leave[t_sel]]),
                      np.concatenate([refl[r_sel], refl[t_sel]]).astype(np.float32),
                      np.concatenate([pixel[r_sel], pixel[t_sel]]),
                      np.concatenate([refl_w[r_sel], trans_w[t_sel]]))
        refraction = (enter[o_sel], refr[o_sel].astype(np.float32), pixel[o_sel], trans_w[o_sel])
        return {"reflection": reflection, "refraction": refraction}
