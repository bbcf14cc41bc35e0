"""Fit the ``auto`` traversal's thresholds and measure ``auto`` against Ranged and Partition.

    python tools/fit_auto.py [--scenes erw6,bart-museum,bart-kitchen,spd-rings] [--packets 8,16]
                             [--size 256[,1024]] [--objective worst-row|total]
                             [--repeat 5] [--measure-repeat 5] [--threads 0]
                             [--thresholds engine/packet/auto_thresholds.json]
                             [--report docs/auto-fit.md] [--limits THRESHOLDS.json]

A reduced, reproducible fit (``engine.bench.auto_fit``): the named scenes at the given
resolutions (one thresholds file for all of them: the footprint is in leaf widths), the given
packet sizes, every ray kind. Needs the BART scenes on
``PACKETRT_SCENE_PATH``. ``--measure-repeat 0`` fits without the frame measurement.
``--limits FILE`` measures the thresholds of a thresholds file (its "limits") instead of
fitting new ones, and writes no thresholds: the report then describes that file's ``auto``.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def read_limits(path: str) -> dict:
    """The "limits" of a thresholds file, checked as ``auto`` checks its options
    (``engine.packet.auto_limits.limits_array``), or ValueError naming the file and what is wrong."""
    import json

    from engine.packet.auto_limits import limits_array
    from engine.packet.choose import LIMIT_NAMES

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"--limits {path}: cannot read a JSON thresholds file ({exc})") from None
    limits = data.get("limits") if isinstance(data, dict) else None
    if not isinstance(limits, dict):
        raise ValueError(f"--limits {path}: expected a \"limits\" table with {', '.join(LIMIT_NAMES)}")
    limits_array(limits, where=f"--limits {path}: limits")  # every name, numbers, a known strategy
    return limits


def main(argv=None) -> int:
    from engine.bench import auto_fit
    from engine.core.errors import PacketrtError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(auto_fit.SCENES))
    parser.add_argument("--packets", default=",".join(map(str, auto_fit.PACKETS)))
    parser.add_argument("--size", default=str(auto_fit.SIZE), help="image side(s), comma-separated")
    parser.add_argument("--objective", default=auto_fit.OBJECTIVES[0], choices=auto_fit.OBJECTIVES)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--measure-repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="threads for the frame measurement (0: all)")
    parser.add_argument("--thresholds", default=str(ROOT / "engine/packet/auto_thresholds.json"))
    parser.add_argument("--report", default=str(ROOT / "docs/auto-fit.md"))
    parser.add_argument("--limits", default=None, help="measure this thresholds file's limits instead of fitting")
    args = parser.parse_args(argv)
    try:
        packets = [int(p) for p in args.packets.split(",")]
        sizes = [int(z) for z in args.size.split(",")]
    except ValueError:
        print(f"fit_auto: --packets and --size must be comma-separated integers, got {args.packets!r} and "
              f"{args.size!r}", file=sys.stderr)
        return 2
    if min(sizes) < 16 or args.repeat < 1 or args.measure_repeat < 0 or args.threads < 0:
        print("fit_auto: --size must be >= 16, --repeat >= 1, --measure-repeat >= 0, --threads >= 0", file=sys.stderr)
        return 2
    limits = None
    if args.limits is not None:
        try:
            limits = read_limits(args.limits)
        except ValueError as exc:
            print(f"fit_auto: {exc}", file=sys.stderr)
            return 2
    from engine.core.atomic import output_file

    try:  # the outputs can be written: checked before the fit, which takes minutes
        for option, path in (("--thresholds", args.thresholds if args.limits is None else None),
                             ("--report", args.report)):
            if path:
                output_file(path, option)
    except PacketrtError as exc:
        print(f"fit_auto: {exc}", file=sys.stderr)
        return 2
    command = "python tools/fit_auto.py " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    try:
        auto_fit.run(args.scenes.split(","), packets, sizes, args.repeat, args.measure_repeat,
                     args.thresholds, args.report, command.strip(), log=lambda m: print(m, flush=True),
                     threads=args.threads, limits=limits, objective=args.objective)
    except PacketrtError as exc:
        print(f"fit_auto: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
