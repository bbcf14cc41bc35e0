"""Run under numba's CUDA simulator (in its own process): ``packetrt animate --device cuda`` on
the small moving .aff path of ``tests/test_animate.py``, refitting, against the CPU's frames.
Prints one JSON object (``tests/test_gpu_animate.py`` checks it). Usage: ``python -m
tests.gpu_sim_animate_check FOLDER [TRAVERSAL]`` (the config word for both devices; default the
config's)."""
from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import numpy as np
from PIL import Image


def main(folder: Path, traversal: str | None = None) -> dict:
    from engine.cli import main as cli
    from tests.cudasim import prepare
    from tests.test_animate import SCENE

    prepare()
    scene = folder / "moving.aff"
    scene.write_text(textwrap.dedent(SCENE))
    codes = {}
    # The device's own name "bvh" is the CPU's BVH traversals on the device ("single" here).
    names = {"cpu": {"bvh": "single"}.get(traversal, traversal), "cuda": traversal}
    for device in ("cpu", "cuda"):
        codes[device] = cli(["animate", "--scene", str(scene), "--size", "12x10", "--packet", "4", "--frames", "3",
                             "--accel", "refit", "--device", device, "-o", str(folder / device),
                             "--stats", str(folder / f"{device}.json")] + (["--audit"] if device == "cuda" else [])
                            + (["--traversal", names[device]] if traversal else []))
    difference = max(float(np.abs(np.asarray(Image.open(folder / "cpu" / f"frame_{i:05d}.png"), np.int32)
                                  - np.asarray(Image.open(folder / "cuda" / f"frame_{i:05d}.png"), np.int32)).max())
                     for i in range(3))
    frames = json.loads((folder / "cuda.json").read_text())["path"]["frames"]
    return {"codes": codes, "png_difference": difference, "policies": [f["accel"]["policy"] for f in frames],
            "rays": [f["rays"] for f in frames],
            "cpu_rays": [f["rays"] for f in json.loads((folder / "cpu.json").read_text())["path"]["frames"]]}


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]), *sys.argv[2:3])))
