"""Open3DOracle: a second ground truth, Open3D's ``RaycastingScene``, on any RayBatch.

Same interface as ``validation.oracle.EmbreeOracle``: ``intersect(rays) -> Hits``,
``occluded(rays) -> bool[R]``, ``describe() -> {"name", "version", "robust"}``.

Open3D wraps its own build of Embree (a different version from embreex's, with its own scene
settings: Open3D sets RTC_SCENE_FLAG_ROBUST) behind a different front end, so it checks the
audit's first oracle as well as our traversals.

How RayBatch maps onto Open3D's queries:

- Open3D casts from the origin with t in [0, inf) and takes no per-ray tnear, so a live ray
  is moved to ``org + tmin * dir`` and ``tmin`` is added back to ``t_hit`` (as
  ``engine.core.embree_scene`` does for embreex). Dead lanes (``tmax < tmin``) are not cast.
- Closest hit: ``cast_rays``; a hit beyond ``tmax`` is a miss (it is the closest hit, so there
  is none inside the segment). ``primitive_uvs`` are Embree's (u, v): hit =
  (1-u-v) v0 + u v1 + v v2, our convention.
- Occlusion: ``test_occlusions`` takes one scalar ``tfar`` for all rays, so a ray with a
  finite segment gets its direction scaled by ``tmax - tmin`` and ``tfar = 1``; rays with
  ``tmax = inf`` go unscaled with ``tfar = inf``.

Open3D's Linux wheels need the Debian package libusb-1.0-0 at import time. When ``import
open3d`` fails, ``load_open3d`` raises ``Open3DUnavailable`` naming the missing library and the
package that provides it.
"""
from __future__ import annotations

import re

import numba
import numpy as np

from engine.core.errors import PacketrtError
from engine.core.types import Hits, RayBatch, Triangles

#: Shared libraries Open3D's wheel loads at import, and the Debian packages that provide them.
DEBIAN_PACKAGES = {
    "libusb-1.0.so.0": "libusb-1.0-0",
    "libgomp.so.1": "libgomp1",
    "libGL.so.1": "libgl1",
    "libEGL.so.1": "libegl1",
    "libX11.so.6": "libx11-6",
    "libstdc++.so.6": "libstdc++6",
}

_MISSING_LIBRARY = re.compile(r"(lib[\w.+-]*?\.so(?:\.\d+)*)")


class Open3DUnavailable(PacketrtError):
    """Open3D cannot be imported here; the message says what to install."""


def explain_import_failure(exc: BaseException) -> str:
    """One line saying why ``import open3d`` failed and what to install."""
    text = str(exc)
    if isinstance(exc, ModuleNotFoundError) and (exc.name or "").split(".")[0] == "open3d":
        return ("the open3d oracle needs the Python package open3d, which is not installed in this "
                "environment: pip install open3d (the project's set-up, `make`, installs it)")
    match = _MISSING_LIBRARY.search(text)
    if match:
        library = match.group(1)
        package = DEBIAN_PACKAGES.get(library)
        fix = (f"install the Debian package {package}: apt-get install {package}" if package else
               f"install the system package that provides {library} (Debian: apt-file search {library})")
        return (f"the open3d oracle cannot load Open3D: the shared library {library} is missing; {fix} "
                f"(.ci/system-deps does this when run as root) [{type(exc).__name__}: {text}]")
    return f"the open3d oracle cannot import open3d: {type(exc).__name__}: {text}"


def load_open3d():
    """The ``open3d`` module, or ``Open3DUnavailable`` saying what is missing."""
    try:
        import open3d
    except (ImportError, OSError) as exc:
        raise Open3DUnavailable(explain_import_failure(exc)) from exc
    return open3d


class Open3DOracle:
    """Ground truth from Open3D's ``t.geometry.RaycastingScene`` (Embree inside, robust flag set
    by Open3D).

    intersect(rays) -> Hits; occluded(rays) -> bool[R]; ``describe()`` gives
    {"name", "version", "robust"} for reports.
    """

    name = "open3d"

    def __init__(self, tris: Triangles, threads: int | None = None):
        o3d = load_open3d()
        self._o3d = o3d
        self.version = o3d.__version__
        self.threads = int(threads if threads is not None else numba.get_num_threads())
        # An unindexed soup: corner k of triangle i is vertex 3 i + k, so primitive ids are ours.
        corners = np.ascontiguousarray(np.stack([tris.v0, tris.v1, tris.v2], axis=1).reshape(-1, 3),
                                       np.float32)
        indices = np.arange(corners.shape[0], dtype=np.uint32).reshape(-1, 3)
        self.scene = o3d.t.geometry.RaycastingScene(nthreads=self.threads)
        self.scene.add_triangles(o3d.core.Tensor(corners), o3d.core.Tensor(indices))

    def _rays(self, org, dirs):
        return self._o3d.core.Tensor(np.ascontiguousarray(np.concatenate([org, dirs], axis=1), np.float32))

    def _shifted(self, rays: RayBatch):
        """(live ray indices, their tmin f32, origins moved to tmin f32[L,3], directions f32[L,3])."""
        live = np.flatnonzero(rays.tmin <= rays.tmax)
        tmin = rays.tmin[live]
        dirs = rays.dir[live].astype(np.float32)
        org = (rays.org[live] + tmin[:, None] * dirs).astype(np.float32)
        return live, tmin, org, dirs

    def intersect(self, rays: RayBatch) -> Hits:
        n = rays.org.shape[0]
        hits = Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int32),
                    np.zeros(n, np.float32), np.zeros(n, np.float32))
        live, tmin, org, dirs = self._shifted(rays)
        if live.size == 0:
            return hits
        answer = self.scene.cast_rays(self._rays(org, dirs), nthreads=self.threads)
        t = answer["t_hit"].numpy().astype(np.float32)
        prim = answer["primitive_ids"].numpy()
        uv = answer["primitive_uvs"].numpy()
        reach = (rays.tmax[live] - tmin).astype(np.float32)
        hit = np.isfinite(t) & (t <= reach) & (prim != np.iinfo(np.uint32).max)
        rows = live[hit]
        hits.t[rows] = t[hit] + tmin[hit]
        hits.prim[rows] = prim[hit].astype(np.int32)
        hits.u[rows] = uv[hit, 0]
        hits.v[rows] = uv[hit, 1]
        return hits

    def occluded(self, rays: RayBatch) -> np.ndarray:
        out = np.zeros(rays.org.shape[0], np.bool_)
        live, tmin, org, dirs = self._shifted(rays)
        if live.size == 0:
            return out
        reach = (rays.tmax[live] - tmin).astype(np.float32)
        finite = np.isfinite(reach) & (reach > 0)
        for sel, scale, tfar in ((finite, True, 1.0), (np.isinf(reach), False, float("inf"))):
            if not sel.any():
                continue
            d = dirs[sel] * reach[sel, None] if scale else dirs[sel]
            answer = self.scene.test_occlusions(self._rays(org[sel], d.astype(np.float32)), tnear=0.0,
                                                tfar=tfar, nthreads=self.threads)
            out[live[sel]] = answer.numpy().astype(bool)
        point = reach == 0  # a one-point segment: occluded when a surface passes through it
        if point.any():
            answer = self.scene.cast_rays(self._rays(org[point], dirs[point]), nthreads=self.threads)
            out[live[point]] = answer["t_hit"].numpy() <= 0
        return out

    def describe(self) -> dict:
        return {"name": self.name, "version": self.version, "robust": True,
                "note": "Open3D RaycastingScene (its own Embree build; Open3D sets RTC_SCENE_FLAG_ROBUST)"}
