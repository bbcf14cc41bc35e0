"""The scene's materials as flat arrays the shading kernels index by material id."""
from __future__ import annotations

import numpy as np

#: The value of byte k of an 8-bit image as the scene loaders give it: float32(k) / 255.
BYTE_PALETTE = np.arange(256, dtype=np.float32) / np.float32(255.0)


def texture_palette(textures: list) -> tuple[np.ndarray, np.ndarray]:
    """(index i[X,3], palette f32[P]) with palette[index] equal, bit for bit, to the textures'
    texels (each f32[H,W,3]) stacked row after row.

    Textures read from 8-bit images (every value k/255) share ``BYTE_PALETTE`` and a u8 index:
    a quarter of the memory of float texels, so the kitchen's 30 MB of texels become 7.5 MB that
    stay in cache, and the random texel gathers of the surface pass get about twice as fast.
    Any other texture gets a palette of its distinct values and the narrowest index that holds
    them, so no value is ever rounded.
    """
    texels = np.concatenate([np.asarray(t, np.float32).reshape(-1, 3) for t in textures])
    as_bytes = np.rint(np.clip(texels, 0.0, 1.0) * np.float32(255.0)).astype(np.uint8)
    if np.array_equal(BYTE_PALETTE[as_bytes], texels):
        return as_bytes, BYTE_PALETTE
    palette, index = np.unique(texels, return_inverse=True)
    dtype = np.uint8 if palette.size <= 1 << 8 else np.uint16 if palette.size <= 1 << 16 else np.uint32
    return np.ascontiguousarray(index.reshape(texels.shape).astype(dtype)), palette.astype(np.float32)


class MaterialTable:
    """M materials as arrays indexed by material id.

    ambient, diffuse, specular, reflectance: f32[M,3]; shininess, transmission, ior: f32[M]
    (ior 1 where the scene gives none). Textures packed for numba: texel j, channel c of all
    textures stacked row after row is palette[texels[j, c]] (texels u8/u16/u32[X,3], palette
    f32[P], see ``texture_palette``); texture_layout i64[3,M] holds, per material, where its
    texture begins in texels (row 0, -1: untextured), its width (row 1) and height (row 2).
    ``texture`` keeps the f32[H,W,3] arrays (or None) as the scene gave them. ``can_spawn``:
    some material reflects or transmits, so a hit may cast a child ray.
    """

    def __init__(self, materials):
        self.ambient = np.array([m.ambient for m in materials], np.float32).reshape(-1, 3)
        self.diffuse = np.array([m.diffuse for m in materials], np.float32).reshape(-1, 3)
        self.specular = np.array([m.specular for m in materials], np.float32).reshape(-1, 3)
        self.reflectance = np.array([m.reflectance for m in materials], np.float32).reshape(-1, 3)
        self.shininess = np.array([m.shininess for m in materials], np.float32)
        self.transmission = np.array([m.transmission for m in materials], np.float32)
        self.ior = np.array([m.ior if m.ior > 0 else 1.0 for m in materials], np.float32)
        # Whether any hit can cast a child ray: a mirror child needs a positive reflectance and
        # a refracted or totally reflected one a positive transmission (``engine.render.spawn``).
        self.can_spawn = bool((self.reflectance > 0).any() or (self.transmission > 0).any())
        self.texture = [m.texture for m in materials]
        self.texture_layout = np.zeros((3, len(materials)), np.int64)
        self.texture_layout[0] = -1
        parts, start = [], 0
        for i, texture in enumerate(self.texture):
            if texture is None:
                continue
            h, w = texture.shape[:2]
            self.texture_layout[:, i] = start, w, h
            parts.append(texture)
            start += h * w
        if parts:
            self.texels, self.palette = texture_palette(parts)
        else:
            self.texels, self.palette = np.zeros((1, 3), np.uint8), np.ones(1, np.float32)
