"""Where a frame goes between its traversals: each shading pass timed around its call. A
diagnostic, not a benchmark (speed claims come from ``packetrt bench``).

    PACKETRT_SCENE_PATH=... python tools/frame_passes.py CONFIG.toml [FRAMES]

Renders FRAMES frames (default 9) of CONFIG after a warm-up frame, with every shading kernel
that ``engine.render.whitted`` calls wrapped in a timer, and prints the median frame, trace and
the rest, each pass's median milliseconds a frame, and the trace per ray kind. The wrappers cost
a few microseconds a call, against passes of milliseconds.
"""
from __future__ import annotations

import statistics
import sys
import time

import engine.render.whitted as whitted
from engine.render import config as cfg
from scenes.catalog import scene_from_config

USAGE = "PACKETRT_SCENE_PATH=... python tools/frame_passes.py CONFIG.toml [FRAMES]"
PASSES = ("shade_surface", "light_directions", "add_light_in_place", "add_light", "gather_and_spawn",
          "compact_into_packets", "camera_batch")


def main(argv: list) -> int:
    if not 1 <= len(argv) <= 2:
        print(f"usage: {USAGE}", file=sys.stderr)
        return 2
    frames = int(argv[1]) if len(argv) > 1 else 9
    config = cfg.load(argv[0])
    renderer = whitted.WhittedRenderer(scene_from_config(config.scene, config.override), config)
    renderer.warm_up()
    renderer.render()
    seconds = {}
    kernels = {name: getattr(whitted, name) for name in PASSES}

    def timed(name, kernel):
        def call(*args, **kwargs):
            start = time.perf_counter()
            answer = kernel(*args, **kwargs)
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - start
            return answer
        return call

    per_pass, totals, traces, kinds = {name: [] for name in PASSES}, [], [], {}
    for name, kernel in kernels.items():
        setattr(whitted, name, timed(name, kernel))
    try:
        for _ in range(frames):
            seconds.clear()
            result = renderer.render()
            for name in PASSES:
                per_pass[name].append(seconds.get(name, 0.0))
            totals.append(result.seconds["total"])
            traces.append(sum(result.seconds["trace"].values()))
            for kind, value in result.seconds["trace"].items():
                kinds.setdefault(kind, []).append(value)
    finally:
        for name, kernel in kernels.items():
            setattr(whitted, name, kernel)
    ms = lambda values: 1e3 * statistics.median(values)
    print(f"frame {ms(totals):.1f} ms, trace {ms(traces):.1f}, the rest {ms(totals) - ms(traces):.1f} "
          f"(medians of {frames} frames)")
    for name in PASSES:
        print(f"  {name:22s} {ms(per_pass[name]):6.2f} ms")
    for kind, values in kinds.items():
        print(f"  trace {kind:16s} {ms(values):6.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
