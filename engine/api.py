"""The Python API: ray queries on a mesh with trimesh's names, and renders for notebooks.

>>> import numpy as np, trimesh
>>> from engine import RayTracer
>>> tracer = RayTracer(trimesh.creation.icosphere())          # or (vertices, faces), a trimesh or packetrt Scene
>>> origins = np.random.default_rng(0).normal(size=(1000, 3)) * 3      # (n, 3)
>>> directions = -origins + np.random.default_rng(1).normal(size=(1000, 3))  # (n, 3), any length
>>> tracer.intersects_first(origins, directions)             # (n,) int64, -1 = miss
>>> tracer.intersects_any(origins, directions)               # (n,) bool
>>> locations, index_ray, index_tri = tracer.intersects_location(origins, directions)
>>> hits = tracer.intersect(origins, directions)             # Hits(t, prim, u, v), each (n,)
>>> image, stats = tracer.render({"render": {"width": 256, "height": 256}})

Conventions
    - A ray is ``origin + t * direction`` for t in [tmin, tmax] (defaults 0 and inf; both may be
      given per ray). Directions need not be unit length, as in trimesh; ``Hits.t`` is in units
      of each ray's own direction length (the hit point is ``origin + t * direction``; it is the
      distance when the direction is unit). A direction of zero length, or of a length outside
      1e-18 .. 1e18 (where float32 t or |d|^2 would underflow or overflow), is an error.
    - Rays and locations are in the mesh's own coordinates, also for a mesh far from the origin,
      which is re-centred inside (``scene.origin``): the queries move the rays with it.
    - Triangle indices are face indices of the mesh (rows of ``faces``), or indices into
      ``scene.triangles`` for a Scene. Barycentrics: hit = (1-u-v) v0 + u v1 + v v2.
    - All intersection arithmetic is float32 (the inputs are rounded to float32 first); the
      answers are those of the shared watertight kernel, equal to Embree's up to floating-point
      ties (a ray through a shared edge may report either triangle).
    - ``intersects_location`` and ``intersects_id`` return the first hit per ray only (trimesh's
      ``multiple_hits=False``), in increasing ray order. For trimesh's own semantics (every hit
      by default, ``contains_points``, float64 locations, bad rays as misses) use
      ``RayMeshIntersector`` (engine/query/), a drop-in ``mesh.ray``.

Incoherent rays become packets here: rays are grouped by direction octant, sorted by a Morton
code over origin and direction inside each octant, and dealt to n x n packets (``packet``) of
2x2 SIMD rays, each octant starting a new packet, so a packet's rays point the same way and
start near each other. The packet lanes left over are dead (tmax < tmin), as the packet contract
says. The sorted rays are also laid out along a Z-order curve on a virtual screen, so the
``rayspace`` traversal sees neighbouring rays in neighbouring pixels. Answers are mapped back to
the input order.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit, prange

from engine.core.checked import is_flag
from engine.core.errors import ConfigError, memory_errors_as
from engine.core.threads import numba_threads
from engine.core.types import RAY_KINDS, Hits, Packets, RayBatch, Triangles, empty_hits
from engine.packet.compact import inverse_component
from engine.query.errors import BadRayWarning, QueryInputError, QueryTypeError
from engine.query.intersector import RayMeshIntersector
from engine.core.radix import radix_argsort

__all__ = ["RayTracer", "RayMeshIntersector", "RayInputError", "RayInputTypeError", "ApiArgumentError",
           "QueryInputError", "QueryTypeError", "BadRayWarning"]

#: Direction lengths the float32 kernels handle without underflow or overflow in t or |d|^2.
MIN_DIRECTION_LENGTH, MAX_DIRECTION_LENGTH = 1e-18, 1e18

#: Bits per coordinate of the 6-D (origin, direction) Morton code; 6 * 9 = 54 bits.
MORTON_BITS = 9
#: q (0 .. 2^MORTON_BITS - 1) with bit b moved to bit 6 b: one coordinate of the 6-D Morton code,
#: looked up (``spread_bits`` loops over the bits; a table read is one load a coordinate).
SPREAD_BY_6 = np.array([sum(((q >> b) & 1) << (6 * b) for b in range(MORTON_BITS)) for q in range(1 << MORTON_BITS)],
                       np.uint64)


class RayInputError(QueryInputError):
    """Ray arrays given to a query are malformed; the message names the argument and a row.
    A ValueError (and a PacketrtError)."""


class RayInputTypeError(RayInputError, QueryTypeError):
    """A ray argument has the wrong type (strings, objects, complex numbers); also a TypeError."""


class ApiArgumentError(ConfigError, ValueError):
    """A RayTracer argument (mesh, traversal, packet, threads, multiple_hits) is not allowed;
    a ConfigError that is also a ValueError."""


def _real_dtype(name: str, value, shape: str) -> None:
    """RayInputTypeError unless ``value`` converts to a real (bool, int or float) array."""
    try:
        kind = np.asarray(value).dtype.kind
    except (TypeError, ValueError) as exc:
        raise RayInputTypeError(f"{name} must be a numeric array of shape {shape}: {exc}") from None
    if kind not in "biuf":
        raise RayInputTypeError(f"{name} must be a real numeric array of shape {shape}, got dtype "
                                f"{np.asarray(value).dtype}")


# -- inputs ----------------------------------------------------------------------------------
def _vectors(name: str, value, n: int | None = None, check_finite: bool = True) -> np.ndarray:
    """f32[n,3] from an array-like, with a RayInputError naming ``name`` when it is not one
    (or, with ``check_finite``, when a row is not finite in float32)."""
    _real_dtype(name, value, "(n, 3)")
    try:
        with np.errstate(over="ignore"):
            f32 = np.ascontiguousarray(value, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise RayInputError(f"{name} must be a numeric array of shape (n, 3): {exc}") from None
    if f32.ndim != 2 or f32.shape[1] != 3:
        raise RayInputError(f"{name} must have shape (n, 3), got {f32.shape}")
    if n is not None and f32.shape[0] != n:
        raise RayInputError(f"{name} has {f32.shape[0]} rows but origins has {n}; give one direction per origin")
    if check_finite and not np.isfinite(f32).all():
        bad = ~np.isfinite(f32).all(axis=1)
        i = int(np.flatnonzero(bad)[0])
        row = np.asarray(value[i] if hasattr(value, "__getitem__") else f32[i], np.float64)
        what = "is not finite" if not np.isfinite(row).all() else "overflows float32"
        raise RayInputError(f"{name}[{i}] {what} ({row.tolist()}); {int(bad.sum())} such row(s) in all")
    return f32


def _segment_bound(name: str, value, n: int, default: float) -> np.ndarray:
    if value is None:
        return np.full(n, default, np.float32)
    _real_dtype(name, value, f"({n},) or a number")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RayInputError(f"{name} must be a number or an array of shape (n,): {exc}") from None
    if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
        raise RayInputError(f"{name} must be a number or an array of shape ({n},), got shape {arr.shape}")
    arr = np.broadcast_to(arr, (n,))
    bad = np.isnan(arr)
    if bad.any():
        raise RayInputError(f"{name}[{int(np.flatnonzero(bad)[0])}] is NaN")
    with np.errstate(over="ignore"):  # beyond float32's range is +-inf, as a bound means
        return np.ascontiguousarray(arr.astype(np.float32))


def check_rays(origins, directions, tmin=None, tmax=None):
    """(org f32[n,3], dir f32[n,3], tmin f32[n], tmax f32[n]) from user input, or RayInputError.

    origins, directions: (n, 3) finite (in float32); direction lengths in 1e-18 .. 1e18.
    tmin: finite, >= 0;
    tmax >= tmin (inf allowed). Scalars broadcast to every ray.

    Converted, then checked in one parallel pass (``count_invalid_rays``); only when some ray
    breaks a rule do the numpy checks of ``explain_bad_rays`` run, to raise the error that names
    the first such row. A million rays: 38 ms of numpy checks became a pass of a few ms.
    """
    try:
        org = _vectors("origins", origins, check_finite=False)
        dirs = _vectors("directions", directions, org.shape[0], check_finite=False)
        n = org.shape[0]
        lo = _segment_bound("tmin", tmin, n, 0.0)
        hi = _segment_bound("tmax", tmax, n, np.inf)
    except RayInputError:
        return explain_bad_rays(origins, directions, tmin, tmax)  # the same error, in the same order
    if count_invalid_rays(org, dirs, lo, hi, MIN_DIRECTION_LENGTH, MAX_DIRECTION_LENGTH) == 0:
        return org, dirs, lo, hi
    return explain_bad_rays(origins, directions, tmin, tmax)


@njit(cache=True, parallel=True)
def count_invalid_rays(org, dirs, lo, hi, shortest, longest):
    """How many rays break a rule of ``check_rays`` (org, dirs f32[n,3]; lo, hi f32[n]): a
    coordinate not finite, a zero direction or one whose float64 length is outside
    [shortest, longest], tmin not finite or negative, tmax below tmin (or NaN)."""
    bad = 0
    for i in prange(org.shape[0]):
        ox, oy, oz = org[i, 0], org[i, 1], org[i, 2]
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        finite = np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz) and np.isfinite(dx) \
            and np.isfinite(dy) and np.isfinite(dz)
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        aimed = (dx != 0 or dy != 0 or dz != 0) and shortest <= length <= longest
        bounds = np.isfinite(lo[i]) and lo[i] >= 0 and hi[i] >= lo[i]
        if not (finite and aimed and bounds):
            bad += 1
    return bad


#: Embree misses rays whose directions are shorter than about 3e-17 (its reciprocals overflow),
#: though check_rays allows 1e-18; such directions are scaled by a power of two first.
EMBREE_SAFE_EXPONENTS = (-40, 40)


def embree_direction_lengths(dirs, lo, hi):
    """(dirs, tmin, tmax, factor f32[n] or None): rays whose largest direction component lies
    outside 2^-40 .. 2^40 rescaled by a power of two to near unit length, and their segment
    bounds with them (t * factor is the distance along the caller's direction). A power of two
    scales every float32 exactly, so the rays are the same lines and segments. None: no ray
    needed it (the arrays are returned as they were)."""
    exponent = np.frexp(np.abs(dirs).max(axis=1))[1]
    low, high = EMBREE_SAFE_EXPONENTS
    moved = (exponent < low) | (exponent > high)
    if not moved.any():
        return dirs, lo, hi, None
    factor = np.ones(len(dirs), np.float32)
    factor[moved] = np.ldexp(np.float32(1.0), -exponent[moved])  # 2^-e: direction * 2^-e is near unit
    scaled = np.ascontiguousarray(dirs * factor[:, None], np.float32)
    with np.errstate(over="ignore"):  # a huge tmin times 2^e is beyond any hit: inf is right
        lo, hi = (lo / factor).astype(np.float32), (hi / factor).astype(np.float32)
    return scaled, lo, hi, factor


def explain_bad_rays(origins, directions, tmin=None, tmax=None):
    """``check_rays``'s rules one at a time in numpy: raises the RayInputError naming the first
    row that breaks the first rule broken (returns the checked rays if none is)."""
    org = _vectors("origins", origins)
    dirs = _vectors("directions", directions, org.shape[0])
    zero = ~(dirs != 0).any(axis=1)
    if zero.any():
        i = int(np.flatnonzero(zero)[0])
        raise RayInputError(f"directions[{i}] has zero length; {int(zero.sum())} zero direction(s) in all")
    length = np.sqrt(np.einsum("ij,ij->i", dirs.astype(np.float64), dirs.astype(np.float64)))
    odd = (length < MIN_DIRECTION_LENGTH) | (length > MAX_DIRECTION_LENGTH)
    if odd.any():
        i = int(np.flatnonzero(odd)[0])
        raise RayInputError(f"directions[{i}] has length {length[i]:.3g}, outside "
                            f"{MIN_DIRECTION_LENGTH:g} .. {MAX_DIRECTION_LENGTH:g} where float32 t and "
                            f"squared lengths stay exact enough; normalise the directions")
    n = org.shape[0]
    lo = _segment_bound("tmin", tmin, n, 0.0)
    hi = _segment_bound("tmax", tmax, n, np.inf)
    bad = ~np.isfinite(lo) | (lo < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise RayInputError(f"tmin[{i}] = {float(lo[i])} must be finite and >= 0")
    bad = hi < lo
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise RayInputError(f"tmax[{i}] = {float(hi[i])} is below tmin[{i}] = {float(lo[i])}")
    return org, dirs, lo, hi


# -- incoherent rays -> packets --------------------------------------------------------------
@njit(cache=True, parallel=True)
def morton_keys_kernel(org, dirs, lo, hi, keys):
    """keys[i] (u64): direction octant (3 bits, sign bits of x, y, z) above a 6-D Morton code of
    the origin (quantized within the box lo..hi) and the unit direction (within [-1, 1]^3)."""
    top = (1 << MORTON_BITS) - 1
    for i in prange(org.shape[0]):
        code = np.uint64(0)
        norm = 0.0
        for a in range(3):
            norm += np.float64(dirs[i, a]) * np.float64(dirs[i, a])
        norm = np.sqrt(norm)
        octant = np.uint64(0)
        for a in range(3):
            span = hi[a] - lo[a]
            x = (np.float64(org[i, a]) - lo[a]) / span if span > 0 else 0.0
            qo = min(max(int(np.floor(x * top + 0.5)), 0), top)
            y = (np.float64(dirs[i, a]) / norm + 1.0) * 0.5
            qd = min(max(int(np.floor(y * top + 0.5)), 0), top)
            code |= SPREAD_BY_6[qo] << np.uint64(5 - a)
            code |= SPREAD_BY_6[qd] << np.uint64(2 - a)
            if np.signbit(dirs[i, a]):
                octant |= np.uint64(1) << np.uint64(2 - a)
        keys[i] = code | (octant << np.uint64(6 * MORTON_BITS))


@njit(cache=True, inline="always")
def even_bits(value):
    """Bits 0, 2, 4, ... of ``value`` (u64) packed into bits 0, 1, 2, ...: five mask-and-shift
    steps instead of a loop over 32 bits."""
    x = value & np.uint64(0x5555555555555555)
    x = (x | (x >> np.uint64(1))) & np.uint64(0x3333333333333333)
    x = (x | (x >> np.uint64(2))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    x = (x | (x >> np.uint64(4))) & np.uint64(0x00FF00FF00FF00FF)
    x = (x | (x >> np.uint64(8))) & np.uint64(0x0000FFFF0000FFFF)
    return (x | (x >> np.uint64(16))) & np.uint64(0x00000000FFFFFFFF)


@njit(cache=True)
def _z_order(rank, side):
    """Pixel y * side + x of position ``rank`` (< 2^62) along a Z-order curve (even bits x, odd
    bits y)."""
    code = np.uint64(rank)
    return np.int64(even_bits(code >> np.uint64(1))) * side + np.int64(even_bits(code))


@njit(cache=True)
def incoherent_packets_kernel(order, sorted_keys, block, octant_shift):
    """Deal rays, sorted by key (``order`` i64[n], ``sorted_keys`` u64[n]), into packets of at
    most ``block`` rays, each direction octant starting a fresh packet, each packet padded to
    whole SIMD rays. Returns (gather i64[R]: input ray of each lane or -1, offsets i32[K+1],
    pixel i32[R]: Z-order virtual pixel or -1, side: the virtual screen's side)."""
    n = order.shape[0]
    n_packets = 0
    n_lanes = 0
    n_ranks = 0
    i = 0
    while i < n:
        octant = sorted_keys[i] >> octant_shift
        j = i
        while j < n and (sorted_keys[j] >> octant_shift) == octant:
            j += 1
        n_ranks += (j - i + block - 1) // block * block
        s = i
        while s < j:
            m = min(block, j - s)
            n_packets += 1
            n_lanes += (m + 3) // 4 * 4
            s += m
        i = j
    side = 1
    while side * side < n_ranks:
        side *= 2
    gather = np.full(n_lanes, -1, np.int64)
    pixel = np.full(n_lanes, -1, np.int32)
    offsets = np.zeros(n_packets + 1, np.int32)
    k = 0
    lane = 0
    base = 0
    i = 0
    while i < n:
        octant = sorted_keys[i] >> octant_shift
        j = i
        while j < n and (sorted_keys[j] >> octant_shift) == octant:
            j += 1
        s = i
        while s < j:
            m = min(block, j - s)
            for r in range(m):
                gather[lane + r] = order[s + r]
                pixel[lane + r] = _z_order(base + s - i + r, side)
            lane += (m + 3) // 4 * 4
            k += 1
            offsets[k] = lane
            s += m
        base += (j - i + block - 1) // block * block
        i = j
    return gather, offsets, pixel, side


@njit(cache=True, parallel=True)
def gather_rays_kernel(gather, org, dirs, tmin, tmax, out_org, out_dir, out_inv, out_tmin, out_tmax, out_weight,
                       lane_of):
    """Lane l takes input ray gather[l], with its inverse direction (``inverse_component``, the
    numbers of ``safe_inverse``) and weight 1, and lane_of[gather[l]] = l; a padding lane (-1)
    becomes dead: direction (0, 0, 1), tmin 1 > tmax 0, weight 0."""
    for lane in prange(gather.shape[0]):
        g = gather[lane]
        if g >= 0:
            for a in range(3):
                out_org[lane, a] = org[g, a]
                out_dir[lane, a] = dirs[g, a]
                out_inv[lane, a] = inverse_component(dirs[g, a])
                out_weight[lane, a] = 1
            out_tmin[lane] = tmin[g]
            out_tmax[lane] = tmax[g]
            lane_of[g] = lane
        else:
            for a in range(3):
                out_org[lane, a] = 0
                out_dir[lane, a] = 0
                out_weight[lane, a] = 0
            out_dir[lane, 2] = 1
            for a in range(3):
                out_inv[lane, a] = inverse_component(out_dir[lane, a])
            out_tmin[lane] = 1
            out_tmax[lane] = 0


@njit(cache=True, parallel=True)
def origin_box(org):
    """(lo f64[3], hi f64[3]): the smallest and largest origin coordinate per axis (org f32[M,3],
    M >= 1), the values of ``org.min(axis=0)`` and ``org.max(axis=0)`` in one parallel pass."""
    parts = min(org.shape[0], 64)
    lo = np.empty((parts, 3), np.float32)
    hi = np.empty((parts, 3), np.float32)
    for p in prange(parts):
        start = p * org.shape[0] // parts
        stop = (p + 1) * org.shape[0] // parts
        for a in range(3):
            lo[p, a] = org[start, a]
            hi[p, a] = org[start, a]
        for i in range(start + 1, stop):
            for a in range(3):
                lo[p, a] = min(lo[p, a], org[i, a])
                hi[p, a] = max(hi[p, a], org[i, a])
    box_lo = np.empty(3, np.float64)
    box_hi = np.empty(3, np.float64)
    for a in range(3):
        box_lo[a] = lo[:, a].min()
        box_hi[a] = hi[:, a].max()
    return box_lo, box_hi


@njit(cache=True, parallel=True)
def answers_in_input_order(lane_of, t, prim, u, v):
    """The lanes' hits (f32/i32/f32/f32[R]) of input rays 0 .. n-1 (lane_of i64[n]): one
    parallel gather for the four arrays."""
    n = lane_of.shape[0]
    out_t = np.empty(n, np.float32)
    out_prim = np.empty(n, np.int32)
    out_u = np.empty(n, np.float32)
    out_v = np.empty(n, np.float32)
    for i in prange(n):
        lane = lane_of[i]
        out_t[i] = t[lane]
        out_prim[i] = prim[lane]
        out_u[i] = u[lane]
        out_v[i] = v[lane]
    return out_t, out_prim, out_u, out_v


def incoherent_batch(kind: str, org, dirs, tmin, tmax, n: int):
    """(RayBatch, Packets, lane_of i64[M]) for arbitrary rays (f32[M,3], f32[M,3], f32[M], f32[M],
    M >= 1): packets of at most n x n rays grouped by direction octant and a Morton code over
    origin and direction; ``lane_of[i]`` is input ray i's lane."""
    count = org.shape[0]
    keys = np.empty(count, np.uint64)
    morton_keys_kernel(org, dirs, *origin_box(org), keys)
    order = radix_argsort(keys)  # 200,000 rays: 1.3 ms, numpy's quicksort 2.3 ms
    gather, offsets, pixel, side = incoherent_packets_kernel(order, keys[order], n * n,
                                                             np.uint64(6 * MORTON_BITS))
    lanes = gather.shape[0]
    out_org = np.empty((lanes, 3), np.float32)
    out_dir = np.empty((lanes, 3), np.float32)
    out_inv = np.empty((lanes, 3), np.float32)
    out_tmin = np.empty(lanes, np.float32)
    out_tmax = np.empty(lanes, np.float32)
    weight = np.empty((lanes, 3), np.float32)
    lane_of = np.empty(count, np.int64)
    gather_rays_kernel(gather, org, dirs, tmin, tmax, out_org, out_dir, out_inv, out_tmin, out_tmax, weight, lane_of)
    rays = RayBatch(out_org, out_dir, out_inv, out_tmin, out_tmax, pixel, weight, kind)
    return rays, Packets(offsets, n, int(side), int(side)), lane_of


# -- the tracer ------------------------------------------------------------------------------
def _scene_from(mesh_or_scene):
    from engine.core.scene import Scene, SceneBuilder, check_triangles

    if isinstance(mesh_or_scene, Scene):
        return mesh_or_scene
    builder = SceneBuilder("mesh", source="RayTracer")
    if isinstance(mesh_or_scene, Triangles):  # one default material for every triangle
        tris = check_triangles(mesh_or_scene, "RayTracer Triangles")
        builder.add_material(_default_material())
        builder.add_triangles(tris._replace(material=np.zeros_like(tris.material)))
        return builder.build()
    if hasattr(mesh_or_scene, "graph") and hasattr(mesh_or_scene, "to_mesh"):  # a trimesh.Scene (a glTF's)
        # Its meshes placed by their nodes' transforms, as one mesh (trimesh's own to_mesh).
        if not mesh_or_scene.geometry:
            raise ApiArgumentError("the trimesh.Scene holds no geometry")
        mesh_or_scene = mesh_or_scene.to_mesh()
    if hasattr(mesh_or_scene, "vertices") and hasattr(mesh_or_scene, "faces"):  # trimesh.Trimesh
        vertices, faces = mesh_or_scene.vertices, mesh_or_scene.faces
    elif isinstance(mesh_or_scene, (tuple, list)) and len(mesh_or_scene) == 2:
        vertices, faces = mesh_or_scene
    else:
        raise ApiArgumentError("RayTracer needs a trimesh.Trimesh or trimesh.Scene, a (vertices (V,3), faces "
                               f"(T,3)) pair, packetrt Triangles or a packetrt Scene; got {type(mesh_or_scene).__name__}")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ApiArgumentError(f"faces must be an integer array of shape (T, 3), got {faces.dtype} {faces.shape}")
    if len(faces) == 0:
        raise ApiArgumentError("the mesh has no faces")
    builder.add_mesh(vertices, faces, builder.add_material(_default_material()), source="RayTracer mesh")
    return builder.build()


def _default_material():
    from engine.core.scene import Material

    return Material()


def _on_host(array) -> np.ndarray:
    """``array`` as a numpy array: a device answer (numba ``DeviceNDArray``) copied back."""
    return array if isinstance(array, np.ndarray) else array.copy_to_host()


def _as_config(config, device: str = "cpu"):
    """The checked Config of ``render``'s argument; a tracer on ``device = "cuda"`` renders there
    whatever the config's own [render] device says, and the config is checked as a device config
    (so the device's traversal names, ``bvh``, are known). A CPU tracer keeps the config's device."""
    from dataclasses import replace

    from engine.render import config as cfg

    def on_device(data: dict) -> dict:
        if device == "cpu":
            return data
        render = data.get("render", {})
        return {**data, "render": {**render, "device": device}} if isinstance(render, dict) else data

    if config is None:
        config = cfg.Config()
    if isinstance(config, cfg.Config):
        if device != "cpu" and config.render.device != device:
            config = replace(config, render=replace(config.render, device=device))
        return cfg.validate(config)
    if isinstance(config, dict):
        return cfg.from_dict(on_device(config))
    if isinstance(config, (str, Path)):
        if not str(config).strip():
            raise ApiArgumentError("render config path is empty; give a TOML file, a dict or a Config")
        return cfg.from_dict(on_device(cfg.read_toml(str(config), "config")), source=str(config))
    raise ApiArgumentError(f"render config must be a Config, a dict of TOML tables or a TOML path; "
                      f"got {type(config).__name__}")


class RayTracer:
    """Ray queries and renders over one triangle mesh.

    mesh_or_scene  a ``trimesh.Trimesh``, a ``(vertices f[V,3], faces i[T,3])`` pair, packetrt
                   ``Triangles`` or a packetrt ``Scene``. A mesh gets one default material, an
                   auto-framed camera and one point light (for ``render``).
    traversal      traversal plugin for the queries (``packetrt plugins``): "partition"
                   (default; the packet traversal that copes best with incoherent rays),
                   "ranged", "masked", "simd", "auto" (per packet), "single", "wide" (one ray at a
                   time over an 8-wide tree), "rayspace", "embree".
    frustum        frustum builder for the packets: "general" (default; valid for any origins),
                   "none", or any registered name (a builder that does not fit marks packets
                   unculled).
    packet         n of the n x n packets (2, 4, 8, 16, 32).
    threads        numba threads for each query (0 = all cores), set for that call only: the
                   caller's own count (``numba.set_num_threads``) is back when it returns.
    leaf_size, bins  BVH build settings, as in a config's [render] table.
    device         "cpu" (default) or "cuda": queries on the GPU (``engine.gpu.queries``), by the
                   device's ``bvh`` traversal (any BVH traversal name selects it). Rays given as
                   device arrays (torch, CuPy, numba: ``__cuda_array_interface__``) are traced in
                   place and answered with device arrays; numpy rays are copied once and
                   answered with numpy arrays. ``render`` then renders on the GPU too.

    Every query takes ``(origins (n,3), directions (n,3))`` plus optional ``tmin`` / ``tmax``
    keywords (scalars or (n,) arrays; defaults 0 and inf) and answers in input order.

    The BVH is built once, here; every query reuses it.
    """

    def __init__(self, mesh_or_scene, traversal: str = "partition", frustum: str = "general",
                 packet: int = 8, *, threads: int = 0, leaf_size: int = 4, bins: int = 16, device: str = "cpu"):
        from engine.core.bvh import build_bvh, check_build_settings, scene_bounds
        from engine.packet.layout import check_packet_size
        from engine.render.plugins import make_frustum, make_traversal
        from engine.render.tracer import Tracer

        self.scene = _scene_from(mesh_or_scene)
        self.triangles: Triangles = self.scene.triangles
        if isinstance(threads, (bool, np.bool_)) or not isinstance(threads, (int, np.integer)):
            raise ApiArgumentError(f"threads must be an integer >= 0 (0 = all cores), got {threads!r}")
        self.threads = int(threads)
        if self.threads < 0:
            raise ApiArgumentError(f"threads must be >= 0 (0 = all cores), got {threads}")
        if device not in ("cpu", "cuda"):
            raise ApiArgumentError(f"device must be 'cpu' or 'cuda', got {device!r}")
        self.device = device
        try:  # the plugin layers raise ConfigError; the API's mistakes are ValueErrors too
            self.packet = check_packet_size(packet, "RayTracer packet")
            self.traversal_name, self.frustum_name = traversal, frustum
            if device == "cuda":
                from engine.render.device_names import device_traversal_name

                if device_traversal_name(traversal) not in ("bvh", "wide"):
                    raise ApiArgumentError(f"RayTracer(device='cuda') traces with the device's bvh traversal; "
                                           f"got traversal={traversal!r}")
                traversal = "single" if traversal == "bvh" else traversal  # the CPU side's reference
            self.traversal = make_traversal(traversal)
            self.frustum = make_frustum(frustum)
            leaf_size, bins = check_build_settings(leaf_size, bins)
        except ConfigError as exc:
            if isinstance(exc, (ApiArgumentError, TypeError)):
                raise
            raise ApiArgumentError(str(exc)) from None
        self.bvh = build_bvh(self.triangles, leaf_size=leaf_size, bins=bins)
        self.bounds = scene_bounds(self.bvh)
        self.tracer = Tracer(self.bvh, self.triangles, self.bounds, dict.fromkeys(RAY_KINDS, self.traversal),
                             dict.fromkeys(RAY_KINDS, self.frustum))
        self.tracer.prepare()
        self.device_queries = None
        if device == "cuda":
            from engine.gpu.queries import DeviceQueries

            self.device_queries = DeviceQueries(self.triangles, self.bvh)

    def __repr__(self) -> str:
        return (f"RayTracer({self.scene.name!r}, {self.scene.n_triangles:,} triangles, "
                f"traversal={self.traversal_name!r}, frustum={self.frustum_name!r}, packet={self.packet}, "
                f"device={self.device!r})")

    # -- the two queries ---------------------------------------------------------------
    def _local(self, origins):
        """``origins`` moved into the scene's frame: a scene far from the origin is re-centred when
        built (``Scene.origin``, in float64), and rays given in the mesh's own coordinates must
        move with it, in float64 before the kernels' float32 (else every ray missed such a mesh,
        Embree's too). Unchanged when the scene was not moved, or when the input is not a real
        numeric array (``check_rays`` then names what is wrong); device arrays cannot be moved
        here, and a moved scene refuses them."""
        if not any(self.scene.origin):
            return origins
        if hasattr(origins, "__cuda_array_interface__"):
            raise ApiArgumentError(f"this mesh was re-centred (it lies {max(map(abs, self.scene.origin)):.3g} from "
                                   f"the origin); give its rays as numpy arrays, which are moved with it")
        arr = np.asarray(origins)
        if arr.dtype.kind not in "biuf" or arr.ndim != 2 or arr.shape[1:] != (3,):  # what check_rays takes
            return origins
        return arr.astype(np.float64) - np.asarray(self.scene.origin, np.float64)

    def _batch(self, kind, origins, directions, tmin, tmax):
        """(RayBatch in packet order, Packets, lane of each input ray i64[n], per-ray factor f32[n]
        to multiply hit distances by, or None); None for n = 0."""
        org, dirs, lo, hi = check_rays(origins, directions, tmin, tmax)
        count = org.shape[0]
        if count == 0:
            return None
        scale = None
        if self.traversal_name == "embree":
            dirs, lo, hi, scale = embree_direction_lengths(dirs, lo, hi)
        return (*incoherent_batch(kind, org, dirs, lo, hi, self.packet), scale)

    @memory_errors_as(RayInputError)
    def intersect(self, origins, directions, tmin=None, tmax=None) -> Hits:
        """Closest hit of every ray.

        origins, directions: (n, 3); tmin, tmax: scalars or (n,) (defaults 0, inf).
        Returns ``Hits`` of (n,) arrays in input order: t f32 (inf = miss; hit point =
        origin + t * direction), prim i32 (triangle index, -1 = miss), u, v f32 (barycentrics
        of v1 and v2). With ``device="cuda"``, device-array rays get device-array answers.
        """
        origins = self._local(origins)
        if self.device_queries is not None:
            return self.device_queries.intersect(origins, directions, tmin, tmax, check_rays)
        with numba_threads(self.threads):  # for this call only (``engine.core.threads``)
            batch = self._batch("reflection", origins, directions, tmin, tmax)
            if batch is None:
                return empty_hits(0)
            rays, packets, lane, scale = batch
            hits = Hits(*answers_in_input_order(lane, *self.tracer.trace("reflection", "intersect", rays, packets)))
            if scale is not None:  # distances along the rescaled directions, back to the caller's
                hits.t[:] = hits.t * scale
            return hits

    @memory_errors_as(RayInputError)
    def occluded(self, origins, directions, tmin=None, tmax=None) -> np.ndarray:
        """bool (n,): does ray i hit anything with tmin <= t <= tmax (any hit, early exit).
        With ``device="cuda"``, device-array rays get a u8 (n,) device array (1 = occluded)."""
        origins = self._local(origins)
        if self.device_queries is not None:
            return self.device_queries.occluded(origins, directions, tmin, tmax, check_rays)
        with numba_threads(self.threads):
            batch = self._batch("shadow", origins, directions, tmin, tmax)
            if batch is None:
                return np.zeros(0, np.bool_)
            rays, packets, lane, _ = batch
            return self.tracer.trace("shadow", "occluded", rays, packets)[lane]

    # -- trimesh's names ---------------------------------------------------------------
    # trimesh's interface is numpy: these answer numpy arrays for device-array rays too (the
    # device's answers are copied back once; ``intersect`` / ``occluded`` keep them there).
    def intersects_first(self, ray_origins, ray_directions, **segment) -> np.ndarray:
        """int64 (n,): index of the first triangle each ray hits, -1 for a miss."""
        return _on_host(self.intersect(ray_origins, ray_directions, **segment).prim).astype(np.int64)

    def intersects_any(self, ray_origins, ray_directions, **segment) -> np.ndarray:
        """bool (n,): whether each ray hits any triangle."""
        return _on_host(self.occluded(ray_origins, ray_directions, **segment)).astype(np.bool_)

    def intersects_id(self, ray_origins, ray_directions, multiple_hits: bool = False,
                      return_locations: bool = False, **segment):
        """(index_tri int64 (m,), index_ray int64 (m,)[, locations f64 (m, 3)]) for the m rays
        that hit, first hit only, in increasing ray order."""
        _first_hit_only(multiple_hits, "intersects_id")
        if not is_flag(return_locations):  # a string such as 'no' was taken as True
            raise ApiArgumentError(f"intersects_id: return_locations must be True or False, got {return_locations!r}")
        hits = Hits(*map(_on_host, self.intersect(ray_origins, ray_directions, **segment)))
        index_ray = np.flatnonzero(hits.prim >= 0).astype(np.int64)
        index_tri = hits.prim[index_ray].astype(np.int64)
        if not return_locations:
            return index_tri, index_ray
        return index_tri, index_ray, self._locations(hits, index_ray)

    def intersects_location(self, ray_origins, ray_directions, multiple_hits: bool = False, **segment):
        """(locations f64 (m, 3), index_ray int64 (m,), index_tri int64 (m,)) for the m rays that
        hit: the first hit per ray (trimesh's ``multiple_hits=False``), in increasing ray order.
        A location is the hit's barycentric point on its triangle."""
        _first_hit_only(multiple_hits, "intersects_location")  # named as the caller called it
        index_tri, index_ray, locations = self.intersects_id(ray_origins, ray_directions, multiple_hits,
                                                             True, **segment)
        return locations, index_ray, index_tri

    def _locations(self, hits: Hits, index_ray: np.ndarray) -> np.ndarray:
        prim = hits.prim[index_ray]
        u = hits.u[index_ray].astype(np.float64)[:, None]
        v = hits.v[index_ray].astype(np.float64)[:, None]
        t = self.triangles
        return ((1 - u - v) * t.v0[prim].astype(np.float64) + u * t.v1[prim].astype(np.float64)
                + v * t.v2[prim].astype(np.float64)) + np.asarray(self.scene.origin, np.float64)  # the mesh's frame

    # -- renders -----------------------------------------------------------------------
    def render(self, config=None, *, counters: bool = False):
        """(image f32[H,W,3] linear RGB, stats dict) of this tracer's scene.

        config: a ``engine.render.config.Config``, a dict of TOML tables (``{"render": {"width": 256},
        "materials": {"override": "reflective"}}``) or a TOML file path; None = the defaults
        (512 x 512, the paper's traversals and frusta). Its [scene] table is ignored: the tracer
        renders its own geometry (with ``[materials] override`` applied), by the config's own
        [render], [traversal] and [frustum]: the tracer's traversal, frustum, packet, threads,
        leaf_size and bins are for its queries. ``stats`` is the
        document ``packetrt render --stats`` writes, with ``seconds.compile`` (the warm-up that
        compiles or loads the kernels) kept out of the frame's times; ``counters=True`` fills its
        traversal counters from a second, counting render.
        """
        from dataclasses import replace

        from engine.core.scene import override_materials
        from engine.gpu.choose import new_renderer
        from engine.render.report import stats_dict

        if not isinstance(counters, (bool, np.bool_)):
            raise ApiArgumentError(f"render: counters must be True or False, got {counters!r}")
        cfg = _as_config(config, self.device)
        scene = override_materials(self.scene, cfg.override)
        with numba_threads(cfg.render.threads):  # host work too (the GPU renderer's); the caller's count comes back
            renderer = new_renderer(scene, cfg)
            compile_seconds = renderer.warm_up()   # JIT compile or cache load, kept out of the frame's times
            result = renderer.render()
            result.seconds["compile"] = compile_seconds
            if counters:
                renderer.with_counters(result)
        stats = stats_dict(scene, cfg, result)
        stats["config"]["scene"] = {"name": scene.name, "from": "RayTracer"}
        return result.image, stats


def _first_hit_only(multiple_hits: bool, where: str) -> None:
    if not is_flag(multiple_hits):
        raise ApiArgumentError(f"{where}: multiple_hits must be True or False, got {multiple_hits!r}")
    if multiple_hits:
        raise ApiArgumentError(f"{where}: multiple_hits=True is not supported; packetrt answers the first hit "
                          f"per ray (trimesh's multiple_hits=False)")
