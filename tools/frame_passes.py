"""Where a frame goes between its traversals: each shading pass timed around its call. A
diagnostic, not a benchmark (speed claims come from ``packetrt bench``).

    PACKETRT_SCENE_PATH=... python tools/frame_passes.py CONFIG.toml [FRAMES]

Renders FRAMES frames (default 9) of CONFIG after a warm-up frame, with every shading kernel
that ``engine.render.whitted`` calls wrapped in a timer, and prints the median frame, trace and
the rest, each pass's median milliseconds a frame, and the trace per ray kind. The wrappers cost
a few microseconds a call, against passes of milliseconds.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import engine.render.whitted as whitted
from engine.core.errors import PacketrtError
from engine.render import config as cfg
from scenes.catalog import scene_from_config

USAGE = "PACKETRT_SCENE_PATH=... python tools/frame_passes.py CONFIG.toml [FRAMES]"
PASSES = ("shade_surface", "light_directions", "add_light_in_place", "add_light", "gather_and_spawn",
          "compact_into_packets", "camera_batch")


def frame_count(text: str) -> int:
    """FRAMES: a whole number 1..10,000 (argparse turns the ValueError into one usage line)."""
    frames = int(text)
    if not 1 <= frames <= 10_000:
        raise ValueError(text)
    return frames


def parse(argv: list) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="frame_passes.py", usage=USAGE,
                                     description="Each shading pass of a frame timed around its call (a diagnostic).")
    parser.add_argument("config", metavar="CONFIG.toml", help="render config")
    parser.add_argument("frames", metavar="FRAMES", nargs="?", type=frame_count, default=9,
                        help="frames timed after a warm-up frame, 1..10000 (default 9)")
    return parser.parse_args(argv)


def main(argv: list) -> int:
    try:
        args = parse(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2), already printed
        return int(stop.code or 0)
    frames = args.frames
    try:
        config = cfg.load(args.config)
        renderer = whitted.WhittedRenderer(scene_from_config(config.scene, config.override), config)
    except PacketrtError as exc:
        print(f"frame_passes.py: error: {exc}", file=sys.stderr)
        return 2
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
