"""Whole frames of two or more render configurations, interleaved and paired by repetition.

    python tools/paired_frames.py --scene bart-kitchen --recursion kitchen-paper --size 1024 \
        --variant simd/none/2 --variant paper/paper/16 [--repeat 21] [--threads 2] [--report OUT.md]

Each ``--variant`` is TRAVERSAL/FRUSTUM/PACKET, the names of ``packetrt bench`` matrices
(``paper`` for the paper's per-kind choice). Every repetition renders one frame of each variant,
in alternating order, and each later variant's frame and trace time is divided by the first's in
the same repetition (``engine.bench.paired_frames``): Table 2's per-frame ratio without the
host's drift between cells. Prints the markdown report (and writes it to ``--report``, atomically).
Needs the scene on ``PACKETRT_SCENE_PATH``. A bad argument is one line and exit code 2.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_variant(text: str, args):
    """The Cell of ``TRAVERSAL/FRUSTUM/PACKET`` with the run's scene, recursion, size and threads."""
    from engine.bench.matrix import RECURSION, Cell, SceneSpec, parse_variant
    from engine.core.errors import ConfigError

    if args.recursion not in RECURSION:
        raise ConfigError(f"--recursion {args.recursion!r}: expected one of {', '.join(RECURSION)}")
    traversal, frustum, packet = parse_variant(text, "--variant", repr(text))
    return Cell(SceneSpec(args.scene, label=args.scene), traversal, frustum, packet, args.recursion,
                args.size, args.size, threads=args.threads, embree=False)


def main(argv=None) -> int:
    from engine.bench.paired_frames import markdown, paired_frames
    from engine.core.atomic import output_file, write_text
    from engine.core.errors import PacketrtError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", required=True)
    parser.add_argument("--recursion", default="kitchen-paper")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--variant", action="append", default=[])
    parser.add_argument("--repeat", type=int, default=21)
    parser.add_argument("--threads", type=int, default=0, help="threads (0: all)")
    parser.add_argument("--report", default=None)
    args = parser.parse_args(argv)
    if len(args.variant) < 2 or args.repeat < 1 or not 16 <= args.size <= 8192 or args.threads < 0:
        print("paired_frames: give two or more --variant, --repeat >= 1, --size 16..8192, --threads >= 0",
              file=sys.stderr)
        return 2
    try:
        if args.report:
            output_file(args.report, "--report")  # before the frames, not after them
        cells = [parse_variant(v, args) for v in args.variant]
        result = paired_frames(cells, args.repeat, log=lambda m: print(m, file=sys.stderr, flush=True))
        text = markdown(result, f"{args.scene} {args.recursion} {args.size}x{args.size}, "
                                f"{args.repeat} paired repetitions, {cells[0].threads or 'all'} threads")
        if args.report:
            write_text(args.report, text)
    except PacketrtError as exc:
        print(f"paired_frames: {exc}", file=sys.stderr)
        return 2
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
