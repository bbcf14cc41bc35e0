"""The Whitted frame on the GPU: a wavefront of kernels over compacted ray queues.

One generation of rays (the camera rays first, then each generation of reflections and
refractions) is one queue of n rays in device memory, and goes through:

1. ``trace.closest``                 the configured device traversal (``bvh`` or ``rayspace``);
2. ``_shade``                        misses add the background; hits fill their Surface row and,
                                     per light, the light's direction and whether it faces it;
3. a prefix sum of the lit flags     -> the shadow queue, in (light, lane) order;
4. ``trace.occluded``                over the shadow queue;
5. ``_light_and_spawn``              the unshadowed lights into the lane's colour, the colour into
                                     the image, and the lane's children (mirror, total internal
                                     reflection, refraction) flagged;
6. a prefix sum of the child flags   -> the next generation's queue, in parent order.

Steps 2 and 5 call the CPU renderer's own per-lane functions (``fill_surface_lane``,
``light_direction_lane``, ``add_light_lane``, ``spawn_lane``, ``camera_direction``) compiled
for the device (``engine.gpu.twin``): one shading definition, two targets, the same float32
and float64 expressions in the same order, so the two images differ only where floating-point
sums reach a pixel in another order (the GPU adds a pixel's contributions with atomics).
Queues are compacted by stable prefix sums (``engine.gpu.scan``), so rays keep their parents'
pixel order: warps stay coherent and the frame is deterministic up to that summation order.
The image is copied back once per frame.

With an ``observer`` (the audit), every traced queue and its answers are copied to the host and
handed over as a ``RayBatch`` in one packet, exactly as the CPU loop does with its batches.
"""
from __future__ import annotations

import time

import numpy as np

from engine.core.bvh import build_bvh
from engine.core.offset import triangle_magnitudes
from engine.core.triangle import safe_inverse
from engine.core.types import RAY_KINDS, Hits, Packets, RayBatch
from engine.gpu.device import BLOCK, blocks, device_name, require_cuda
from engine.gpu.scan import Scanner
from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles, upload
from engine.gpu.traversals import device_traversals
from engine.gpu.twin import device_twin
from engine.render.camera import camera_direction, image_plane
from engine.render.direct_light import add_light_lane, light_direction_lane
from engine.render.materials import MaterialTable
from engine.render.spawn import CHILDREN_FIELDS as _CHILDREN, spawn_lane
from engine.render.surface import SURFACE_FIELDS as _SURFACE, dot3, fill_surface_lane, texel_at, unit_wrap
from engine.render.whitted import RenderResult

cuda = require_cuda()

_dot3 = device_twin(dot3)
_texel_at = device_twin(texel_at, unit_wrap=device_twin(unit_wrap))
_surface = device_twin(fill_surface_lane, dot3=_dot3, texel_at=_texel_at)
_light_direction = device_twin(light_direction_lane)
_add_light = device_twin(add_light_lane)
_spawn = device_twin(spawn_lane, dot3=_dot3)
_camera_direction = device_twin(camera_direction)

#: Queue kinds, as stored in a queue's ``kind`` array (index into RAY_KINDS order below).
PRIMARY, REFLECTION, REFRACTION = 0, 1, 2
KIND_NAMES = ("primary", "reflection", "refraction")
#: Camera rays are issued in square tiles of this many pixels a side, so a warp's 32 rays are
#: two rows of 16 neighbouring pixels.
TILE = 16
#: Children a lane may spawn: mirror reflection, total internal reflection, refraction.
CHILD_SLOTS = 3


@cuda.jit
def _camera(eye, forward, right, up, half_w, half_h, width, height, org, dirs, tmin, tmax, pixel, weight, kind):
    """The camera queue: rays tile by tile (TILE x TILE, row by row), row by row in a tile."""
    r = cuda.grid(1)
    if r >= width * height:
        return
    # Whole bands of TILE rows lie above; inside a band, tiles are TILE wide (the last narrower)
    # and as tall as the band (the last band shorter).
    bands = (height + TILE - 1) // TILE
    band = min(r // (TILE * width), bands - 1)
    in_band = r - band * TILE * width
    band_h = min(TILE, height - band * TILE)
    tiles_x = (width + TILE - 1) // TILE
    tx = min(in_band // (TILE * band_h), tiles_x - 1)
    local = in_band - tx * TILE * band_h
    tile_w = min(TILE, width - tx * TILE)
    y = band * TILE + local // tile_w
    x = tx * TILE + local % tile_w
    dx, dy, dz = _camera_direction(x, y, width, height, forward, right, up, half_w, half_h)
    org[r, 0], org[r, 1], org[r, 2] = eye[0], eye[1], eye[2]
    dirs[r, 0], dirs[r, 1], dirs[r, 2] = dx, dy, dz
    tmin[r] = np.float32(0.0)
    tmax[r] = np.float32(np.inf)
    pixel[r] = y * width + x
    for c in range(3):
        weight[r, c] = np.float32(1.0)
    kind[r] = PRIMARY


@cuda.jit
def _shade(n, dirs, pixel, weight, prim, u, v,
           v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude, has_normals, has_uvs,
           ambient, texture_start, texture_width, texture_height, texels, ambient_light, background, image,
           hit, point, magnitude, view, normal, facing, entering, material, texel, color, leave,
           n_lights, lights, to_light, dist, ndotl, lit, shadow_tmax, shadow_flag):
    """Surface rows of the hits of queue [0, n), background of its misses, and per light l the
    lit flag of lane i in shadow_flag[l * n + i] (i32, for the shadow queue's prefix sum)."""
    i = cuda.grid(1)
    if i >= n:
        return
    hit[i] = False
    for light in range(n_lights):
        shadow_flag[light * n + i] = 0
    p = prim[i]
    if p < 0:
        for c in range(3):
            cuda.atomic.add(image, (pixel[i], c), weight[i, c] * background[c])
        return
    hit[i] = True
    _surface(i, p, dirs, u, v, v0, v1, v2, ng, normals, uvs, tri_material, corner_magnitude, has_normals, has_uvs,
             ambient, texture_start, texture_width, texture_height, texels, ambient_light, point, magnitude, view,
             normal, facing, entering, material, texel, color, leave)
    for light in range(n_lights):
        _light_direction(i, leave, normal, facing, lights[light], to_light[light], dist[light], ndotl[light],
                         lit[light], shadow_tmax[light])
        shadow_flag[light * n + i] = 1 if lit[light, i] else 0


@cuda.jit
def _shadow_queue(n_flags, n, shadow_flag, offsets, leave, to_light, shadow_tmax, pixel,
                  s_org, s_dir, s_tmin, s_tmax, s_pixel):
    """Shadow ray of every lit (light, lane) pair j = light * n + lane at slot offsets[j]."""
    j = cuda.grid(1)
    if j >= n_flags or shadow_flag[j] == 0:
        return
    light, i = j // n, j % n
    s = offsets[j]
    for a in range(3):
        s_org[s, a] = leave[i, a]
        s_dir[s, a] = to_light[light, i, a]
    s_tmin[s] = np.float32(0.0)
    s_tmax[s] = shadow_tmax[light, i]
    s_pixel[s] = pixel[i]


@cuda.jit
def _light_and_spawn(n, pixel, weight, hit, point, magnitude, view, normal, facing, entering, material, texel,
                     color, diffuse, specular, shininess, reflectance, transmission, ior, n_lights, light_colors,
                     to_light,
                     ndotl, shadow_flag, shadow_offsets, occluded, image, spawn, reflect,
                     mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight, transmit_weight,
                     enter, child_flag):
    """Lights in file order into each hit lane's colour, the colour into the image, and the
    children flags child_flag[CHILD_SLOTS * i + (0 mirror, 1 total internal, 2 refraction)]."""
    i = cuda.grid(1)
    if i >= n:
        return
    mirror[i] = False
    total_internal[i] = False
    refract[i] = False
    if hit[i]:
        for light in range(n_lights):
            j = light * n + i
            if shadow_flag[j] != 0 and occluded[shadow_offsets[j]] == 0:
                _add_light(i, color, normal, to_light[light], ndotl[light], view, material, diffuse, specular,
                           shininess, texel, light_colors[light])
        for c in range(3):
            cuda.atomic.add(image, (pixel[i], c), weight[i, c] * color[i, c])
        if spawn:
            _spawn(i, weight, point, magnitude, view, normal, facing, entering, material, reflectance, transmission,
                   ior, reflect, mirror, total_internal, refract, reflect_dir, refract_dir, reflect_weight,
                   transmit_weight, enter)
    child_flag[CHILD_SLOTS * i] = 1 if mirror[i] else 0
    child_flag[CHILD_SLOTS * i + 1] = 1 if total_internal[i] else 0
    child_flag[CHILD_SLOTS * i + 2] = 1 if refract[i] else 0


@cuda.jit
def _next_queue(n_flags, child_flag, offsets, pixel, leave, enter, reflect_dir, refract_dir, reflect_weight,
                transmit_weight, org, dirs, tmin, tmax, c_pixel, c_weight, c_kind, kind_count):
    """Child j = CHILD_SLOTS * lane + slot at offsets[j] of the next queue; counts per kind."""
    j = cuda.grid(1)
    if j >= n_flags or child_flag[j] == 0:
        return
    i, slot = j // CHILD_SLOTS, j % CHILD_SLOTS
    s = offsets[j]
    for a in range(3):
        if slot == 2:
            org[s, a] = enter[i, a]
            dirs[s, a] = refract_dir[i, a]
            c_weight[s, a] = transmit_weight[i, a]
        else:
            org[s, a] = leave[i, a]
            dirs[s, a] = reflect_dir[i, a]
            c_weight[s, a] = reflect_weight[i, a] if slot == 0 else transmit_weight[i, a]
    tmin[s] = np.float32(0.0)
    tmax[s] = np.float32(np.inf)
    c_pixel[s] = pixel[i]
    kind = REFRACTION if slot == 2 else REFLECTION
    c_kind[s] = kind
    cuda.atomic.add(kind_count, kind, 1)


class _Buffers:
    """Device arrays grown on demand and reused from frame to frame (allocation is slow)."""

    def __init__(self):
        self.arrays = {}

    def take(self, name, rows, tail=(), dtype=np.float32):
        """A device array of at least ``rows`` rows (shape (capacity,) + tail), reused."""
        held = self.arrays.get(name)
        if held is None or held.shape[0] < rows or held.shape[1:] != tuple(tail) or held.dtype != dtype:
            capacity = max(int(rows), 1)
            if held is not None:
                capacity = max(capacity, held.shape[0] * 3 // 2)
            held = cuda.device_array((capacity,) + tuple(tail), dtype)
            self.arrays[name] = held
        return held


class _Queue:
    """A generation's rays on the device: org, dirs f32[C,3], tmin, tmax f32[C], pixel i32[C],
    weight f32[C,3], kind i8[C]; the first ``n`` are live."""

    FIELDS = {"org": ((3,), np.float32), "dirs": ((3,), np.float32), "tmin": ((), np.float32),
              "tmax": ((), np.float32), "pixel": ((), np.int32), "weight": ((3,), np.float32),
              "kind": ((), np.int8)}

    def __init__(self, buffers: _Buffers, slot: int, rows: int):
        for name, (tail, dtype) in self.FIELDS.items():
            setattr(self, name, buffers.take(f"queue{slot}.{name}", rows, tail, dtype))
        self.n = 0

    def to_host(self, n: int):
        return {name: getattr(self, name)[:n].copy_to_host() for name in self.FIELDS}


def host_batch(kind: str, fields: dict) -> tuple:
    """(RayBatch, Packets) on the host of one kind's rays from a copied queue (one packet)."""
    org = np.ascontiguousarray(fields["org"], np.float32)
    dirs = np.ascontiguousarray(fields["dirs"], np.float32)
    r = org.shape[0]
    rays = RayBatch(org, dirs, safe_inverse(dirs), np.ascontiguousarray(fields["tmin"]),
                    np.ascontiguousarray(fields["tmax"]), np.ascontiguousarray(fields["pixel"], np.int32),
                    np.ascontiguousarray(fields["weight"], np.float32), kind)
    return rays, Packets(np.array([0, r], np.int32), 2, 1, 1)


class GpuWhittedRenderer:
    """Renders one scene with one config on the CUDA device. Build once, ``render()`` often.

    The traversal per ray kind comes from the config by name (``engine.gpu.traversals``); the
    BVH is built by the CPU builder and uploaded (or given, for an animation that refits it).
    """

    device = "cuda"

    def __init__(self, scene, config, *, observer=None, count: bool = False, bvh=None):
        self.config = config
        self.observer = observer
        self.count = count
        self.buffers = _Buffers()
        self.scanner = Scanner()
        self.device_name = device_name()
        self.scene = None
        self.set_scene(scene, bvh)

    def set_scene(self, scene, bvh=None) -> None:
        """Render ``scene`` from now on over ``bvh`` (None: build one); uploads triangles, tree,
        materials and lights. ``prepare_seconds`` holds the upload time (outside the frame)."""
        start = time.perf_counter()
        cfg = self.config.render
        if self.scene is None or [id(m) for m in scene.materials] != [id(m) for m in self.scene.materials]:
            table = MaterialTable(scene.materials)
            self.materials = {name: upload(getattr(table, name)) for name in (
                "ambient", "diffuse", "specular", "reflectance", "shininess", "transmission", "ior",
                "texture_start", "texture_width", "texture_height", "texels")}
        self.scene = scene
        self.tris = scene.triangles
        self.bvh = bvh if bvh is not None else build_bvh(self.tris, leaf_size=cfg.leaf_size, bins=cfg.bins)
        self.device_tris = DeviceTriangles.from_host(self.tris, triangle_magnitudes(self.tris))
        self.device_bvh = DeviceBVH.from_host(self.bvh)
        self.traversal = device_traversals(self.config, self.device_bvh, self.device_tris, self.tris)
        lights = scene.lights
        self.n_lights = len(lights)
        self.lights = upload(np.array([l.position for l in lights], np.float32).reshape(-1, 3))
        self.light_colors = upload(np.array([l.color for l in lights], np.float32).reshape(-1, 3))
        self.ambient_light = upload(np.asarray(scene.ambient_light, np.float32))
        self.background = upload(np.asarray(scene.background, np.float32))
        cuda.synchronize()
        self.prepare_seconds = {"upload": time.perf_counter() - start}

    def warm_up(self) -> float:
        """Compile every kernel by one small frame no observer sees; returns its seconds."""
        observer, self.observer = self.observer, None
        start = time.perf_counter()
        try:
            self.render(size=(TILE + 3, TILE + 1))
        finally:
            self.observer = observer
        return time.perf_counter() - start

    # -- the frame ----------------------------------------------------------------------------
    def render(self, size: tuple | None = None) -> RenderResult:
        """One frame on the device; ``size`` (width, height) overrides the config's."""
        cfg = self.config.render
        width, height = size or (cfg.width, cfg.height)
        start = time.perf_counter()
        take = self.buffers.take
        pixels = width * height
        image = take("image", pixels, (3,))
        _clear(image, pixels)
        kind_count = take("kind_count", 3, (), np.int32)
        kind_count.copy_to_device(np.zeros(kind_count.shape[0], np.int32))
        trace_events = []
        rays = dict.fromkeys(RAY_KINDS, 0)
        rays["primary"] = pixels

        queue = _Queue(self.buffers, 0, pixels)
        eye, forward, right, up, half_w, half_h = image_plane(self.scene, width, height)
        _camera[blocks(pixels), BLOCK](upload(eye.astype(np.float32)), upload(forward), upload(right), upload(up),
                                       half_w, half_h, width, height, queue.org, queue.dirs, queue.tmin, queue.tmax,
                                       queue.pixel, queue.weight, queue.kind)
        queue.n = pixels
        for depth in range(cfg.max_depth + 1):
            spawn = depth < cfg.max_depth
            queue = self._generation(queue, depth, spawn, depth < cfg.max_reflection_depth, image, width, height,
                                     trace_events, rays, kind_count)
            if queue is None:
                break
        host_image = image[:pixels].copy_to_host()  # synchronises: the frame is done
        counts = kind_count.copy_to_host()
        rays["reflection"], rays["refraction"] = int(counts[REFLECTION]), int(counts[REFRACTION])
        total = time.perf_counter() - start
        trace_seconds = dict.fromkeys(RAY_KINDS, 0.0)
        for kind, begin, end in trace_events:
            trace_seconds[kind] += begin.elapsed_time(end) / 1e3
        seconds = {"bvh": self.bvh.build_seconds, "trace": trace_seconds,
                   "shade": max(total - sum(trace_seconds.values()), 0.0), "total": total,
                   "plugin_build": self.prepare_seconds}
        return RenderResult(host_image.reshape(height, width, 3), seconds, rays, {}, {},
                            {"device": {"name": self.device_name, "traversal": {
                                k: self.traversal[k].name for k in RAY_KINDS}}})

    def _timed(self, events, kind, launch) -> None:
        """Run ``launch()`` between two CUDA events, kept for the trace time of ``kind``."""
        begin, end = cuda.event(), cuda.event()
        begin.record()
        launch()
        end.record()
        events.append((kind, begin, end))

    def _generation(self, queue, depth, spawn, reflect, image, width, height, events, rays, kind_count):
        """Trace and shade one queue; returns the next generation's queue (None: no children)."""
        n, take, m, t = queue.n, self.buffers.take, self.materials, self.device_tris
        # Primary rays are all of one kind; a secondary queue mixes reflections and refractions
        # and is traced by the reflection traversal unless the config gives refraction another.
        kind = "primary" if depth == 0 else "reflection"
        trace = self.traversal[kind]
        hits = Hits(take("t", n), take("prim", n, (), np.int32), take("u", n), take("v", n))
        self._timed(events, kind, lambda: trace.closest(queue.org, queue.dirs, queue.tmin, queue.tmax, queue.pixel,
                                                         n, width, height, hits.t, hits.prim, hits.u, hits.v))
        if self.observer is not None:
            self._observe_closest(queue, n, hits)
        surface = {name: take(f"surface.{name}", n, tail, dtype) for name, (tail, dtype) in _SURFACE.items()}
        lights = max(self.n_lights, 1)
        to_light, dist = take("to_light", lights * n, (3,)), take("dist", lights * n)
        ndotl, lit, shadow_tmax = take("ndotl", lights * n), take("lit", lights * n, (), np.bool_), \
            take("shadow_tmax", lights * n)
        per_light = [a[:lights * n].reshape((lights, n) + a.shape[1:]) for a in (to_light, dist, ndotl, lit,
                                                                                   shadow_tmax)]
        shadow_flag = take("shadow_flag", lights * n, (), np.int32)
        _shade[blocks(n), BLOCK](n, queue.dirs, queue.pixel, queue.weight, hits.prim, hits.u, hits.v,
                                 t.v0, t.v1, t.v2, t.ng, t.normals, t.uvs, t.material, t.magnitude, t.has_normals,
                                 t.has_uvs, m["ambient"], m["texture_start"], m["texture_width"],
                                 m["texture_height"], m["texels"], self.ambient_light, self.background, image,
                                 *surface.values(), self.n_lights, self.lights, *per_light, shadow_flag)
        n_flags = self.n_lights * n
        shadow_offsets = take("shadow_offsets", n_flags + 1, (), np.int32)
        n_shadow = self.scanner.exclusive_scan(shadow_flag, n_flags, shadow_offsets)
        occluded = take("occluded", n_shadow, (), np.uint8)
        if n_shadow:
            s = {name: take(f"shadow.{name}", n_shadow, tail, dtype) for name, (tail, dtype) in _Queue.FIELDS.items()
                 if name not in ("weight", "kind")}
            _shadow_queue[blocks(n_flags), BLOCK](n_flags, n, shadow_flag, shadow_offsets, surface["leave"],
                                                  per_light[0], per_light[4], queue.pixel, s["org"], s["dirs"],
                                                  s["tmin"], s["tmax"], s["pixel"])
            shadow = self.traversal["shadow"]
            self._timed(events, "shadow", lambda: shadow.occluded(s["org"], s["dirs"], s["tmin"], s["tmax"],
                                                                  s["pixel"], n_shadow, width, height, occluded))
            rays["shadow"] += n_shadow
            if self.observer is not None:
                self._observe_shadow(s, n_shadow, occluded)
        children = {name: take(f"child.{name}", n, tail, dtype) for name, (tail, dtype) in _CHILDREN.items()}
        child_flag = take("child_flag", CHILD_SLOTS * n, (), np.int32)
        _light_and_spawn[blocks(n), BLOCK](n, queue.pixel, queue.weight, surface["hit"], surface["point"],
                                           surface["magnitude"], surface["view"], surface["normal"],
                                           surface["facing"], surface["entering"], surface["material"],
                                           surface["texel"], surface["color"], m["diffuse"], m["specular"],
                                           m["shininess"], m["reflectance"], m["transmission"], m["ior"],
                                           self.n_lights, self.light_colors, per_light[0], per_light[2], shadow_flag,
                                           shadow_offsets, occluded, image, spawn, reflect, *children.values(),
                                           child_flag)
        if not spawn:
            return None
        child_offsets = take("child_offsets", CHILD_SLOTS * n + 1, (), np.int32)
        n_next = self.scanner.exclusive_scan(child_flag, CHILD_SLOTS * n, child_offsets)
        if n_next == 0:
            return None
        nxt = _Queue(self.buffers, (depth + 1) % 2, n_next)
        _next_queue[blocks(CHILD_SLOTS * n), BLOCK](CHILD_SLOTS * n, child_flag, child_offsets, queue.pixel,
                                                    surface["leave"], children["enter"], children["reflect_dir"],
                                                    children["refract_dir"], children["reflect_weight"],
                                                    children["transmit_weight"], nxt.org, nxt.dirs, nxt.tmin,
                                                    nxt.tmax, nxt.pixel, nxt.weight, nxt.kind, kind_count)
        nxt.n = n_next
        return nxt

    # -- the audit's view ---------------------------------------------------------------------
    def _observe_closest(self, queue, n, hits) -> None:
        """Hand each kind's rays of a traced queue, with their hits, to the observer."""
        fields = queue.to_host(n)
        answer = Hits(hits.t[:n].copy_to_host(), hits.prim[:n].copy_to_host(), hits.u[:n].copy_to_host(),
                      hits.v[:n].copy_to_host())
        for code, kind in enumerate(KIND_NAMES):
            chosen = np.flatnonzero(fields["kind"] == code)
            if chosen.size == 0:
                continue
            rays, packets = host_batch(kind, {k: v[chosen] for k, v in fields.items()})
            self.observer(kind, "intersect", rays, packets, Hits(*(np.ascontiguousarray(a[chosen]) for a in answer)))

    def _observe_shadow(self, s, n, occluded) -> None:
        fields = {name: s[name][:n].copy_to_host() for name in s}
        fields["weight"] = np.ones((n, 3), np.float32)
        rays, packets = host_batch("shadow", fields)
        self.observer("shadow", "occluded", rays, packets, occluded[:n].copy_to_host().astype(bool))

    def with_counters(self, result: RenderResult) -> RenderResult:
        """The device kernels keep no traversal counters: ``result`` as it is."""
        return result


@cuda.jit
def _zero_rows(image, rows):
    i = cuda.grid(1)
    if i < rows:
        for c in range(3):
            image[i, c] = np.float32(0.0)


def _clear(image, rows: int) -> None:
    _zero_rows[blocks(rows), BLOCK](image, rows)

