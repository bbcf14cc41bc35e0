"""A BART ``.aff`` scene along its animation path: parsed once, placed at any time.

BART's rules are to render the whole path, so a frame must not pay for parsing. ``AffAnimation``
parses the files and walks the scene graph once (``scenes.aff``), places every block under a
static transform once, and then, per frame, only re-places what moves: blocks under an animated
transform (``x name``) and animated triangles (``tpa``). Their rows of the triangle arrays are
rebuilt by the same ``make_triangles`` as a whole scene's, so ``scene_at(t)`` equals a scene
loaded from scratch at ``t`` bit for bit (the triangle arrays are computed row by row).

``load_aff`` (one instant) and the catalog's ``aff`` loader and animator live here too.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.checked import COORDINATE_LIMIT
from engine.core.errors import ConfigError, SceneError
from engine.core.scene import PointLight, SceneBuilder, make_triangles, recentring
from engine.core.types import Triangles

from .aff import Loader, _camera_from, _face_normals, _floats, _transform, check_params
from .aff_placement import MIRRORED, MovingRows, write_triangle_rows
from .catalog import scene_animator, scene_loader


class AffAnimation:
    """The scene rooted at ``path``, placed at any ``time`` by ``scene_at(time)``.

    tessellation, camera, lights: as the loader parameters in ``scenes.aff``.
    start, end: the animation range of the file's ``a`` directive in seconds (0, 0 without one);
    frames: its frame count (1 without one). animated: whether anything moves (a transform, a
    ``tpa`` triangle or the camera).
    """

    def __init__(self, path, tessellation: int = 3, camera: str = "auto", lights: Optional[int] = None):
        started = _time.perf_counter()
        self.path = Path(path)
        if not self.path.is_file():
            raise SceneError(f"{self.path}: .aff file not found")
        self.loader = loader = Loader(self.path, 0.0, tessellation)
        loader.walk(self.path)
        if lights is not None and lights > len(loader.lights):
            raise ConfigError(f"lights = {lights}, but {self.path.name} has {len(loader.lights)} point light(s); "
                              f"give 0..{len(loader.lights)} or \"all\"")
        self.keep_lights, self.camera_mode, self.tessellation = lights, camera, tessellation
        self.moving_nodes = loader.animated_nodes()
        if not loader.instances and not loader.animated_tris:
            raise SceneError(f"{self.path}: the scene has no geometry")
        self.has_normals = any(g.normals is not None for _, g, _ in loader.instances) or bool(loader.animated_tris)
        self.has_uvs = any(g.uvs is not None for _, g, _ in loader.instances)
        world = loader.world_matrices(0.0)
        # Blocks under static transforms are placed once (their rows complete: normals and uvs
        # filled in); None marks a block placed per frame, with every other moving row.
        self.static_parts = [None if self.moving_nodes[node] else self._complete(world[node], g, m)
                             for node, g, m in loader.instances]
        self.moving = MovingRows(loader, [p is None for p in self.static_parts], self.has_normals, self.has_uvs)
        anim = loader.settings["animation"]
        self.start, self.end, self.frames = (float(anim[0]), float(anim[1]), int(anim[2])) if anim else (0.0, 0.0, 1)
        _, camera_kind = _camera_from(loader.settings["view"], loader.keyframes, 0.0, camera, str(self.path))
        self.animated = bool(self.moving_nodes.any() or loader.animated_tris or camera_kind == "animated")
        # Rows of the triangle arrays each moving part fills, and the arrays of the last full build.
        self._moving_rows: Optional[np.ndarray] = None
        self._base: Optional[Triangles] = None
        self.origin: Optional[np.ndarray] = None   # re-centring shift, set by the first build
        self._materials_checked = False            # set once a frame's build has checked them
        self.parse_seconds = _time.perf_counter() - started

    # -- geometry ------------------------------------------------------------------------
    def _complete(self, matrix, geometry, material) -> tuple:
        """(corners, normals | None, uvs | None, material i32[t]) of a block placed by
        ``matrix``, normals (geometric where the block has none) and uvs (zero) filled in when
        the scene carries them."""
        placed, normals = _transform(matrix, geometry.corners, geometry.normals)
        uvs = geometry.uvs
        if np.linalg.det(matrix[:3, :3]) < 0:  # a mirror turns the winding: turn it back (see mirrored_rows)
            placed, normals, uvs = (None if x is None else x[:, MIRRORED] for x in (placed, normals, uvs))
        if self.has_normals and normals is None:
            normals = _face_normals(placed)
        uvs = (uvs if uvs is not None else np.zeros((len(placed), 3, 2))) if self.has_uvs else None
        return placed, normals if self.has_normals else None, uvs, np.full(len(placed), material, np.int32)

    def _placed(self, time: float, world: list, moving_only: bool) -> tuple:
        """(corners f64[T,3,3], normals f64[T,3,3] | None, uvs f64[T,3,2] | None, material
        i32[T]) of every row in scene order, or of the moving rows only, at ``time`` (``world``:
        the transform nodes' matrices then)."""
        moved = self.moving.place(world, time)
        if moving_only:
            return moved
        pieces, blocks = [], iter(self.moving.blocks)
        for static in self.static_parts:
            if static is None:
                _, start, end = next(blocks)
                static = tuple(None if a is None else a[start:end] for a in moved)
            pieces.append(static)
        tail = self.moving.n_block_rows
        pieces.append(tuple(None if a is None else a[tail:] for a in moved))
        return tuple(None if pieces[0][i] is None else np.concatenate([p[i] for p in pieces]) for i in range(4))

    def _triangles(self, corners, normals, uvs, materials) -> Triangles:
        """One Triangles from placed rows (see ``_placed``), re-centred by ``origin``."""
        if self.origin is not None:
            corners = corners - self.origin
        t = len(corners)
        return make_triangles(corners.reshape(-1, 3), np.arange(3 * t).reshape(t, 3), materials,
                              normals=normals, uvs=uvs, source=str(self.path))

    def _triangles_at(self, time: float, world: list) -> Triangles:
        """The scene's triangles at ``time``: the first call builds every row; later calls copy
        that build and rebuild the moving rows only (equal, row for row, to a full build). The
        caller copies what it keeps (the first call's arrays are the kept build)."""
        if self._base is None:
            placed = self._placed(time, world, moving_only=False)
            # A scene far from the origin is re-centred, as SceneBuilder does for meshes, by one
            # shift for the whole path: the scene's at the path's start, whatever time comes
            # first, so that `render --time t` and an animation's frame at t (from any --start)
            # are the same image. The first frame's shift made them differ by a pixel.
            at_start = placed if time == self.start else \
                self._placed(self.start, self.loader.world_matrices(self.start), moving_only=False)
            corners = at_start[0].reshape(-1, 3)
            self.origin = recentring(corners.min(axis=0), corners.max(axis=0))
            self._base = self._triangles(*placed)
            rows, start = [], 0
            for (_, geometry, _), static in zip(self.loader.instances, self.static_parts):
                if static is None:
                    rows.append(np.arange(start, start + len(geometry.corners)))
                start += len(geometry.corners)
            rows.append(np.arange(start, start + len(self.loader.animated_tris)))
            self._moving_rows = np.concatenate(rows).astype(np.int64)
            return self._base
        fresh = [a.copy() for a in self._base]
        rows = self._moving_rows
        if rows.size:
            corners, normals, uvs, material = self._placed(time, world, moving_only=True)
            origin = np.zeros(3) if self.origin is None else np.asarray(self.origin, np.float64)
            none3, none2 = np.zeros((0, 3, 3)), np.zeros((0, 3, 2))
            if write_triangle_rows(rows, corners, none3 if normals is None else normals,
                                   none2 if uvs is None else uvs, material, origin, COORDINATE_LIMIT, *fresh):
                return Triangles(*fresh)
            moved = self._triangles(corners, normals, uvs, material)   # says which corner is bad
            for array, new in zip(fresh, moved):
                if array.shape[0]:            # normals / uvs may be absent: shape (0, ...)
                    array[rows] = new
        return Triangles(*fresh)

    # -- the scene -----------------------------------------------------------------------
    def scene_at(self, time: float):
        """The Scene at ``time`` seconds (clamped to the keys by the splines, as BART holds the
        end keys): triangles, camera and lights placed, materials shared between frames."""
        started = _time.perf_counter()
        time = float(time)
        loader = self.loader
        world = loader.world_matrices(time)
        first = self._base is None
        tris = self._triangles_at(time, world)
        builder = SceneBuilder(self.path.stem, source=str(self.path))
        builder.materials = list(loader.builder.materials)
        # The first frame's arrays are the kept build, which build() copies; a later frame's are
        # its own fresh copy, kept as they are (a second copy of 110k triangles: 2 ms a frame).
        builder.add_triangles(tris, owned=not first)
        shift = np.zeros(3) if self.origin is None else self.origin
        placed_lights = [PointLight(_floats(world[node][:3, :3] @ position + world[node][:3, 3] - shift), _floats(colour))
                         for node, position, colour in loader.lights]
        view = loader.settings["view"]
        cam, camera_kind = _camera_from(view, loader.keyframes, time, self.camera_mode, str(self.path))
        if cam is not None and self.origin is not None:
            cam = replace(cam, eye=_floats(np.asarray(cam.eye) - shift), look_at=_floats(np.asarray(cam.look_at) - shift))
        anim = loader.settings["animation"]
        n_tpa = len(loader.animated_tris)
        n_moving = sum(len(g.corners) for (_, g, _), s in zip(loader.instances, self.static_parts) if s is None)
        t = tris.v0.shape[0]
        info = {
            "triangles": t, "static_triangles": t - n_moving - n_tpa, "animated_triangles": n_moving + n_tpa,
            "tpa_triangles": n_tpa, "primitives": dict(loader.counts), "files": len(loader.parsed),
            "materials": len(builder.materials), "textures": len(loader.textures),
            "keyframes": sorted(loader.keyframes), "unkeyed_transforms": sorted(loader.unkeyed),
            "camera": camera_kind, "tessellation": self.tessellation,
            "animation": ({"start": anim[0], "end": anim[1], "frames": anim[2]} if anim else None),
            "resolution": view.get("resolution") if view else None,
            "hither": float(view["hither"][0]) if view and "hither" in view else None,
            "file_lights": len(loader.lights),
        }
        # The materials are the loader's objects for the whole path: checked with the first frame.
        scene = builder.build(camera=cam, lights=placed_lights, background=loader.settings["background"],
                              ambient_light=loader.settings["ambient"], materials_checked=self._materials_checked,
                              animated=self.animated, time=time, info=info)
        self._materials_checked = True
        if self.origin is not None:
            scene.origin = _floats(self.origin)
        if self.keep_lights is not None:
            # After build: with no light, build() would make one up; lights = 0 means none at all.
            scene.lights = placed_lights[:self.keep_lights]
        info["load_seconds"] = round(_time.perf_counter() - started, 3)
        return scene


def load_aff(path: Path, time: float = 0.0, tessellation: int = 3, camera: str = "auto",
             lights: Optional[int] = None):
    """Load the .aff scene rooted at ``path`` at ``time`` seconds, keeping the first ``lights``
    point lights in file order (None: all of them)."""
    started = _time.perf_counter()
    animation = AffAnimation(path, tessellation, camera, lights)
    scene = animation.scene_at(time)
    scene.info["load_seconds"] = round(_time.perf_counter() - started, 3)
    return scene


def _checked_time(time) -> float:
    try:
        time = float(time)
    except (TypeError, ValueError):
        raise ConfigError(f"scene time must be a number of seconds, got {time!r}") from None
    if not math.isfinite(time):
        raise ConfigError(f"scene time must be finite, got {time!r}")
    return time


@scene_loader("aff")
def aff_scene(files, params, time):
    """Catalog loader: the first file is the root .aff."""
    if not files:
        raise SceneError("the aff loader needs the root .aff file")
    tessellation, camera, lights = check_params(params)
    return load_aff(Path(files[0]), _checked_time(time), tessellation, camera, lights)


@scene_animator("aff")
def aff_animation(files, params) -> AffAnimation:
    """Catalog animator: the scene parsed once, for ``scene_at(time)`` per frame."""
    if not files:
        raise SceneError("the aff loader needs the root .aff file")
    tessellation, camera, lights = check_params(params)
    return AffAnimation(Path(files[0]), tessellation, camera, lights)
