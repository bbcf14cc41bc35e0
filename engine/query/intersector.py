"""``RayMeshIntersector``: trimesh's ray-intersector interface (``mesh.ray``) on packetrt kernels.

>>> import trimesh
>>> from engine import RayMeshIntersector
>>> mesh = trimesh.creation.icosphere()
>>> mesh.ray = RayMeshIntersector(mesh)      # mesh.contains, ray voxelisation ... now use packetrt

Semantics follow trimesh's backends (``trimesh.ray.ray_pyembree`` / ``ray_triangle``):

- Rays are ``origin + t * direction`` for t >= 0; directions need not be unit length.
- ``intersects_id`` / ``intersects_location`` return *every* hit along each ray by default
  (``multiple_hits=True``, at most ``max_hits`` = 100 per ray); hits are grouped by ray in
  increasing ray index and, within a ray, in increasing distance. A ray through an edge or a
  vertex shared by several triangles crosses the surface once and is reported once (hits within
  1e-6 of the mesh's scale, or 2^-21 of their distance, of the previous one are merged, as
  trimesh's stepping does). The mesh's frame (centre and scale) counts only the vertices the
  faces use, as trimesh's bounds do.
- Index arrays are int64 (``intersects_first``: int32 like trimesh's default embree backend);
  locations are float64 (n, 3).
- A ray with a NaN or inf component or a zero direction is a miss, counted in one
  ``BadRayWarning``; only malformed arrays raise (``QueryInputError``, a ValueError;
  ``QueryTypeError`` for a wrong type, also a TypeError).

Precision: the mesh is moved to its own centre and scale before its corners are rounded to
float32 (``frame``), and locations are float64 (``locations``).

Reuse: the arrays a query works in (lanes, frusta, answers before they are gathered into the
returned arrays) are kept from one query to the next (``engine.core.scratch``), as fresh
arrays page-fault (447 x 447 bunny camera rays, first hits, 2 threads, medians of 15
interleaved queries: 15.1 ms fresh, 11.2 ms reused; the kitchen 12.3 ms either way, as glibc
happened to keep its pages). Returned arrays are always new. A
query made while another thread is inside one on the same intersector works in fresh arrays.

Freshness: every query compares the hashes of ``mesh.faces`` and ``mesh.vertices`` (trimesh
caches them until the arrays change) with the ones the structure was built for: new faces
rebuild the BVH, moved vertices refit it. Pickling and copying keep the mesh and rebuild the
structure on first use, as trimesh's intersectors do.
"""
from __future__ import annotations

import threading
import warnings
import zlib
from contextlib import contextmanager
from typing import NamedTuple

import numpy as np

from engine.core.bvh import build_bvh, check_build_settings
from engine.core.bvh_refit import refit_bvh
from engine.core.checked import is_flag
from engine.core.errors import ConfigError, ConfigTypeError, memory_errors_as
from engine.core.scratch import Scratch
from engine.core.scene import make_triangles
from engine.core.threads import at_own_threads
from engine.core.types import BVH, Triangles
from engine.packet.compact import new_array
from engine.packet.kernels import child_order_keys
from engine.query.coherent import (PACK_INPUT, PACK_NONE, PACK_SORTED, block_medians, coherent_blocks,
                                   packet_first_hits, packing, row_length, tiled_rows)
from engine.query.contains import DIRECTIONS, contains_kernel
from engine.query.errors import BadRayWarning, QueryInputError, QueryTypeError, caller_stacklevel
from engine.query.frame import FAR_ORIGIN, MeshFrame, mesh_frame
from engine.query.hits import (collect_hits_kernel, compact_hits_kernel, count_hits_kernel, fill_hits_kernel,
                               first_hit_kernel)
from engine.query.locations import locations_kernel
from engine.query.order import coherent_order, ray_order
from engine.query.wide import packed_tree

#: Hits closer than this fraction of the mesh's scale (trimesh's ``mesh.scale``: its box's
#: diagonal) to the previous one along a ray are one crossing; trimesh steps 1e-6 of that scale
#: past each hit. ``merge_gap`` puts it in the local frame's units.
MERGE_GAP = 1e-6


def merge_gap(frame: MeshFrame) -> np.float32:
    """MERGE_GAP of trimesh's scale in the local frame (whose unit is the largest extent, so the
    diagonal there is 1 to sqrt(3)): with the largest extent instead, a kitchen ray kept two
    hits 9e-6 apart that trimesh's 1.2e-5 step merges."""
    return np.float32(MERGE_GAP * max(float(np.linalg.norm(frame.hi - frame.lo)), 1.0))

#: trimesh's default cap on hits per ray.
DEFAULT_MAX_HITS = 100

#: How rays are ordered before the walk (see RayMeshIntersector).
ORDERS = ("input", "morton")

#: Hits per ray kept by the one-walk all-hits kernel; rays with more take a count-then-fill walk.
SLOT = 8


class _Structure(NamedTuple):
    faces_key: object
    vertices_key: object
    faces: np.ndarray      # i64[T,3]
    frame: MeshFrame
    bvh: BVH
    nodes: np.ndarray      # f32[W,8,8] the 8-wide tree over bvh (``wide.pack_nodes``), leaf slots at blocks
    node_bits: np.ndarray  # i32[W,8,8] nodes' memory as int32: rows 6 and 7, each slot's child and size
    block_tri: np.ndarray  # i32[G,10,4] blocks' memory as int32: row 9, each lane's triangle
    blocks: np.ndarray     # f32[G,10,4] the leaves' local corners, four triangles a block
                           # (engine.query.leaf_blocks)
    tris: Triangles        # the local float32 triangles in face order (the packet walk's)
    order_keys: np.ndarray  # the packet walk's child_order_keys of bvh (made once: 0.5 ms a query)


class _Rays(NamedTuple):
    origins: np.ndarray    # f64[n,3] world, input order
    directions: np.ndarray  # f64[n,3] world, input order
    rows: np.ndarray       # i64[n] input ray walked in row k
    rank: np.ndarray       # i64[n] row of each input ray


def _content_key(array):
    """trimesh's cached content hash of a TrackedArray; a CRC of the bytes for a plain array."""
    try:
        return hash(array)
    except TypeError:
        arr = np.ascontiguousarray(array)
        return arr.shape, str(arr.dtype), zlib.crc32(arr.view(np.uint8).reshape(-1))


def _points(name: str, value) -> np.ndarray:
    """f64[n,3] from user input, or a QueryInputError / QueryTypeError naming ``name``."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise QueryTypeError(f"{name} must be a real numeric array of shape (n, 3): {exc}") from None
    if arr.dtype.kind not in "biuf":
        raise QueryTypeError(f"{name} must be a real numeric array of shape (n, 3), got dtype {arr.dtype}")
    # Nothing to ask: [], shape (0,), (0, 3) -- but (3, 0) is three points of the wrong shape.
    if arr.size == 0 and (arr.ndim < 2 or (arr.ndim == 2 and arr.shape[0] == 0)):
        return np.zeros((0, 3), np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise QueryInputError(f"{name} must have shape (n, 3), got {arr.shape}")
    return np.ascontiguousarray(arr, np.float64)


def _flag(name: str, value) -> bool:
    """A yes/no argument: True, False (numpy's too) or 1 / 0, as trimesh's callers pass them; a
    string or an array is a QueryTypeError ("no" would read as yes)."""
    if is_flag(value):
        return bool(value)
    raise QueryTypeError(f"{name} must be True or False, got {value!r}")


def _max_hits(value) -> int:
    if value is None:
        return np.iinfo(np.int64).max
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise QueryTypeError(f"max_hits must be a positive integer or None, got {value!r}")
    if value < 1:
        raise QueryInputError(f"max_hits must be >= 1 (or None for no limit), got {value}")
    return int(min(value, np.iinfo(np.int64).max))  # beyond int64 is no limit, as None


def _mesh_arrays(mesh):
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise QueryTypeError(f"RayMeshIntersector needs a mesh with .vertices and .faces (a trimesh.Trimesh), "
                             f"got {type(mesh).__name__}")
    faces = np.asarray(mesh.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise QueryInputError(f"mesh.faces must be an integer array of shape (T, 3), got {faces.dtype} {faces.shape}")
    if len(faces) == 0:
        raise QueryInputError("mesh.faces is empty: the mesh has no triangles to intersect")
    vertices = _points("mesh.vertices", mesh.vertices)
    if faces.min() < 0 or faces.max() >= len(vertices):
        row = int(np.flatnonzero(((faces < 0) | (faces >= len(vertices))).any(axis=1))[0])
        raise QueryInputError(f"mesh.faces[{row}] = {faces[row].tolist()} refers to a vertex that does not exist "
                              f"(the mesh has {len(vertices)} vertices)")
    # Only the vertices the faces use count (as for trimesh's bounds): a stray NaN one is no error.
    used = np.zeros(len(vertices), np.bool_)
    used[faces.reshape(-1)] = True
    bad = used & ~np.isfinite(vertices).all(axis=1)
    if bad.any():  # checked here: after the move to the mesh's frame every vertex would read NaN
        row = int(np.flatnonzero(bad)[0])
        raise QueryInputError(f"mesh.vertices[{row}] = {vertices[row].tolist()} is not finite "
                              f"({int(bad.sum())} such vertices)")
    return vertices, faces.astype(np.int64)


class RayMeshIntersector:
    """Ray queries on a trimesh mesh, with trimesh's ``mesh.ray`` interface (see the module doc).

    mesh       a ``trimesh.Trimesh`` (or anything with ``vertices`` f[V,3] and ``faces`` i[T,3]);
               kept as ``self.mesh`` and followed as it changes.
    leaf_size, bins  BVH build settings.
    order      "input" (default): rays are walked in the order given, except that first and
               any hits of a batch from one eye or sensor given in a shuffled order are sorted
               into packets first
               (``engine.query.coherent.packing``); "morton": the per-ray walk takes every
               batch sorted by direction octant and a Morton code of the origin
               (``engine.query.order``, numba, parallel). On random rays that sort cost more
               than it saved (see README, "Using packetrt from trimesh").
    threads    numba threads for each query (0, the default: all cores), set for that call only:
               the caller's own count (``numba.set_num_threads``) is back when it returns.
    """

    def __init__(self, mesh, *, leaf_size: int = 4, bins: int = 16, order: str = "input", threads: int = 0):
        _mesh_arrays(mesh)
        if order not in ORDERS:
            raise QueryInputError(f"order must be one of {', '.join(ORDERS)}, got {order!r}")
        if isinstance(threads, (bool, np.bool_)) or not isinstance(threads, (int, np.integer)):
            raise QueryTypeError(f"threads must be an integer >= 0 (0 = all cores), got {threads!r}")
        if threads < 0:
            raise QueryInputError(f"threads must be >= 0 (0 = all cores), got {threads}")
        try:  # checked here, not at the first query that builds the tree
            leaf_size, bins = check_build_settings(leaf_size, bins)
        except ConfigTypeError as exc:
            raise QueryTypeError(str(exc)) from None
        except ConfigError as exc:
            raise QueryInputError(str(exc)) from None
        self.mesh = mesh
        self.threads = int(threads)
        self._leaf_size, self._bins, self._order = leaf_size, bins, order
        self._structure_cache = None
        self._new_buffers()

    def _new_buffers(self) -> None:
        self._scratch, self._scratch_lock, self._iota = Scratch(), threading.Lock(), np.arange(0, dtype=np.int64)

    @contextmanager
    def _buffers(self):
        """``allocate(name, rows, tail, dtype)`` for one query's internal arrays: views of this
        intersector's scratch, or fresh arrays while another thread holds the scratch."""
        if not self._scratch_lock.acquire(blocking=False):
            yield new_array
            return
        try:
            yield self._scratch.allocator("query")
        finally:
            self._scratch_lock.release()

    def _identity(self, n: int) -> np.ndarray:
        """0..n-1 (i64[n], read only by the kernels), kept: the input order of n rays."""
        if self._iota.shape[0] < n:
            self._iota = np.arange(n, dtype=np.int64)
        return self._iota[:n]

    def __repr__(self) -> str:
        return f"RayMeshIntersector({len(self.mesh.faces):,} faces)"

    # -- structure that follows the mesh -------------------------------------------------
    def _structure(self) -> _Structure:
        faces_key, vertices_key = _content_key(self.mesh.faces), _content_key(self.mesh.vertices)
        old = self._structure_cache
        if old is not None and old.faces_key == faces_key and old.vertices_key == vertices_key:
            return old
        vertices, faces = _mesh_arrays(self.mesh)
        frame, local = mesh_frame(vertices, faces)
        tris = make_triangles(local, faces, 0, source="mesh")
        if old is not None and old.faces_key == faces_key and np.array_equal(old.faces, faces):
            bvh = refit_bvh(old.bvh, tris)  # vertices moved, same triangles: same tree, new boxes
            faces = old.faces
        else:
            bvh = build_bvh(tris, leaf_size=self._leaf_size, bins=self._bins)
        nodes, block_tri, blocks = packed_tree(bvh, tris.v0, tris.v1, tris.v2)
        keys = child_order_keys(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
        self._structure_cache = _Structure(faces_key, vertices_key, faces, frame, bvh, nodes, nodes.view(np.int32),
                                           block_tri, blocks, tris, keys)
        return self._structure_cache

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_structure_cache"] = None  # rebuilt on first use, as trimesh drops its cache
        for key in ("_scratch", "_scratch_lock", "_iota"):  # a lock does not pickle; buffers are not state
            state.pop(key, None)
        return state

    def __setstate__(self, state):
        state.setdefault("threads", 0)  # pickled before the option existed
        self.__dict__.update(state)
        self._new_buffers()

    def __copy__(self):
        return RayMeshIntersector(self.mesh, leaf_size=self._leaf_size, bins=self._bins, order=self._order,
                                  threads=self.threads)

    def __deepcopy__(self, memo):
        return self.__copy__()

    # -- rays --------------------------------------------------------------------------
    def _rays(self, s: _Structure, ray_origins, ray_directions) -> _Rays:
        origins = _points("ray_origins", ray_origins)
        directions = _points("ray_directions", ray_directions)
        if origins.shape != directions.shape:
            raise QueryInputError(f"ray_directions has shape {directions.shape} but ray_origins has "
                                  f"{origins.shape}; give one direction per origin")
        n = len(origins)
        if self._order == "morton":
            rows = ray_order(origins, directions, s.frame.center, s.frame.scale)
            rank = np.empty_like(rows)
            rank[rows] = np.arange(n)
        else:
            rows = rank = self._identity(n)
        return _Rays(origins, directions, rows, rank)

    @staticmethod
    def _warn_bad(ok: np.ndarray) -> None:
        bad = len(ok) - int(np.count_nonzero(ok))
        if bad:
            warnings.warn(f"{bad} of {len(ok)} rays have a NaN/inf component, a zero direction or an origin "
                          f"{FAR_ORIGIN:.0e} mesh sizes or more from the mesh; answered as misses", BadRayWarning,
                          stacklevel=caller_stacklevel())

    @staticmethod
    def _tree(s: _Structure):
        return s.nodes, s.node_bits, s.block_tri, s.blocks

    @staticmethod
    def _frame_args(s: _Structure, rays: _Rays):
        return rays.origins, rays.directions, s.frame.center, float(s.frame.scale)

    def _first(self, s, rays, any_hit, allocate):
        """(triangle i64[n], u, v f32[n]) of the first (any_hit: some) hit of every ray, in
        arrays from ``allocate`` (``_buffers``)."""
        n = len(rays.rows)
        tri = allocate("tri", n, (), np.int64)
        u = allocate("u", n)
        v = allocate("v", n)
        ok = allocate("ok", n, (), np.bool_)
        how = packing(rays.origins, rays.directions, s.frame.scale)
        rows = rays.rows
        if how == PACK_SORTED:
            # Shuffled rays from one eye: sorted, neighbours make packets. When they do not (too
            # few rays for their spread), the per-ray walk keeps the caller's order: it reads
            # the rays and writes the answers in sequence, which a sorted order does not.
            rows = coherent_order(rays.origins, rays.directions, s.frame.center, s.frame.scale, allocate)
            if not coherent_blocks(block_medians(rays.origins, rays.directions, s.frame.scale, rows)):
                how, rows = PACK_NONE, rays.rows
        if how == PACK_INPUT:
            width = row_length(rays.directions) if self._order == "input" else 0
            if width:  # an image given row by row: walked in tiles, as the render path walks it
                rows = tiled_rows(n, width, allocate)
        if how == PACK_NONE:
            first_hit_kernel(*self._tree(s), *self._frame_args(s, rays), rows, any_hit, tri, u, v, ok)
        else:
            packet_first_hits(s.bvh, s.tris, s.order_keys, rays.origins, rays.directions, s.frame.center,
                              s.frame.scale, rows, any_hit, tri, u, v, ok, allocate)
        self._warn_bad(ok)
        return tri, u, v

    def _all(self, s, rays, max_hits, allocate):
        """(index_ray, index_tri i64[m], u, v f32[m]): every hit, by ray then distance (new
        arrays; the per-ray slots come from ``allocate``)."""
        tree, frame = self._tree(s), self._frame_args(s, rays)
        n = len(rays.rows)
        slot = min(SLOT, max_hits)
        bt, bu, bv = (allocate(name, n * slot) for name in ("slot_t", "slot_u", "slot_v"))
        btri = allocate("slot_tri", n * slot, (), np.int32)
        kept = allocate("kept", n, (), np.int64)
        ok = allocate("ok", n, (), np.bool_)
        collect_hits_kernel(*tree, *frame, rays.rows, merge_gap(s.frame), max_hits, slot, bt, btri, bu, bv, kept, ok)
        self._warn_bad(ok)
        offsets = np.arange(n + 1, dtype=np.int64) * slot  # where each row's hits start
        over = np.flatnonzero(kept < 0)
        if len(over):  # rays with many hits: count, then fill exact slices, appended to the buffers
            rows = rays.rows[over]
            counts = np.empty(len(over), np.int64)
            count_hits_kernel(*tree, *frame, rows, counts)
            extra = np.zeros(len(over) + 1, np.int64)
            np.cumsum(counts, out=extra[1:])
            et, eu, ev = (np.empty(int(extra[-1]), np.float32) for _ in range(3))
            etri = np.empty(int(extra[-1]), np.int32)
            extra_kept = np.empty(len(over), np.int64)
            fill_hits_kernel(*tree, *frame, rows, extra, merge_gap(s.frame), max_hits, et, etri, eu, ev, extra_kept)
            offsets[over] = n * slot + extra[:-1]
            kept[over] = extra_kept
            bt, btri, bu, bv = (np.concatenate(pair) for pair in ((bt, et), (btri, etri), (bu, eu), (bv, ev)))
        out_offsets = np.zeros(n + 1, np.int64)
        np.cumsum(kept[rays.rank], out=out_offsets[1:])
        m = int(out_offsets[-1])
        index_ray, index_tri = np.empty(m, np.int64), np.empty(m, np.int64)
        t, u, v = (np.empty(m, np.float32) for _ in range(3))
        compact_hits_kernel(offsets, kept, rays.rank, out_offsets, bt, btri, bu, bv, index_ray, index_tri, t, u, v)
        return index_ray, index_tri, u, v

    # -- trimesh's interface -------------------------------------------------------------
    @memory_errors_as(QueryInputError)
    @at_own_threads  # numba's count for this call only (``engine.core.threads``)
    def intersects_id(self, ray_origins, ray_directions, multiple_hits: bool = True,
                      max_hits: int | None = DEFAULT_MAX_HITS, return_locations: bool = False):
        """Triangles hit by rays.

        ray_origins, ray_directions: (n, 3) float. multiple_hits: every hit along each ray (True,
        trimesh's default) or only the first. max_hits: at most this many hits per ray (None: no
        limit). Returns ``(index_tri int64 (m,), index_ray int64 (m,))`` plus
        ``locations float64 (m, 3)`` with return_locations; hits are ordered by ray index, then
        by distance along the ray.
        """
        limit = _max_hits(max_hits)
        multiple_hits, return_locations = _flag("multiple_hits", multiple_hits), _flag("return_locations",
                                                                                      return_locations)
        s = self._structure()
        rays = self._rays(s, ray_origins, ray_directions)
        with self._buffers() as allocate:
            if multiple_hits:
                index_ray, index_tri, u, v = self._all(s, rays, limit, allocate)
            else:  # gathered into new arrays before the scratch is let go
                tri, u, v = self._first(s, rays, False, allocate)
                index_ray = np.flatnonzero(tri >= 0).astype(np.int64)
                index_tri, u, v = tri[index_ray], u[index_ray], v[index_ray]
        if not return_locations:
            return index_tri, index_ray
        locations = np.empty((len(index_ray), 3), np.float64)
        locations_kernel(s.frame.corners, rays.origins, rays.directions, index_ray, index_tri, u, v, locations)
        return index_tri, index_ray, locations

    def intersects_location(self, ray_origins, ray_directions, multiple_hits: bool = True,
                            max_hits: int | None = DEFAULT_MAX_HITS):
        """``(locations float64 (m, 3), index_ray int64 (m,), index_tri int64 (m,))``: where rays
        hit the surface (every hit by default), ordered as ``intersects_id``. A location lies on
        the ray and on its triangle's plane, computed in float64."""
        index_tri, index_ray, locations = self.intersects_id(ray_origins, ray_directions, multiple_hits,
                                                             max_hits, True)
        return locations, index_ray, index_tri

    @memory_errors_as(QueryInputError)
    @at_own_threads
    def intersects_first(self, ray_origins, ray_directions):
        """int32 (n,): the first triangle each ray hits, -1 for a miss (or a bad ray)."""
        s = self._structure()
        rays = self._rays(s, ray_origins, ray_directions)
        with self._buffers() as allocate:
            return self._first(s, rays, False, allocate)[0].astype(np.int32)

    @memory_errors_as(QueryInputError)
    @at_own_threads
    def intersects_any(self, ray_origins, ray_directions):
        """bool (n,): whether each ray hits the surface (any hit, early exit)."""
        s = self._structure()
        rays = self._rays(s, ray_origins, ray_directions)
        with self._buffers() as allocate:
            return self._first(s, rays, True, allocate)[0] >= 0

    @memory_errors_as(QueryInputError)
    @at_own_threads
    def contains_points(self, points):
        """bool (n,): whether each point (n, 3) is inside the mesh, by the parity of the surface
        crossings along rays from it (see ``engine.query.contains``). Meaningful for watertight
        meshes; a point on the surface may go either way (as in trimesh). A NaN point is outside."""
        pts = _points("points", points)
        s = self._structure()
        out = np.empty(len(pts), np.bool_)
        contains_kernel(*self._tree(s), pts, s.frame.center, float(s.frame.scale), s.frame.lo, s.frame.hi,
                        DIRECTIONS.astype(np.float32), merge_gap(s.frame), out)
        return out
