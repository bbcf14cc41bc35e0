"""The Whitted loop: the only shading code. Every traversal variant renders through it.

Generation by generation:

1. primary rays, made in packet order (``engine.render.camera``) -> closest hits;
2. the surface at every hit and the background of the misses (``engine.render.surface``);
3. for every point light, a shadow ray for each hit lane that faces it, kept in its own packet
   (compacted by ``engine.packet.compact``, or walked in the batch's own lanes when nearly every
   lane casts one) -> occlusion -> diffuse + Phong specular of the lit lanes
   (``engine.render.direct_light``);
4. the light into the image, and the children (``engine.render.spawn``): a reflection batch
   (mirror reflections, and total internal reflections) and a refraction batch, each built in
   the packets of the camera tiles the rays descend from, dead lanes compacted out;
5. repeat from 2 with the children, up to ``max_depth`` generations (mirror reflections only
   off hits of depth < ``max_reflection_depth``).

Everything between two traversals is a numba kernel, parallel over packets, on per-lane arrays
of the batch: nothing is sorted, no image-wide array is concatenated, and a pixel is written only
by the packet of its tile, so contributions need no atomics. The traversal and frustum for each
ray kind come from the config (new plugin instances per renderer, ``engine.render.plugins``);
every batch is cast through ``engine.render.tracer``, which times and counts it. Plugins that
trace a whole batch at once (Embree, the ray-space hierarchy) and the packet traversals all go
through this one loop and the same shading kernels.

A traversal plugin may define ``prepare(tris) -> seconds`` to build its own structure before
timing starts. ``observer(kind, query, rays, packets, answer)`` is called after every cast batch
(query "intersect" with Hits, or "occluded" with bool[R]); the audit and the benchmark use it.
An observer with ``wants_walk_order = True`` also gets ``from_end`` with each shadow batch: the
end such a batch is walked from (``engine.render.shadow_order``), so that a replay walks it so.
The arrays are views of the renderer's per-lane arrays, which later batches of the same frame
overwrite: an observer that keeps a batch keeps a copy (``engine.core.types.copied_batch``).
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np

from engine.core.bvh import build_bvh, scene_bounds
from engine.core.offset import triangle_magnitudes
from engine.core.scene import Scene
from engine.core.types import RAY_KINDS, Hits, Packets, RayBatch, stats_by_depth, stats_totals
from engine.packet.compact import compact_into_packets
from engine.render.camera import camera_batch
from engine.render.config import Config
from engine.render.direct_light import add_light, add_light_in_place, light_directions
from engine.render.materials import MaterialTable
from engine.render.plugins import configured
from engine.render.shadow_order import ShadowOrder
from engine.core.scratch import Scratch
from engine.core.threads import at_own_threads, thread_count
from engine.render.spawn import gather_and_spawn, new_children
from engine.render.surface import new_surface, shade_surface
from engine.render.surface_record import surface_records
from engine.render.tracer import Tally, Tracer

WARM_UP_SIZE = 32                           # pixels a side of the compile-absorbing warm-up frame
#: A light's shadow rays are walked in their parent batch's own lanes (no compaction) when at
#: least this fraction of the batch's lanes cast one. Compacting costs about 9 ns a ray on two
#: threads and the walk skips dead lanes cheaply (the frusta leave them out): on kitchen-paper
#: (the reflection batch's shadow rays, 78% lit) 0.7 against 0.9 saved 3.6 ms of compaction for
#: 0.7-1.3 ms more walk. On the default scene at 1024x1024 (its camera batch's shadow rays are
#: fewer than 70% lit) 0.3 against 0.7 saves 11 ms of compaction for 5 ms more walk: frames
#: 137.1 -> 130.8 ms (medians of 24, alternating); the kitchen and the Cornell box unchanged.
IN_PLACE_SHADOWS = 0.3


@dataclass
class RenderResult:
    """One render's image and measurements.

    image: f32[H,W,3] linear RGB. seconds: {"bvh", "trace": {kind: s}, "shade", "total",
    "plugin_build": {plugin: s}}. rays: {kind: live rays cast}. counters: {"ray_aabb" |
    "ray_tri" | "nodes": {kind: n}} and counters_by_depth (the same per BVH depth, lists), empty
    unless the render counted. extra: {kind: plugin statistics}. shadow_order: {"LIGHT/KIND":
    "surface" | "light" | "undecided"}, the end each light's shadow rays were walked from
    (``engine.render.shadow_order``). shadow_order_at_start: the renderer's ShadowOrder as the
    frame began (a counting pass replays the frame from it), or None. ``engine.render.report``
    turns it into the ``--stats`` document.
    """

    image: np.ndarray
    seconds: dict
    rays: dict
    counters: dict
    counters_by_depth: dict
    extra: dict = field(default_factory=dict)
    shadow_order: dict = field(default_factory=dict)
    shadow_order_at_start: object = field(default=None, repr=False, compare=False)

    def mrays_per_s(self) -> dict:
        return {k: (self.rays[k] / self.seconds["trace"][k] / 1e6 if self.seconds["trace"][k] > 0 else 0.0)
                for k in RAY_KINDS}


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

    def __init__(self, scene: Scene, config: Config, *, observer=None, count: bool = False, bvh=None):
        """``bvh``: a tree over ``scene.triangles`` to use (an animation keeps it current,
        ``engine.render.accel``); None builds one."""
        self.config = config
        self.observer = observer
        self.count = count
        # Kernels run on this many threads inside set_scene, warm_up and render only
        # (``at_own_threads``): the caller's own numba count is back when each returns.
        self.threads = thread_count(config.render.threads)
        self.traversal, self.frustum = configured(config)
        # Which end each light's shadow rays are walked from, learnt from frame to frame.
        self.shadow_order = ShadowOrder(config.render.shadow_order)
        self.in_place_shadows = IN_PLACE_SHADOWS  # the warm-up tries both sides of it
        # Per-lane arrays reused from frame to frame (fresh pages cost more than the shading).
        self.scratch = Scratch()
        self.scene = None
        self.set_scene(scene, bvh)

    @at_own_threads
    def set_scene(self, scene: Scene, bvh=None) -> None:
        """Render ``scene`` from now on (an animation's next frame: moved triangles, camera and
        lights) over ``bvh`` (None: build one), keeping the plugins and the scratch arrays.
        Plugins with their own acceleration structure (Embree) build it now, outside the timed
        trace; ``prepare_seconds`` says how long that took."""
        if self.scene is None or [id(m) for m in scene.materials] != [id(m) for m in self.scene.materials]:
            self.materials = MaterialTable(scene.materials)
        self.scene = scene
        self.tris = scene.triangles
        self.bvh = bvh if bvh is not None else build_bvh(self.tris, leaf_size=self.config.render.leaf_size,
                                                         bins=self.config.render.bins)
        self.bounds = scene_bounds(self.bvh)
        self.corner_magnitude = triangle_magnitudes(self.tris)  # for secondary-ray offsets
        t = self.tris
        self.surface_records = surface_records(t.v0, t.v1, t.v2, t.ng, t.normals, t.uvs, t.material,
                                               self.corner_magnitude)
        self.ambient_light = np.asarray(scene.ambient_light, np.float32)
        self.background = np.asarray(scene.background, np.float32)
        self.tracer = Tracer(self.bvh, self.tris, self.bounds, self.traversal, self.frustum)
        self.prepare_seconds = self.tracer.prepare()

    def _trace(self, kind, rays, packets, query, tally, slot):
        """Trace through the Tracer, answering into reused arrays under ``slot``."""
        r = rays.org.shape[0]
        take = self.scratch.allocator(slot)
        if query == "intersect":
            answer = Hits(take("t", r), take("prim", r, (), np.int32), take("u", r), take("v", r))
        else:
            answer = take("occluded", r, (), np.bool_)
        answer = self.tracer.trace(kind, query, rays, packets, tally, answer)
        if self.observer is not None:
            self.observer(kind, query, rays, packets, answer)
        return answer

    def _trace_shadow(self, light: int, kind: str, rays, packets, tally):
        """Occlusion of light ``light``'s shadow rays from hits of ``kind`` rays, walked from the
        end ``shadow_order`` chooses (or as a trial of both: ``engine.render.shadow_order``)."""
        orders = self.tracer.orders_any_hit("shadow")   # embree, single and rayspace ignore the end
        if orders:
            self.shadow_order.record(light, kind)
        trial = {} if self.shadow_order.wants_trial(light, kind) and orders else None
        occluded = self.tracer.trace("shadow", "occluded", rays, packets, tally,
                                     self.scratch.take(("shadow", "occluded"), rays.org.shape[0], (), np.bool_),
                                     from_end=self.shadow_order.from_light(light, kind), trial=trial)
        if trial is not None:
            self.shadow_order.add_trial(light, kind, trial)
        if self.observer is not None:
            if getattr(self.observer, "wants_walk_order", False):
                # The end such a batch is walked from from now on (a replay walks it so).
                self.observer("shadow", "occluded", rays, packets, occluded,
                              from_end=self.shadow_order.from_light(light, kind))
            else:
                self.observer("shadow", "occluded", rays, packets, occluded)
        return occluded

    # -- the loop ------------------------------------------------------------------------
    @at_own_threads
    def warm_up(self) -> float:
        """Compile (or load from numba's disk cache) the kernels this config uses, by small
        renders (WARM_UP_SIZE square, at least four packets a side, so that a shadow batch has
        the packets of a shadow-order trial) that no observer sees; returns their seconds, which
        ``packetrt render`` reports as ``seconds.compile``. The small image is rendered twice,
        with every shadow batch walked in place and with every one compacted, as a real frame's
        batches may go either way; what the trials learnt is then forgotten, so that the first
        real frame decides. A kernel only reached by rays the small image does not cast still
        compiles in the first frame."""
        side = max(WARM_UP_SIZE, 4 * self.config.render.packet)
        observer, self.observer = self.observer, None
        start = time.perf_counter()
        try:
            for in_place in (0.0, 2.0):
                self.in_place_shadows = in_place
                self.render(size=(side, side))
        finally:
            self.observer = observer
            self.in_place_shadows = IN_PLACE_SHADOWS
            self.shadow_order = ShadowOrder(self.config.render.shadow_order)
        return time.perf_counter() - start

    @at_own_threads
    def render(self, size: tuple | None = None) -> RenderResult:
        """One frame; ``size`` (width, height) overrides the config's image size."""
        cfg = self.config.render
        width, height = size or (cfg.width, cfg.height)
        tally = Tally(count=self.count)
        order_at_start = copy.deepcopy(self.shadow_order)   # a few small dicts
        start = time.perf_counter()
        image = np.zeros((width * height, 3), np.float32)
        batches = [camera_batch(self.scene, width, height, cfg.packet, self.scratch.allocator(("primary", 0)))]
        shade_seconds = 0.0
        for depth in range(cfg.max_depth + 1):
            spawn = depth < cfg.max_depth and self.materials.can_spawn
            parents = []
            for rays, packets in batches:
                slot = (rays.kind, depth % 2)  # a generation's arrays never overwrite its parents'
                hits = self._trace(rays.kind, rays, packets, "intersect", tally, slot)
                shade_start = time.perf_counter()
                trace_before = sum(tally.seconds.values())
                shaded = self._shade(rays, packets, hits, image, spawn, depth < cfg.max_reflection_depth, tally, slot)
                parents.append((rays, packets) + shaded)
                shade_seconds += time.perf_counter() - shade_start - (sum(tally.seconds.values()) - trace_before)
            if not spawn:
                break
            shade_start = time.perf_counter()
            batches = self._next_generation(parents, width, height, cfg.packet, (depth + 1) % 2)
            shade_seconds += time.perf_counter() - shade_start
            if not batches:
                break
        total = time.perf_counter() - start
        counters, by_depth, extra = _summarise_stats(tally.stats)
        seconds = {"bvh": self.bvh.build_seconds, "trace": tally.seconds, "shade": shade_seconds, "total": total,
                   "plugin_build": self.prepare_seconds}
        return RenderResult(image.reshape(height, width, 3), seconds, tally.rays, counters, by_depth, extra,
                            self.shadow_order.chosen(), order_at_start)

    @at_own_threads
    def with_counters(self, result: RenderResult) -> RenderResult:
        """``result`` with counters and plugin statistics from a second, counting render (so the
        timed render does not pay for counting) of the same frame: it starts from the shadow
        order ``result``'s frame started from, so it walks every shadow batch from the same end
        and makes the same trials (the counters of the first frame do not depend on how many
        frames followed it); the renderer's own order is left as it was."""
        count, self.count = self.count, True
        held = self.shadow_order
        if result.shadow_order_at_start is not None:
            self.shadow_order = copy.deepcopy(result.shadow_order_at_start)
        try:
            counted = self.render()
        finally:
            self.count = count
            self.shadow_order = held
        result.counters, result.counters_by_depth, result.extra = counted.counters, counted.counters_by_depth, counted.extra
        result.shadow_order = counted.shadow_order
        return result


    # -- shading: numba kernels over the batch's lanes ---------------------------------------
    def _shade(self, rays: RayBatch, packets: Packets, hits, image, spawn: bool, reflect: bool, tally, slot):
        """Add a traced batch's background, ambient and direct light to ``image`` (f32[W*H,3]),
        casting one shadow batch per light; returns (Surface, Children) of its lanes (children
        flags all False unless ``spawn``). ``reflect`` False: no mirror reflections. ``slot``:
        the scratch key of this batch's per-lane arrays."""
        m, tris, n = self.materials, self.tris, packets.size
        r = rays.org.shape[0]
        take = self.scratch.allocator(slot)
        surface = new_surface(r, take)
        shade_surface(packets.offsets, rays.dir, rays.pixel, rays.weight, hits.prim, hits.u, hits.v,
                      tris.v0, tris.v1, tris.v2, tris.ng, tris.normals, tris.uvs, tris.material,
                      self.corner_magnitude, self.surface_records, m.ambient, m.texture_layout, m.texels, m.palette, self.ambient_light,
                      self.background, image, *surface)
        if self.scene.lights:
            light = self.scratch.allocator("light")
            to_light, inv_to_light = light("to_light", r, (3,)), light("inv_to_light", r, (3,))
            dist, ndotl, shadow_tmax = light("dist", r), light("ndotl", r), light("shadow_tmax", r)
            lit = light("lit", r, (), np.bool_)
            unit_weight = self.scratch.constant(("light", "unit_weight"), r, 1.0, (3,))
            zero_tmin = self.scratch.constant(("light", "zero_tmin"), r, 0.0)
        for index, light in enumerate(self.scene.lights):
            lit_lanes = light_directions(surface.hit, surface.leave, surface.normal, surface.facing,
                                         np.asarray(light.position, np.float32), to_light, dist, ndotl, lit,
                                         shadow_tmax, inv_to_light)
            if lit_lanes == 0:
                continue  # no hit faces this light
            light_color = np.asarray(light.color, np.float32)
            if lit_lanes >= self.in_place_shadows * r:
                # Enough lanes cast a shadow ray (``IN_PLACE_SHADOWS``): walk them in this batch's
                # own lanes and packets (the unlit ones dead) rather than copy them into
                # compacted packets.
                shadow = RayBatch(surface.leave, to_light, inv_to_light, zero_tmin, shadow_tmax, rays.pixel,
                                  unit_weight, "shadow")
                occluded = self._trace_shadow(index, rays.kind, shadow, packets, tally)
                add_light_in_place(surface.color, lit, occluded, surface.normal, to_light, ndotl, surface.view,
                                   surface.material, m.diffuse, m.specular, m.shininess, surface.texel, light_color)
                continue
            offsets, org, dirs, inv, tmin, tmax, pixel, weight, _, lane = compact_into_packets(
                n, packets.width, packets.height, (packets.offsets,), (rays.pixel,), (lit,), (surface.leave,),
                (to_light,), (shadow_tmax,), (unit_weight,), self.scratch.allocator("shadow"))
            shadow = RayBatch(org, dirs, inv, tmin, tmax, pixel, weight, "shadow")
            occluded = self._trace_shadow(index, rays.kind, shadow, Packets(offsets, n, packets.width, packets.height),
                                          tally)
            add_light(surface.color, lane, occluded, surface.normal, to_light, ndotl, surface.view,
                      surface.material, m.diffuse, m.specular, m.shininess, surface.texel, light_color)
        children = new_children(r, take)
        gather_and_spawn(packets.offsets, rays.pixel, rays.weight, surface.hit, surface.point, surface.magnitude,
                         surface.view, surface.normal, surface.facing, surface.entering, surface.material,
                         surface.color, m.reflectance, m.transmission, m.ior, image, spawn, reflect, *children)
        return surface, children

    def _next_generation(self, parents, width: int, height: int, n: int, parity: int) -> list:
        """The reflection and refraction batches of the next generation, each with its packets:
        the children of every parent batch (rays, packets, Surface, Children), merged in the
        packets of their camera tiles, in the scratch slots of generation ``parity``. Kinds with
        no child are left out."""
        reflection = {"offsets": [], "pixel": [], "flag": [], "org": [], "dir": [], "tmax": [], "weight": []}
        refraction = {key: [] for key in reflection}

        def source(into, rays, packets, flag, org, direction, tmax, weight):
            for key, value in zip(into, (packets.offsets, rays.pixel, flag, org, direction, tmax, weight)):
                into[key].append(value)

        for rays, packets, surface, children in parents:
            endless = self.scratch.constant(("endless", rays.kind), rays.org.shape[0], np.inf)
            source(reflection, rays, packets, children.mirror, surface.leave, children.reflect_dir, endless,
                   children.reflect_weight)
            source(reflection, rays, packets, children.total_internal, surface.leave, children.reflect_dir,
                   endless, children.transmit_weight)
            source(refraction, rays, packets, children.refract, children.enter, children.refract_dir, endless,
                   children.transmit_weight)
        batches = []
        for kind, sources in (("reflection", reflection), ("refraction", refraction)):
            if not sources["offsets"]:
                continue
            offsets, org, dirs, inv, tmin, tmax, pixel, weight, _, _ = compact_into_packets(
                n, width, height, *(tuple(sources[key]) for key in sources),
                allocate=self.scratch.allocator((kind, parity)))
            if offsets.shape[0] > 1:
                batches.append((RayBatch(org, dirs, inv, tmin, tmax, pixel, weight, kind),
                                Packets(offsets, n, width, height)))
        return batches
