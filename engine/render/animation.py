"""Rendering an animation path in one process, the way BART measures it.

Per frame, four phases, each timed:

- ``scene``: keyframe interpolation and transforms (``ScenePath.scene_at``; the files were
  parsed once, before the path);
- ``accel``: keeping the BVH current (``engine.render.accel``: rebuild, refit or auto), plus
  the build of any plugin's own structure (Embree's scene is rebuilt for the moved triangles);
- ``trace``: every ray batch's traversal (frustum build included), as in a still render;
- ``shade``: the rest of the frame (camera rays, shading, compaction, image).

JIT compile time is kept apart: ``warm_up`` compiles (or loads) the builder, the refit and the
frame kernels on the path's first frame before any frame is timed.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from engine.core.errors import ConfigError
from engine.core.bvh import build_bvh
from engine.core.threads import at_own_threads
from engine.render.accel import BVHKeeper
from engine.render.plugins import uses_bvh
from engine.render.whitted import RenderResult, WhittedRenderer

#: The most frames one animation may have (a frame count beyond is surely a typo).
MAX_FRAMES = 100_000


def path_times(start: float, end: float, frames: int) -> list[float]:
    """``frames`` instants evenly spaced over [start, end], both ends included (one frame:
    ``start``)."""
    if frames == 1:
        return [float(start)]
    step = (end - start) / (frames - 1)
    return [float(start + i * step) for i in range(frames - 1)] + [float(end)]


def plan_times(path, frames: int | None = None, fps: float | None = None, start: float | None = None,
               end: float | None = None) -> list[float]:
    """The frame instants of an animation of ``path`` (a ScenePath): over [start, end] (default:
    the whole path) at ``frames`` frames, or ``fps`` frames per second of scene time, or the
    scene's own frame count scaled to the range. Out-of-range values raise ConfigError."""
    lo = path.start if start is None else start
    hi = path.end if end is None else end
    for name, value in (("--start", lo), ("--end", hi)):
        if not math.isfinite(value) or not path.start <= value <= path.end:
            raise ConfigError(f"{name} {value:g} is outside the animation path of {path.name!r}: "
                              f"{path.start:g}..{path.end:g} s")
    if hi < lo:
        raise ConfigError(f"--end {hi:g} is before --start {lo:g}")
    if frames is not None and fps is not None:
        raise ConfigError("give --frames or --fps, not both")
    if fps is not None:
        if not (math.isfinite(fps) and fps > 0):
            raise ConfigError(f"--fps must be a positive number of frames per second, got {fps:g}")
        span_frames = (hi - lo) * fps  # a float first: 1e308 fps overflows to inf, which floor() refuses
        if not span_frames + 1 <= MAX_FRAMES:
            raise ConfigError(f"--fps {fps:g} over {hi - lo:g} s makes {span_frames + 1:,.0f} frames; "
                              f"at most {MAX_FRAMES:,}")
        count = math.floor(span_frames + 1e-9) + 1
        # min(): lo + i / fps may round past the end (50.00000000000001 s), a time --end refuses.
        return [min(lo + i / fps, hi) for i in range(count)]
    if frames is None:
        span = path.end - path.start
        frames = path.frames if span <= 0 else max(1, round(path.frames * (hi - lo) / span))
    if not 1 <= frames <= MAX_FRAMES:
        raise ConfigError(f"--frames must be in 1..{MAX_FRAMES:,}, got {frames:,}")
    return path_times(lo, hi, frames)


@dataclass
class Frame:
    """One rendered frame: its index on the path, its time, the render, and its record
    ({"time", "seconds": {"scene", "accel", "trace", "shade", "total"}, "accel": {"policy",
    "sah_cost", "sah_ratio"}, "rays"})."""

    index: int
    time: float
    result: RenderResult
    record: dict


class AnimationRenderer:
    """Renders frames of ``path`` (a ScenePath) with ``config``, keeping the BVH current by the
    config's ``[accel]`` policy. ``observer_for(scene, bvh)``: makes the renderer's observer
    for each frame (the animation audit), or None."""

    def __init__(self, path, config, observer_for=None, make_renderer=WhittedRenderer):
        """``make_renderer(scene, config, bvh=...)``: the frame renderer (the front end passes
        ``engine.gpu.choose.new_renderer``, which gives the GPU's for ``device = "cuda"``)."""
        self.path, self.config, self.observer_for = path, config, observer_for
        self.threads = config.render.threads  # numba's count inside each method below only
        self.make_renderer = make_renderer
        self.keeper = self._new_keeper()
        self.renderer = None
        self.last_frame_seconds = None   # auto's rebuild budget is a share of it
        self.fresh_observer = None       # the observer of the last render_with_fresh_tree

    def _new_keeper(self) -> BVHKeeper:
        r, a = self.config.render, self.config.accel
        return BVHKeeper(a.update, leaf_size=r.leaf_size, bins=r.bins, degrade=a.degrade, budget=a.budget,
                         needs_tree=uses_bvh(self.config))

    @at_own_threads
    def warm_up(self, time_: float) -> float:
        """Compile or load every kernel a frame uses (scene placement, the build, a refit, the
        SAH cost, the frame) on the scene at ``time_``, with throwaway state; returns seconds."""
        start = time.perf_counter()
        scene = self.path.scene_at(time_)
        # A second time: the first call places every row, later ones only the moving rows (a
        # kernel of their own, which compiled inside frame 0's timed scene phase: 0.8 s).
        other = self.path.end if time_ != self.path.end else self.path.start
        if other != time_:
            scene = self.path.scene_at(other)
            scene = self.path.scene_at(time_)
        keeper = BVHKeeper("auto", leaf_size=self.config.render.leaf_size, bins=self.config.render.bins)
        bvh, _ = keeper.update(scene.triangles)
        keeper.update(scene.triangles)                      # a refit and its SAH cost
        if self.renderer is None:
            self.renderer = self.make_renderer(scene, self.config, bvh=bvh)
        else:
            self.renderer.set_scene(scene, bvh)
        self.renderer.warm_up()
        return time.perf_counter() - start

    @at_own_threads
    def frame(self, index: int, time_: float) -> Frame:
        """Render the frame at ``time_`` (``index``: its place on the path, for the record)."""
        started = time.perf_counter()
        scene = self.path.scene_at(time_)
        bvh, accel = self.keeper.update(scene.triangles, self.last_frame_seconds)
        if self.renderer is None:
            self.renderer = self.make_renderer(scene, self.config, bvh=bvh)
        else:
            self.renderer.set_scene(scene, bvh)
        # accel: our tree's update and plugins' own builds (Embree's scene for the moved
        # triangles); scene: the rest of getting the frame's scene ready.
        accel_seconds = accel["seconds"] + sum(self.renderer.prepare_seconds.values())
        scene_seconds = time.perf_counter() - started - accel_seconds
        self.renderer.observer = self.observer_for(scene, bvh) if self.observer_for else None
        result = self.renderer.render()
        trace = sum(result.seconds["trace"].values())
        seconds = {"scene": scene_seconds, "accel": accel_seconds, "trace": trace,
                   "shade": result.seconds["total"] - trace}
        seconds["total"] = seconds["scene"] + seconds["accel"] + result.seconds["total"]
        self.last_frame_seconds = seconds["total"]
        record = {"index": index, "time": time_, "seconds": seconds,
                  "accel": {"policy": accel["policy"], "reason": accel.get("reason"), "sah_cost": accel["sah_cost"],
                            "sah_ratio": accel["sah_ratio"]},
                  "rays": dict(result.rays)}
        return Frame(index, time_, result, record)

    @at_own_threads
    def render_with_fresh_tree(self, observer_for=None) -> RenderResult:
        """The frame just rendered, again, over a tree freshly built for it (``observer_for(scene,
        bvh)`` makes the observer of that render, or None); the kept tree is put back."""
        scene, kept = self.renderer.scene, self.renderer.bvh
        r = self.config.render
        fresh = build_bvh(scene.triangles, leaf_size=r.leaf_size, bins=r.bins)
        observer = self.renderer.observer
        try:
            self.renderer.set_scene(scene, fresh)
            self.renderer.observer = observer_for(scene, fresh) if observer_for else None
            return self.renderer.render()
        finally:
            self.fresh_observer = self.renderer.observer
            self.renderer.set_scene(scene, kept)
            self.renderer.observer = observer

    @at_own_threads
    def compare_with_fresh_tree(self, frame: Frame, repeat: int = 2) -> dict:
        """Trace the frame just rendered again, with the kept tree and with one freshly built for
        it, interleaved, ``repeat`` times each; the fastest of each compared (the same moment,
        so machine noise hits both). Adds and returns frame.record["fresh_tree"] = {"kept",
        "fresh" (trace seconds), "trace_ratio" (kept / fresh)}. Not part of the frame's time."""
        scene, kept = self.renderer.scene, self.renderer.bvh
        r = self.config.render
        fresh = build_bvh(scene.triangles, leaf_size=r.leaf_size, bins=r.bins)
        observer, self.renderer.observer = self.renderer.observer, None
        times = {"kept": [], "fresh": []}
        try:
            for _ in range(repeat):
                for name, bvh in (("kept", kept), ("fresh", fresh)):
                    self.renderer.set_scene(scene, bvh)
                    times[name].append(sum(self.renderer.render().seconds["trace"].values()))
        finally:
            self.renderer.set_scene(scene, kept)
            self.renderer.observer = observer
        best = {name: min(values) for name, values in times.items()}
        best["trace_ratio"] = best["kept"] / best["fresh"] if best["fresh"] > 0 else None
        frame.record["fresh_tree"] = best
        return best

    def restart(self) -> None:
        """Forget the kept tree (the next frame builds afresh), e.g. after frames were skipped."""
        self.keeper = self._new_keeper()
        self.last_frame_seconds = None


def path_summary(records: list) -> dict:
    """BART's numbers over frame records: {"frames": records, "mean_fps", "slowest_seconds",
    "total_seconds", "phase_share": {phase: share of the total}}."""
    totals = [r["seconds"]["total"] for r in records]
    total = float(sum(totals))
    phases = ("scene", "accel", "trace", "shade")
    return {
        "frames": records,
        "mean_fps": len(records) / total if total > 0 else None,
        "slowest_seconds": max(totals) if totals else None,
        "total_seconds": total,
        "phase_share": {p: (sum(r["seconds"][p] for r in records) / total if total > 0 else None) for p in phases},
        "policies": {p: sum(r["accel"]["policy"] == p for r in records) for p in ("rebuild", "refit", "none")},
    }
