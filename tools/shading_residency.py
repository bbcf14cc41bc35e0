"""How much would a tile-resident frame save on shading? A bound, measured on a real frame.

    PACKETRT_SCENE_PATH=... NUMBA_NUM_THREADS=1 python tools/shading_residency.py CONFIG.toml

Issue 14 asks for a tile-resident loop (a thread carries its tile's packets through every
generation, so their lanes stay in cache) unless generation-at-a-time measures as fast. What
residency can save is the memory traffic of the per-lane passes between traversals. This renders
one frame of CONFIG, keeps the arguments of the first (primary) call of the two largest shading
passes (``shade_surface``, ``gather_and_spawn``) and times each pass

- once over the whole batch after flushing the caches (generation-at-a-time: the lanes were
  written long before), best of 5, and
- chunk by chunk (4, 16, 64 packets), each chunk run twice in a row and only the second run
  timed (tile-resident: the chunk's lanes were just touched), best of 3 sweeps, with the
  per-call overhead (the same calls on no packet) printed beside it.

Run it on one thread, so that both sides see one core's caches. The passes write the same
values each time (``gather_and_spawn`` adds the light into the image again, which does not
change the time), so repeating them is safe here.
"""
from __future__ import annotations

import sys
import time

import numpy as np

import engine.render.whitted as whitted
from engine.render import config as cfg
from engine.render.spawn import gather_and_spawn
from engine.render.surface import shade_surface
from scenes.catalog import scene_from_config

PASSES = {"shade_surface": shade_surface, "gather_and_spawn": gather_and_spawn}
CHUNKS = (4, 16, 64)
FLUSH_BYTES = 64 << 20      # twice this machine's L3


def first_calls(config_path: str) -> dict:
    """{pass name: the argument tuple of its first call in a frame of the config}."""
    config = cfg.load(config_path)
    renderer = whitted.WhittedRenderer(scene_from_config(config.scene, config.override), config)
    renderer.warm_up()
    captured = {}

    def capturing(name, kernel):
        def call(*args):
            captured.setdefault(name, args)
            return kernel(*args)
        return call

    for name, kernel in PASSES.items():
        setattr(whitted, name, capturing(name, kernel))
    try:
        renderer.render()
    finally:
        for name, kernel in PASSES.items():
            setattr(whitted, name, kernel)
    return captured


def main(config_path: str) -> None:
    calls = first_calls(config_path)
    flush = np.ones(FLUSH_BYTES, np.uint8)
    for name, kernel in PASSES.items():
        args = list(calls[name])
        offsets = args[0].copy()  # both passes take the packet offsets i32[K+1] first
        packets = offsets.shape[0] - 1
        streamed = []
        for _ in range(5):
            flush += 1
            start = time.perf_counter()
            kernel(*args)
            streamed.append(time.perf_counter() - start)
        print(f"{name}: {packets} packets, whole batch after a cache flush {min(streamed) * 1e3:.1f} ms")
        for chunk in CHUNKS:
            sweeps = []
            for _ in range(3):
                flush += 1
                total = 0.0
                for first in range(0, packets, chunk):
                    args[0] = offsets[first:min(packets, first + chunk) + 1]
                    kernel(*args)
                    start = time.perf_counter()
                    kernel(*args)
                    total += time.perf_counter() - start
                sweeps.append(total)
            args[0] = offsets[:1]
            start = time.perf_counter()
            for _ in range(0, packets, chunk):
                kernel(*args)
            overhead = time.perf_counter() - start
            print(f"  chunks of {chunk:2d} packets, each just touched: {min(sweeps) * 1e3:.1f} ms "
                  f"(of which call overhead {overhead * 1e3:.1f} ms)")


if __name__ == "__main__":
    import argparse

    from engine.core.errors import PacketrtError

    parser = argparse.ArgumentParser(prog="shading_residency.py", description=__doc__.splitlines()[0])
    parser.add_argument("config", metavar="CONFIG.toml", help="render config (run with NUMBA_NUM_THREADS=1)")
    try:
        main(parser.parse_args().config)
    except PacketrtError as exc:
        sys.exit(f"shading_residency.py: error: {exc}")
