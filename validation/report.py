"""Audit report folder: ``audit.json``, the rendered image and a mismatch map.

mismatches.png is the render darkened to a third, with every pixel whose ray tree held a
mismatching ray painted red: a quick look shows whether errors cluster on edges, on one
object or on one ray kind's paths.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.core.errors import PacketrtError
from engine.core.atomic import json_text, write_text
from engine.render.image import save_png


#: The files a report folder gets (the CLI checks each can be written before the audit runs).
REPORT_FILES = ("audit.json", "render.png", "mismatches.png")


def write_report(folder: str, report: dict, image: np.ndarray, bad_pixels, width: int, height: int) -> None:
    target = Path(folder)
    try:
        target.mkdir(parents=True, exist_ok=True)
        write_text(target / "audit.json", json_text(report))
    except OSError as exc:
        raise PacketrtError(f"cannot write report folder {folder!r}: {exc.strerror or exc}") from None
    save_png(image, str(target / "render.png"))
    marked = (image / 3.0).reshape(-1, 3).copy()
    pixels = np.asarray([p for p in bad_pixels if p >= 0], np.int64)
    if pixels.size:
        marked[pixels] = (1.0, 0.0, 0.0)
    save_png(marked.reshape(height, width, 3), str(target / "mismatches.png"))
