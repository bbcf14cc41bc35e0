"""Writing images: float32 linear RGB -> clamped, gamma-encoded 8-bit PNG."""
from __future__ import annotations

from engine.core.atomic import replacing


import numpy as np

from engine.core.errors import PacketrtError

GAMMA = 2.2


def to_srgb8(image: np.ndarray) -> np.ndarray:
    """f32[H,W,3] linear -> u8[H,W,3]: clamp to [0, 1], encode with 1/2.2, round."""
    clamped = np.clip(np.nan_to_num(image, nan=0.0), 0.0, 1.0)
    return np.round(clamped ** (1.0 / GAMMA) * 255.0).astype(np.uint8)


def save_png(image: np.ndarray, path: str) -> None:
    """Write ``image`` (f32[H,W,3] linear) as PNG, creating the folder; errors name the path."""
    from PIL import Image

    try:
        with replacing(path) as tmp:
            Image.fromarray(to_srgb8(image)).save(tmp, format="PNG")
    except OSError as exc:
        raise PacketrtError(f"cannot write image {path!r}: {exc.strerror or exc}") from None
