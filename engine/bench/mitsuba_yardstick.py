"""Mitsuba 3 as the GPU yardstick: its closest-hit and occlusion queries on the very same rays.

On a GPU the variant is ``cuda_ad_rgb`` (Dr.Jit's CUDA backend; Mitsuba traces with OptiX); any
other variant name works too -- ``llvm_ad_rgb`` (Embree inside Mitsuba, vectorised by Dr.Jit's
LLVM backend) and ``scalar_rgb`` (one ray per Python call: for correctness checks on a few rays,
never for timing) are how it is tested on a machine without a GPU. Mitsuba is optional: nothing
imports it until a yardstick is asked for, and ``mitsuba_available(variant)`` says in one line why
it cannot be used here (not installed; no CUDA driver; no libLLVM).

The scene is one ``Mesh`` shape made from the triangle soup (3T vertices, faces [3i, 3i+1, 3i+2],
written through ``mi.traverse``) in a scene dict with nothing else: no sensor, emitter or
integrator is needed to trace rays. Triangle i of our arrays is Mitsuba's ``prim_index`` i.

Segments. Mitsuba 3 rays have no ``mint``: ``Ray3f(o, d, maxt, time, wavelengths)`` is traced
from t = 0 (the backends' own epsilon aside) up to ``maxt``. Every ray the Whitted loop casts
has tmin = 0, and then the ray is passed as it is, maxt = tmax. A live ray with tmin != 0 is
moved to ``org + tmin * dir`` with maxt = tmax - tmin and tmin added back to the hit distance --
exactly what ``engine.core.embree_scene`` does for embreex, which has no tnear either, so the two
yardsticks see the same segments. An unbounded tmax becomes Mitsuba's own "no limit" (the
largest float32, ``Ray3f``'s default maxt). A dead lane (tmax < tmin, or NaN) is not traced
(``active`` is false) and is answered as a miss / not occluded. Directions are not normalised
(``Ray3f`` does not normalise either), so t is in units of ``dir`` as everywhere in packetrt.

Timing (``time_queries``): the rays are converted to Dr.Jit arrays once, outside the timed
region; each timed call builds the query's lazy graph, evaluates its outputs (``dr.eval``) and
waits for the device (``dr.sync_thread``). One untimed call first (Dr.Jit compiles the kernel and
caches it), then the median of ``repeats`` calls. What is timed is what a Mitsuba user pays for
one wavefront of rays: Python's trip through Dr.Jit's tracing, the kernel launch, the trace.
"""
from __future__ import annotations

import statistics
import time

import numpy as np

from engine.core.errors import ConfigError, PacketrtError

#: Mitsuba's own "no limit" on a ray (Ray3f's default maxt: the largest float32).
MITSUBA_MAXT = np.float32(np.finfo(np.float32).max)
QUERIES = ("closest", "occluded")


class MitsubaUnavailable(PacketrtError):
    """Mitsuba is not importable here, or the variant asked for cannot be set (one line why)."""


def load_mitsuba(variant: str):
    """The ``mitsuba`` module with ``variant`` set; MitsubaUnavailable (one line) if it cannot be."""
    try:
        import mitsuba as mi
    except Exception as exc:  # ImportError, or a bundled library that fails to load
        raise MitsubaUnavailable(f"mitsuba is not importable: {_one_line(exc)}") from None
    if variant not in mi.variants():
        raise MitsubaUnavailable(f"mitsuba {mi.__version__} has no variant {variant!r}; "
                                 f"it has: {', '.join(mi.variants())}")
    try:
        if mi.variant() != variant:
            mi.set_variant(variant)
    except Exception as exc:  # e.g. ImportError: "the CUDA backend hasn't been initialized"
        raise MitsubaUnavailable(f"mitsuba variant {variant!r} cannot be set: {_one_line(exc)}") from None
    return mi


def mitsuba_available(variant: str = "cuda_ad_rgb") -> str | None:
    """None if mitsuba imports and ``variant`` can be set here, else a one-line reason."""
    try:
        load_mitsuba(variant)
    except MitsubaUnavailable as exc:
        return str(exc)
    return None


def _one_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"


def _f32(array, shape_tail: tuple, what: str) -> np.ndarray:
    """``array`` as C-contiguous float32 of shape (R, *shape_tail); ConfigError otherwise."""
    out = np.ascontiguousarray(array, dtype=np.float32)
    if out.ndim != 1 + len(shape_tail) or out.shape[1:] != shape_tail:
        raise ConfigError(f"mitsuba yardstick: {what} must have shape (R{''.join(', ' + str(s) for s in shape_tail)}),"
                          f" got {out.shape}")
    return out


def segments(org, direction, tmin, tmax) -> tuple:
    """Our segments as Mitsuba rays: (origin f32[R,3], dir f32[R,3], maxt f32[R], shift f32[R],
    live bool[R]). org, direction: (R,3); tmin, tmax: (R,). ``shift`` (tmin of a live ray, else 0)
    is added back to a hit distance; a ray with tmin = 0 keeps its origin bit for bit."""
    org, direction = _f32(org, (3,), "org"), _f32(direction, (3,), "dir")
    tmin, tmax = _f32(tmin, (), "tmin"), _f32(tmax, (), "tmax")
    n = org.shape[0]
    if not (direction.shape[0] == tmin.shape[0] == tmax.shape[0] == n):
        raise ConfigError(f"mitsuba yardstick: org, dir, tmin, tmax disagree on the ray count "
                          f"({n}, {direction.shape[0]}, {tmin.shape[0]}, {tmax.shape[0]})")
    live = tmin <= tmax  # False for NaN too
    shift = np.where(live, tmin, np.float32(0)).astype(np.float32)
    moved = shift != 0
    origin = org
    if moved.any():
        origin = org.copy()
        origin[moved] = org[moved] + shift[moved, None] * direction[moved]
    with np.errstate(invalid="ignore", over="ignore"):
        maxt = np.where(live, np.minimum(tmax - shift, MITSUBA_MAXT), np.float32(0)).astype(np.float32)
    return origin, direction, maxt, shift, live


class MitsubaRays:
    """One batch of rays already in Mitsuba's types: ``ray`` (a vectorised Ray3f; a list of
    scalar Ray3f on a scalar variant), ``active`` (its live mask), plus the numpy ``shift``
    f32[R] and ``live`` bool[R] needed to read answers back in our conventions."""

    def __init__(self, mi, org, direction, tmin, tmax):
        origin, direction, maxt, self.shift, self.live = segments(org, direction, tmin, tmax)
        self.count = origin.shape[0]
        self.scalar = mi.variant().startswith("scalar")
        if self.scalar:
            self.ray = []
            for i in range(self.count):
                ray = mi.Ray3f(mi.Point3f(*origin[i]), mi.Vector3f(*direction[i]))
                ray.maxt = float(maxt[i])
                self.ray.append(ray)
            self.active = [bool(x) for x in self.live]
            return
        column = [np.ascontiguousarray(origin[:, j]) for j in range(3)]
        towards = [np.ascontiguousarray(direction[:, j]) for j in range(3)]
        self.ray = mi.Ray3f(mi.Point3f(*[mi.Float(c) for c in column]),
                            mi.Vector3f(*[mi.Float(c) for c in towards]))
        self.ray.maxt = mi.Float(maxt)
        self.active = mi.Bool(self.live)
        import drjit as dr

        dr.eval(self.ray, self.active)  # on the device before any timed call
        dr.sync_thread()


class MitsubaScene:
    """A Mitsuba scene over a triangle soup, for ``variant`` (default ``cuda_ad_rgb``).

    v0, v1, v2: f32[T,3] triangle corners (``Triangles.v0`` and ``v0 + e1``, ``v0 + e2``).
    ``closest(org, dir, tmin, tmax) -> (t f32[R], prim i32[R])`` (inf / -1 on a miss);
    ``occluded(org, dir, tmin, tmax) -> bool[R]``; org, dir: (R,3), tmin, tmax: (R,), any
    float dtype. ``build_seconds``: mesh upload and Mitsuba's acceleration build (OptiX /
    Embree), device synchronised. MitsubaUnavailable if the variant cannot run here.
    """

    def __init__(self, v0, v1, v2, variant: str = "cuda_ad_rgb"):
        self.mi = mi = load_mitsuba(variant)
        import drjit as dr

        self.dr, self.variant = dr, variant
        corners = np.stack([_f32(v, (3,), name) for v, name in ((v0, "v0"), (v1, "v1"), (v2, "v2"))], axis=1)
        self.triangles = corners.shape[0]
        if self.triangles == 0:
            raise ConfigError("mitsuba yardstick: the scene has no triangles")
        start = time.perf_counter()
        mesh = mi.Mesh("packetrt", 3 * self.triangles, self.triangles)
        params = mi.traverse(mesh)
        positions, faces = params["vertex_positions"], params["faces"]
        params["vertex_positions"] = type(positions)(np.ascontiguousarray(corners.reshape(-1)))
        params["faces"] = type(faces)(np.arange(3 * self.triangles, dtype=np.uint32))
        params.update()
        self.scene = mi.load_dict({"type": "scene", "soup": mesh})
        dr.sync_thread()
        self.build_seconds = time.perf_counter() - start

    def describe(self) -> dict:
        from importlib import metadata

        return {"name": "mitsuba", "variant": self.variant, "version": self.mi.__version__,
                "drjit": metadata.version("drjit"), "triangles": self.triangles,
                "build_seconds": self.build_seconds}

    def rays(self, org, direction, tmin, tmax) -> MitsubaRays:
        """The rays (org, dir: (R,3); tmin, tmax: (R,)) converted once to Mitsuba's types."""
        self._select()
        return MitsubaRays(self.mi, org, direction, tmin, tmax)

    def _select(self) -> None:
        """Mitsuba's variant is process-wide: make it this scene's again if another was set."""
        if self.mi.variant() != self.variant:
            self.mi.set_variant(self.variant)

    def trace(self, rays: MitsubaRays, query: str):
        """Mitsuba's lazy answers: (t, prim_index, valid) for "closest", (hit,) for "occluded";
        on a scalar variant, lists of Python values."""
        if query not in QUERIES:
            raise ConfigError(f"mitsuba yardstick: query {query!r} is not one of {', '.join(QUERIES)}")
        self._select()
        scene = self.scene
        if rays.scalar:
            if query == "occluded":
                return ([bool(scene.ray_test(r)) if a else False for r, a in zip(rays.ray, rays.active)],)
            answers = [scene.ray_intersect_preliminary(r) if a else None for r, a in zip(rays.ray, rays.active)]
            return ([float(p.t) if p is not None else np.inf for p in answers],
                    [int(p.prim_index) if p is not None else -1 for p in answers],
                    [bool(p.is_valid()) if p is not None else False for p in answers])
        if query == "occluded":
            return (scene.ray_test(rays.ray, active=rays.active),)
        pi = scene.ray_intersect_preliminary(rays.ray, active=rays.active)
        return pi.t, pi.prim_index, pi.is_valid()

    def trace_evaluated(self, rays: MitsubaRays, query: str):
        """``trace`` with its outputs evaluated and the device synchronised (what is timed)."""
        out = self.trace(rays, query)
        self.dr.eval(*out)
        self.dr.sync_thread()
        return out

    def closest(self, org, direction, tmin, tmax) -> tuple:
        """(t f32[R], prim i32[R]) of the closest hits; t = inf and prim = -1 on a miss."""
        rays = self.rays(org, direction, tmin, tmax)
        t, prim, valid = self.trace_evaluated(rays, "closest")
        valid = np.asarray(valid, dtype=np.bool_) & rays.live
        t = np.where(valid, np.asarray(t, dtype=np.float32) + rays.shift, np.float32(np.inf)).astype(np.float32)
        prim = np.where(valid, np.asarray(prim, dtype=np.int64), -1).astype(np.int32)
        return t, prim

    def occluded(self, org, direction, tmin, tmax) -> np.ndarray:
        """bool[R]: some triangle within [tmin, tmax] of a live ray."""
        rays = self.rays(org, direction, tmin, tmax)
        (hit,) = self.trace_evaluated(rays, "occluded")
        return np.asarray(hit, dtype=np.bool_) & rays.live


def time_queries(scene: MitsubaScene, org, direction, tmin, tmax, query: str, repeats: int = 10) -> dict:
    """Mitsuba's time for ``query`` ("closest" or "occluded") on R rays (org, dir: (R,3); tmin,
    tmax: (R,)): {"median_seconds", "grays_per_s" (1e9 rays/s), "mrays_per_s", "rays",
    "seconds" (each timed call), "query", "variant"}. Rays converted once, untimed; one
    untimed warm-up call; then ``repeats`` timed calls, each evaluated and synchronised."""
    if query not in QUERIES:
        raise ConfigError(f"mitsuba yardstick: query {query!r} is not one of {', '.join(QUERIES)}")
    if isinstance(repeats, bool) or not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise ConfigError(f"mitsuba yardstick: repeats must be an integer >= 1, got {repeats!r}")
    rays = scene.rays(org, direction, tmin, tmax)
    if rays.count == 0:
        raise ConfigError("mitsuba yardstick: no rays to time")
    scene.trace_evaluated(rays, query)  # warm-up: Dr.Jit compiles (or loads) the kernel here
    seconds = []
    for _ in range(int(repeats)):
        start = time.perf_counter()
        out = scene.trace_evaluated(rays, query)
        seconds.append(time.perf_counter() - start)
        del out
    median = statistics.median(seconds)
    rate = rays.count / median if median > 0 else float("inf")
    return {"median_seconds": median, "grays_per_s": rate / 1e9, "mrays_per_s": rate / 1e6,
            "rays": rays.count, "seconds": seconds, "query": query, "variant": scene.variant}
