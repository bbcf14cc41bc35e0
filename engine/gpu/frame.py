"""The Whitted frame on the GPU: a wavefront of kernels over compacted ray queues.

One generation of rays (the camera rays first, then each generation of reflections and
refractions) is one queue in device memory, and goes through four kernels:

1. ``trace``            closest hits, by the configured device traversal (``bvh``/``rayspace``);
2. ``_shade``           misses add the background; hits fill their Surface row, the ambient
                        term and, per light, the light's direction; each lit (lane, light) pair
                        appends its shadow ray to the generation's shadow queue;
3. ``trace``            any hit over the shadow queue;
4. ``_light_and_spawn`` the unshadowed lights into the lane's colour (lights in file order), the
                        colour into the image, and the lane's children (mirror reflection, total
                        internal reflection, refraction) appended to the next generation's queue.

Queues are compacted as they are written: a thread appends with an atomic counter that stays on
the device, and every kernel loops over its queue up to that counter (grid-stride), so the host
enqueues a whole frame without waiting for the GPU once; the image is copied back at the end.
Queue capacities are fixed per frame size; a generation that would overflow is detected from
the counters at the end of the frame, and the frame is rendered again with room for it.

Steps 2 and 4 call the CPU renderer's own per-lane functions (``fill_surface_lane``, ``texel_color_lane``,
``light_direction_lane``, ``add_light_lane``, ``spawn_lane``, ``camera_direction``) compiled
for the device (``engine.gpu.twin``): one shading definition, two targets. Pixels receive their
contributions through atomic adds, in whatever order the device runs them.

Arrays travel to kernels packed in a few stacks (``(k, C, 3)`` and ``(k, C)``), unpacked inside:
a numba launch costs a few microseconds per array argument.

With an ``observer`` (the audit), each traced queue and its answers are copied to the host and
handed over as ``RayBatch``es per ray kind, as the CPU loop hands over its batches.
"""
from __future__ import annotations

import functools
import time

import numpy as np

from engine.core.bvh import build_bvh
from engine.core.offset import triangle_magnitudes
from engine.core.triangle import safe_inverse
from engine.core.types import RAY_KINDS, Hits, Packets, RayBatch
from engine.gpu.device import BLOCK, DeviceUnavailable, device_name, require_cuda
from engine.gpu.launch import PreparedLaunch
from engine.gpu.refit import DeviceRefit
from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles, upload
from engine.gpu.traversals import device_traversals
from engine.gpu.twin import device_twin
from engine.render.camera import camera_direction, direction_through, image_plane, image_x, image_y
from engine.render.direct_light import add_light_lane, light_direction_lane
from engine.render.materials import MaterialTable
from engine.render.spawn import spawn_lane
from engine.render.surface import dot3, fill_surface_lane, texel_at, texel_color_lane, unit_wrap
from engine.render.whitted import RenderResult

cuda = require_cuda()

_dot3 = device_twin(dot3)
_texel_at = device_twin(texel_at, unit_wrap=device_twin(unit_wrap))
_surface = device_twin(fill_surface_lane, dot3=_dot3, texel_at=_texel_at)
_texel_color = device_twin(texel_color_lane)
_light_direction = device_twin(light_direction_lane)
_add_light = device_twin(add_light_lane)
_spawn = device_twin(spawn_lane, dot3=_dot3)
_camera_direction = device_twin(camera_direction, image_x=device_twin(image_x), image_y=device_twin(image_y),
                                direction_through=device_twin(direction_through))

#: Queue kinds, as stored in a queue's ``kind`` array.
PRIMARY, REFLECTION, REFRACTION = 0, 1, 2
KIND_NAMES = ("primary", "reflection", "refraction")
#: Camera rays are issued in square tiles of this many pixels a side, so a warp's 32 rays are
#: two rows of 16 neighbouring pixels.
TILE = 16
#: Secondary queues hold this many rays per pixel before a frame is rendered again bigger.
SECONDARY_PER_PIXEL = 2
#: Most blocks a grid-stride kernel is launched with (enough to fill any current GPU).
MAX_BLOCKS = 8192
# Rows of the packed stacks.
Q_ORG, Q_DIR, Q_WEIGHT = 0, 1, 2                      # queue vectors f32[3, C, 3]
Q_TMIN, Q_TMAX = 0, 1                                 # queue scalars f32[2, C]
S_POINT, S_VIEW, S_NORMAL, S_FACING, S_TEXEL, S_COLOR, S_LEAVE = range(7)   # surface vectors
C_REFLECT_DIR, C_REFRACT_DIR, C_REFLECT_WEIGHT, C_TRANSMIT_WEIGHT, C_ENTER = range(5)  # children
L_DIST, L_NDOTL, L_SHADOW_TMAX = 0, 1, 2              # per-light scalars f32[3, L, C]


def grid(bound: int) -> int:
    """Blocks of a grid-stride launch over at most ``bound`` items."""
    return max(1, min(MAX_BLOCKS, -(-int(bound) // BLOCK)))


@cuda.jit
def _camera(eye, basis, half_w, half_h, width, height, q_vec, q_scalar, q_pixel, q_kind, counts):
    """The camera queue: rays tile by tile (TILE x TILE, row by row), row by row in a tile.
    basis: f64[3,3] forward, right, up."""
    if cuda.grid(1) == 0:
        counts[0] = width * height
    for r in range(cuda.grid(1), width * height, cuda.gridsize(1)):
        # Whole bands of TILE rows lie above; inside a band, tiles are TILE wide (the last
        # narrower) and as tall as the band (the last band shorter).
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
        dx, dy, dz = _camera_direction(x, y, width, height, basis[0], basis[1], basis[2], half_w, half_h)
        for a in range(3):
            q_vec[Q_ORG, r, a] = eye[a]
            q_vec[Q_WEIGHT, r, a] = np.float32(1.0)
        q_vec[Q_DIR, r, 0], q_vec[Q_DIR, r, 1], q_vec[Q_DIR, r, 2] = dx, dy, dz
        q_scalar[Q_TMIN, r] = np.float32(0.0)
        q_scalar[Q_TMAX, r] = np.float32(np.inf)
        q_pixel[r] = y * width + x
        q_kind[r] = PRIMARY


@cuda.jit
def _shade(counts, gen, q_vec, q_pixel, hit_tuv, hit_prim, tri_vec, normals, uvs, tri_material, corner_magnitude,
           has_normals, has_uvs, mat_vec, mat_texture, texels, palette, ambient_light, background, image,
           surf_vec, surf_magnitude, surf_flags, surf_material, n_lights, lights, light_dir, light_scalar, lit,
           shadow_slot, s_vec, s_scalar, s_pixel, s_capacity):
    """Surface rows of the hits of queue ``gen``, the background of its misses, and a shadow ray
    per lit (lane, light) appended to the shadow queue (its slot in shadow_slot[light, lane],
    -1 when none; the count in counts[2 gen + 1])."""
    n = min(counts[2 * gen], q_pixel.shape[0])
    dirs, weight = q_vec[Q_DIR], q_vec[Q_WEIGHT]
    t_u, t_v = hit_tuv[1], hit_tuv[2]
    hit, entering = surf_flags[0], surf_flags[1]
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        hit[i] = False
        for light in range(n_lights):
            shadow_slot[light, i] = -1
        p = hit_prim[i]
        if p < 0:
            for c in range(3):
                cuda.atomic.add(image, (q_pixel[i], c), weight[i, c] * background[c])
            continue
        hit[i] = True
        row = _surface(i, p, dirs, t_u, t_v, tri_vec[0], tri_vec[1], tri_vec[2], tri_vec[3], normals, uvs,
                       tri_material, corner_magnitude, (has_normals, has_uvs), mat_texture, surf_vec[S_POINT],
                       surf_magnitude, surf_vec[S_VIEW], surf_vec[S_NORMAL], surf_vec[S_FACING], entering,
                       surf_material, surf_vec[S_LEAVE])
        _texel_color(i, row, surf_material[i], texels, palette, ambient_light, mat_vec[0], surf_vec[S_TEXEL],
                     surf_vec[S_COLOR])
        for light in range(n_lights):
            _light_direction(i, surf_vec[S_LEAVE], surf_vec[S_NORMAL], surf_vec[S_FACING], lights[light],
                             light_dir[light], light_scalar[L_DIST, light], light_scalar[L_NDOTL, light],
                             lit[light], light_scalar[L_SHADOW_TMAX, light])
            if lit[light, i]:
                s = cuda.atomic.add(counts, 2 * gen + 1, 1)
                if s < s_capacity:
                    shadow_slot[light, i] = s
                    for a in range(3):
                        s_vec[0, s, a] = surf_vec[S_LEAVE, i, a]
                        s_vec[1, s, a] = light_dir[light, i, a]
                    s_scalar[0, s] = np.float32(0.0)
                    s_scalar[1, s] = light_scalar[L_SHADOW_TMAX, light, i]
                    s_pixel[s] = q_pixel[i]


@cuda.jit
def _light_and_spawn(counts, gen, q_vec, q_pixel, surf_vec, surf_magnitude, surf_flags, surf_material, mat_vec,
                     mat_scalar, n_lights, light_colors, light_dir, light_scalar, shadow_slot, occluded, image,
                     spawn, reflect, child_flags, child_vec, n_vec, n_scalar, n_pixel, n_kind, kind_count):
    """Lights into each hit lane's colour, the colour into the image and, with ``spawn``, the
    lane's children appended to the next queue (count in counts[2 gen + 2]; ``reflect``
    False: no mirror reflections)."""
    n = min(counts[2 * gen], q_pixel.shape[0])
    capacity = n_pixel.shape[0]
    weight = q_vec[Q_WEIGHT]
    hit = surf_flags[0]
    mirror, total_internal, refract = child_flags[0], child_flags[1], child_flags[2]
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        mirror[i] = False
        total_internal[i] = False
        refract[i] = False
        if not hit[i]:
            continue
        for light in range(n_lights):
            s = shadow_slot[light, i]
            if s >= 0 and occluded[s] == 0:
                _add_light(i, surf_vec[S_COLOR], surf_vec[S_NORMAL], light_dir[light], light_scalar[L_NDOTL, light],
                           surf_vec[S_VIEW], surf_material, mat_vec[1], mat_vec[2], mat_scalar[0],
                           surf_vec[S_TEXEL], light_colors[light])
        for c in range(3):
            cuda.atomic.add(image, (q_pixel[i], c), weight[i, c] * surf_vec[S_COLOR, i, c])
        if not spawn:
            continue
        _spawn(i, weight, surf_vec[S_POINT], surf_magnitude, surf_vec[S_VIEW], surf_vec[S_NORMAL],
               surf_vec[S_FACING], surf_flags[1], surf_material, mat_vec[3], mat_scalar[1], mat_scalar[2], reflect,
               mirror, total_internal, refract, child_vec[C_REFLECT_DIR], child_vec[C_REFRACT_DIR],
               child_vec[C_REFLECT_WEIGHT], child_vec[C_TRANSMIT_WEIGHT], child_vec[C_ENTER])
        for slot in range(3):
            if not (mirror[i] if slot == 0 else (total_internal[i] if slot == 1 else refract[i])):
                continue
            s = cuda.atomic.add(counts, 2 * gen + 2, 1)
            kind = REFRACTION if slot == 2 else REFLECTION
            cuda.atomic.add(kind_count, kind, 1)
            if s >= capacity:
                continue  # counted: the frame is rendered again with room for it
            for a in range(3):
                if slot == 2:
                    n_vec[Q_ORG, s, a] = child_vec[C_ENTER, i, a]
                    n_vec[Q_DIR, s, a] = child_vec[C_REFRACT_DIR, i, a]
                    n_vec[Q_WEIGHT, s, a] = child_vec[C_TRANSMIT_WEIGHT, i, a]
                else:
                    n_vec[Q_ORG, s, a] = surf_vec[S_LEAVE, i, a]
                    n_vec[Q_DIR, s, a] = child_vec[C_REFLECT_DIR, i, a]
                    n_vec[Q_WEIGHT, s, a] = child_vec[C_REFLECT_WEIGHT if slot == 0 else C_TRANSMIT_WEIGHT, i, a]
            n_scalar[Q_TMIN, s] = np.float32(0.0)
            n_scalar[Q_TMAX, s] = np.float32(np.inf)
            n_pixel[s] = q_pixel[i]
            n_kind[s] = kind


@cuda.jit
def _clear(image, rows, counts, kind_count):
    """Zero the image's first ``rows`` rows and every counter."""
    start = cuda.grid(1)
    if start < counts.shape[0]:
        counts[start] = 0
    if start < kind_count.shape[0]:
        kind_count[start] = 0
    for i in range(start, rows, cuda.gridsize(1)):
        for c in range(3):
            image[i, c] = np.float32(0.0)


class FrameArrays:
    """Every device array of a frame of ``pixels`` pixels and ``lights`` lights, allocated once
    and reused (allocation is slow). Secondary queues hold ``secondary`` rays; shadow queues
    ``lights`` times the largest queue."""

    def __init__(self, pixels: int, lights: int, depth: int, secondary: int):
        self.pixels, self.lights, self.secondary = pixels, lights, secondary
        c = max(pixels, secondary)
        rows = max(lights, 1)
        self.capacity = c
        self.shadow_capacity = c * lights
        a = cuda.device_array
        self.image = a((pixels, 3), np.float32)
        self.queues = [(a((3, c, 3), np.float32), a((2, c), np.float32), a(c, np.int32), a(c, np.int8))
                       for _ in range(2)]
        self.hit_tuv, self.hit_prim = a((3, c), np.float32), a(c, np.int32)
        self.surf_vec, self.surf_magnitude = a((7, c, 3), np.float32), a(c, np.float32)
        self.surf_flags, self.surf_material = a((2, c), np.bool_), a(c, np.int32)
        self.light_dir, self.light_scalar = a((rows, c, 3), np.float32), a((3, rows, c), np.float32)
        self.lit, self.shadow_slot = a((rows, c), np.bool_), a((rows, c), np.int32)
        s = max(self.shadow_capacity, 1)
        self.shadow = (a((2, s, 3), np.float32), a((2, s), np.float32), a(s, np.int32))
        self.occluded = a(s, np.uint8)
        self.child_flags, self.child_vec = a((3, c), np.bool_), a((5, c, 3), np.float32)
        # counts[2 g]: rays of generation g; counts[2 g + 1]: its shadow rays.
        self.counts = a(2 * (depth + 2), np.int32)
        self.kind_count = a(3, np.int32)
        # Views and events made once: making a device-array view or an event costs the host
        # tens of microseconds, and a frame would make dozens.
        self.count_views = [self.counts[k:k + 1] for k in range(self.counts.shape[0])]
        self.trace_views = [(v[Q_ORG], v[Q_DIR], sc[Q_TMIN], sc[Q_TMAX], px) for v, sc, px, _ in self.queues]
        self.hit_views = (self.hit_tuv[0], self.hit_prim, self.hit_tuv[1], self.hit_tuv[2])
        s_vec, s_scalar, s_pixel = self.shadow
        self.shadow_views = (s_vec[0], s_vec[1], s_scalar[0], s_scalar[1], s_pixel)
        self.events = [(cuda.event(), cuda.event()) for _ in range(2 * (depth + 1))]
        self.eye, self.basis = a(3, np.float32), a((3, 3), np.float64)  # this frame's camera


def frame_bytes(pixels: int, lights: int, secondary: int) -> int:
    """Device bytes ``FrameArrays`` takes: per queue row 53 bytes (two queues), per lane 156
    (hits, surface, children), per light and lane 29, per shadow-queue row 33."""
    rows = max(pixels, secondary)
    return pixels * 12 + rows * (2 * 53 + 156 + max(lights, 1) * 29) + rows * lights * 33


def check_device_memory(needed: int, pixels: int) -> None:
    """DeviceUnavailable (one line) when the GPU has less free memory than a frame needs."""
    free = cuda.current_context().get_memory_info().free
    if needed > free:
        raise DeviceUnavailable(f"a {pixels:,}-pixel frame needs about {needed / 2**30:.1f} GiB of GPU memory, "
                                f"more than the {free / 2**30:.1f} GiB free on the device; render smaller")


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
        self.device_name = device_name()
        self.arrays = None
        self.secondary_per_pixel = SECONDARY_PER_PIXEL
        #: None, or {launch name: [host seconds, launch-to-finish seconds, calls]} filled by
        #: frames rendered while it is set (each launch then waits for the GPU: profile only).
        self.profile = None
        self.scene = None
        self.set_scene(scene, bvh)

    def set_scene(self, scene, bvh=None) -> None:
        """Render ``scene`` from now on over ``bvh`` (None: build one). The first scene is
        uploaded; a later one of the same size (an animation's next frame) is copied into the
        same device arrays, and a refit of the uploaded tree is redone on the GPU from them
        (``engine.gpu.refit``, the same boxes as the CPU's refit), so the prepared launches stay
        valid. ``prepare_seconds`` holds the upload time (an animation
        counts it as the frame's acceleration-structure time)."""
        start = time.perf_counter()
        cfg = self.config.render
        replaced = False
        if self.scene is None or [id(m) for m in scene.materials] != [id(m) for m in self.scene.materials]:
            table = MaterialTable(scene.materials)
            self.mat_vec = upload(np.stack([table.ambient, table.diffuse, table.specular, table.reflectance]))
            self.mat_scalar = upload(np.stack([table.shininess, table.transmission, table.ior]))
            self.mat_texture = upload(table.texture_layout)
            self.texels = upload(table.texels)
            self.palette = upload(table.palette)
            replaced = True
        self.scene = scene
        self.tris = scene.triangles
        self.bvh = bvh if bvh is not None else build_bvh(self.tris, leaf_size=cfg.leaf_size, bins=cfg.bins)
        magnitude = triangle_magnitudes(self.tris)
        if getattr(self, "device_tris", None) is not None and self.device_tris.fits(self.tris):
            self.device_tris.update(self.tris, magnitude)
        else:
            self.device_tris = DeviceTriangles.from_host(self.tris, magnitude)
            replaced = True
        if not replaced and self.device_bvh.same_topology(self.bvh):
            self.device_refit.refit(self.device_tris)  # the boxes recomputed on the GPU
            self.device_bvh.host_bvh = self.bvh
            # The 8-wide tree, collapsed again; one with another node count is made anew below.
            replaced = not all(self._tell_traversals("refit_from", self.bvh))
        else:
            self.device_bvh = DeviceBVH.from_host(self.bvh, self.tris)
            self.device_refit = DeviceRefit(self.bvh, self.device_bvh)
            replaced = True
        lights = scene.lights
        positions = np.array([l.position for l in lights], np.float32).reshape(-1, 3)
        colors = np.array([l.color for l in lights], np.float32).reshape(-1, 3)
        if not replaced and len(lights) == self.n_lights:
            for held, value in ((self.lights, positions), (self.light_colors, colors)):
                if value.size:
                    held.copy_to_device(value)
            self.ambient_light.copy_to_device(np.asarray(scene.ambient_light, np.float32))
            self.background.copy_to_device(np.asarray(scene.background, np.float32))
        else:
            self.n_lights = len(lights)
            self.lights, self.light_colors = upload(positions), upload(colors)
            self.ambient_light = upload(np.asarray(scene.ambient_light, np.float32))
            self.background = upload(np.asarray(scene.background, np.float32))
            replaced = True
        if replaced:
            self.traversal = device_traversals(self.config, self.device_bvh, self.device_tris, self.tris)
            self._plan_key = None  # the prepared launches hold the replaced arrays
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

    def _tell_traversals(self, method: str, *args) -> list:
        """Call ``method(*args)`` once on each distinct traversal of the frame that has it (kinds
        that name the same traversal share one instance); their answers, in no set order."""
        answers = []
        for traversal in {id(t): t for t in self.traversal.values()}.values():
            call = getattr(traversal, method, None)
            if call is not None:
                answers.append(call(*args))
        return answers

    def _frame_arrays(self, pixels: int) -> FrameArrays:
        depth = self.config.render.max_depth
        held = self.arrays
        if held is None or held.pixels != pixels or held.lights != self.n_lights or \
                held.counts.shape[0] < 2 * (depth + 2) or held.secondary < self.secondary_per_pixel * pixels:
            secondary = self.secondary_per_pixel * pixels
            self.arrays = None  # let the old arrays go before the new ones are asked for
            self._tell_traversals("forget_launches")  # and the launches a traversal prepared over them
            check_device_memory(frame_bytes(pixels, self.n_lights, secondary), pixels)
            self.arrays = FrameArrays(pixels, self.n_lights, depth, secondary)
            self._plan_key = None
        return self.arrays

    # -- the frame ----------------------------------------------------------------------------
    def render(self, size: tuple | None = None) -> RenderResult:
        """One frame on the device; ``size`` (width, height) overrides the config's."""
        cfg = self.config.render
        width, height = size or (cfg.width, cfg.height)
        pixels = width * height
        start = time.perf_counter()
        while True:
            f = self._frame_arrays(pixels)
            events = self._enqueue_frame(f, width, height)
            host_image = f.image.copy_to_host()  # synchronises: the frame is done
            counts = f.counts.copy_to_host()
            generations = counts[0::2]
            if generations.max() <= f.capacity and counts[1::2].max() <= f.shadow_capacity:
                break
            # A generation outgrew its queue: make room and render the frame again.
            self.secondary_per_pixel = int(np.ceil(generations.max() / pixels)) + 1
            start = time.perf_counter()
        kinds = f.kind_count.copy_to_host()
        rays = {"primary": pixels, "shadow": int(counts[1::2].sum()), "reflection": int(kinds[REFLECTION]),
                "refraction": int(kinds[REFRACTION])}
        total = time.perf_counter() - start
        trace_seconds = dict.fromkeys(RAY_KINDS, 0.0)
        for kind, begin, end in events:
            trace_seconds[kind] += begin.elapsed_time(end) / 1e3
        seconds = {"bvh": self.bvh.build_seconds, "trace": trace_seconds,
                   "shade": max(total - sum(trace_seconds.values()), 0.0), "total": total,
                   "plugin_build": self.prepare_seconds}
        extra = {"device": {"name": self.device_name, "traversal": {k: self.traversal[k].name for k in RAY_KINDS}}}
        for kind, traversal in self.traversal.items():
            if hasattr(traversal, "last"):  # the ray-space hierarchy's candidate counts per level
                extra.setdefault("rayspace", {})[kind] = traversal.stats
        return RenderResult(host_image.reshape(height, width, 3), seconds, rays, {}, {}, extra)

    def _enqueue_frame(self, f: FrameArrays, width: int, height: int) -> list:
        """Launch a whole frame into ``f``: this frame's camera into the device, then the steps
        of the frame's plan. Returns the (kind, begin, end) trace events."""
        eye, forward, right, up, half_w, half_h = image_plane(self.scene, width, height)
        f.eye.copy_to_device(eye.astype(np.float32))
        f.basis.copy_to_device(np.stack([forward, right, up]))
        events = []
        for name, step, kind in self._plan(f, width, height, half_w, half_h):
            if kind is None:
                self._launch(name, step)
                continue
            begin, end = f.events[len(events)]
            begin.record()
            self._launch(name, step)
            end.record()
            events.append((kind, begin, end))
        return events

    def _plan(self, f: FrameArrays, width: int, height: int, half_w: float, half_h: float) -> list:
        """[(name, step, traced kind or None)]: every launch of a frame of this size, in order,
        with arguments prepared once (``engine.gpu.launch``) and kept until the size, the
        arrays or the observer change."""
        key = (id(f), width, height, half_w, half_h, self.observer is not None, id(self.traversal))
        if getattr(self, "_plan_key", None) == key:
            return self._plan_steps
        cfg = self.config.render
        pixels = width * height
        steps = [("clear", PreparedLaunch(_clear, grid(pixels), BLOCK, (f.image, pixels, f.counts, f.kind_count)), None),
                 ("camera", PreparedLaunch(_camera, grid(pixels), BLOCK, (f.eye, f.basis, half_w, half_h, width, height,
                                                                         *f.queues[0], f.counts)), None)]
        bound = pixels
        for gen in range(cfg.max_depth + 1):
            spawn = gen < cfg.max_depth
            steps += self._generation_steps(f, gen, bound, spawn, gen < cfg.max_reflection_depth, width, height)
            if not spawn:
                break
            bound = min(3 * bound, f.capacity)
        self._plan_key, self._plan_steps = key, steps
        return steps

    def _launch(self, name: str, launch) -> None:
        """``launch()``; while profiling, timed on the host alone and to the GPU's finish."""
        if self.profile is None:
            launch()
            return
        cuda.synchronize()
        start = time.perf_counter()
        launch()
        host = time.perf_counter() - start
        cuda.synchronize()
        row = self.profile.setdefault(name, [0.0, 0.0, 0])
        row[0] += host
        row[1] += time.perf_counter() - start
        row[2] += 1

    def _generation_steps(self, f, gen, bound, spawn, reflect, width, height) -> list:
        """The steps of one generation: trace its queue (at most ``bound`` rays), shade it, trace
        its shadow rays, light it and write its children into the other queue."""
        queue, nxt = f.queues[gen % 2], f.queues[(gen + 1) % 2]
        q_vec, q_scalar, q_pixel, q_kind = queue
        t = self.device_tris
        # A secondary queue mixes reflections and refractions; it is traced by the reflection
        # traversal (the config's refraction entry applies when both kinds name the same one).
        kind = "primary" if gen == 0 else "reflection"
        steps = [(f"trace {kind}", self.traversal[kind].queue_launch(
            "closest", *f.trace_views[gen % 2], f.count_views[2 * gen], bound, width, height, *f.hit_views,
            secondary=gen > 0), kind)]
        if self.observer is not None:
            steps.append(("observe", functools.partial(self._observe_closest, f, gen, queue), None))
        steps.append(("shade", PreparedLaunch(_shade, grid(bound), BLOCK, (
            f.counts, gen, q_vec, q_pixel, f.hit_tuv, f.hit_prim, t.vec, t.normals, t.uvs, t.material, t.magnitude,
            t.has_normals, t.has_uvs, self.mat_vec, self.mat_texture, self.texels, self.palette, self.ambient_light,
            self.background, f.image, f.surf_vec, f.surf_magnitude, f.surf_flags, f.surf_material, self.n_lights,
            self.lights, f.light_dir, f.light_scalar, f.lit, f.shadow_slot, *f.shadow, f.shadow_capacity)), None))
        if self.n_lights:
            # With one light every shadow ray aims at it: the ray-space hierarchy then indexes
            # them reversed, leaving the light, as the paper does.
            light = tuple(self.scene.lights[0].position) if self.n_lights == 1 else None
            steps.append(("trace shadow", self.traversal["shadow"].queue_launch(
                "occluded", *f.shadow_views, f.count_views[2 * gen + 1], bound * self.n_lights, width, height,
                f.occluded, light=light), "shadow"))
            if self.observer is not None:
                steps.append(("observe", functools.partial(self._observe_shadow, f, gen), None))
        n_vec, n_scalar, n_pixel, n_kind = nxt
        steps.append(("light and spawn", PreparedLaunch(_light_and_spawn, grid(bound), BLOCK, (
            f.counts, gen, q_vec, q_pixel, f.surf_vec, f.surf_magnitude, f.surf_flags, f.surf_material, self.mat_vec,
            self.mat_scalar, self.n_lights, self.light_colors, f.light_dir, f.light_scalar, f.shadow_slot,
            f.occluded, f.image, spawn, reflect, f.child_flags, f.child_vec, n_vec, n_scalar, n_pixel, n_kind,
            f.kind_count)), None))
        return steps

    # -- the audit's view ---------------------------------------------------------------------
    def _observe_closest(self, f, gen, queue) -> None:
        """Hand each kind's rays of a traced queue, with their hits, to the observer."""
        n = min(int(f.counts[2 * gen:2 * gen + 1].copy_to_host()[0]), f.capacity)
        q_vec, q_scalar, q_pixel, q_kind = (a.copy_to_host() for a in queue)
        tuv, prim = f.hit_tuv.copy_to_host(), f.hit_prim.copy_to_host()
        kinds = q_kind[:n]
        for code, kind in enumerate(KIND_NAMES):
            chosen = np.flatnonzero(kinds == code)
            if chosen.size == 0:
                continue
            rays = host_batch(kind, q_vec[Q_ORG][chosen], q_vec[Q_DIR][chosen], q_scalar[Q_TMIN][chosen],
                              q_scalar[Q_TMAX][chosen], q_pixel[chosen], q_vec[Q_WEIGHT][chosen])
            hits = Hits(*(np.ascontiguousarray(a) for a in (tuv[0][chosen], prim[chosen], tuv[1][chosen],
                                                            tuv[2][chosen])))
            self.observer(kind, "intersect", rays, _one_packet(chosen.size), hits)

    def _observe_shadow(self, f, gen) -> None:
        n = min(int(f.counts[2 * gen + 1:2 * gen + 2].copy_to_host()[0]), f.shadow_capacity)
        if n == 0:
            return
        s_vec, s_scalar, s_pixel = (a.copy_to_host() for a in f.shadow)
        rays = host_batch("shadow", s_vec[0][:n], s_vec[1][:n], s_scalar[0][:n], s_scalar[1][:n], s_pixel[:n],
                          np.ones((n, 3), np.float32))
        self.observer("shadow", "occluded", rays, _one_packet(n), f.occluded[:n].copy_to_host().astype(bool))

    def with_counters(self, result: RenderResult) -> RenderResult:
        """The device kernels keep no traversal counters: ``result`` as it is."""
        return result


def host_batch(kind: str, org, dirs, tmin, tmax, pixel, weight) -> RayBatch:
    """A host RayBatch of one kind's rays copied from a queue."""
    dirs = np.ascontiguousarray(dirs, np.float32)
    return RayBatch(np.ascontiguousarray(org, np.float32), dirs, safe_inverse(dirs), np.ascontiguousarray(tmin),
                    np.ascontiguousarray(tmax), np.ascontiguousarray(pixel, np.int32),
                    np.ascontiguousarray(weight, np.float32), kind)


def _one_packet(r: int) -> Packets:
    """The whole batch as one packet (the oracles and the reference traversal ignore packets)."""
    return Packets(np.array([0, r], np.int32), 2, 1, 1)
