"""The animated preview of a frame sequence: one file a person can open (WebP, else GIF)."""
from __future__ import annotations

import numpy as np

from engine.core.atomic import replacing

#: Longest side of a preview frame, and the most frames a preview keeps (evenly spaced).
PREVIEW_SIDE = 256
PREVIEW_FRAMES = 240


def preview_format() -> str:
    """"webp" when this Pillow can write WebP, else "gif"."""
    from PIL import features

    return "webp" if features.check("webp") else "gif"


def shrink(image8: np.ndarray):
    """A PIL image of ``image8`` (u8[H,W,3]) at most PREVIEW_SIDE pixels on its longer side."""
    from PIL import Image

    picture = Image.fromarray(image8)
    scale = PREVIEW_SIDE / max(picture.size)
    if scale < 1:
        picture = picture.resize((max(1, round(picture.width * scale)), max(1, round(picture.height * scale))),
                                 Image.Resampling.BOX)
    return picture


def keep_for_preview(n_frames: int) -> set:
    """Indices (of 0..n_frames-1) the preview keeps: all, or PREVIEW_FRAMES evenly spaced."""
    if n_frames <= PREVIEW_FRAMES:
        return set(range(n_frames))
    return {round(i * (n_frames - 1) / (PREVIEW_FRAMES - 1)) for i in range(PREVIEW_FRAMES)}


def write_preview(pictures: list, path, seconds_per_frame: float) -> None:
    """Write ``pictures`` (PIL images, in order) as an endlessly looping animation to ``path``
    (its suffix picks WebP or GIF), each shown ``seconds_per_frame``, through a temporary
    file and a rename."""
    duration = max(20, round(seconds_per_frame * 1000))
    with replacing(path) as tmp:
        first, rest = pictures[0], pictures[1:]
        if str(path).endswith(".webp"):
            first.save(tmp, format="WEBP", save_all=True, append_images=rest, duration=duration, loop=0,
                       lossless=False, quality=80)
        else:
            first.save(tmp, format="GIF", save_all=True, append_images=rest, duration=duration, loop=0)
