"""The scene's materials as flat arrays the shading kernels index by material id."""
from __future__ import annotations

import numpy as np


class MaterialTable:
    """M materials as arrays indexed by material id.

    ambient, diffuse, specular, reflectance: f32[M,3]; shininess, transmission, ior: f32[M]
    (ior 1 where the scene gives none). Textures packed for numba: texels f32[X,3] holds every
    texture's rows one after another; texture_start i64[M] is where material m's texture begins
    in it (-1: untextured), texture_width, texture_height i64[M] its size. ``texture`` keeps the
    f32[H,W,3] arrays (or None) as the scene gave them.
    """

    def __init__(self, materials):
        self.ambient = np.array([m.ambient for m in materials], np.float32).reshape(-1, 3)
        self.diffuse = np.array([m.diffuse for m in materials], np.float32).reshape(-1, 3)
        self.specular = np.array([m.specular for m in materials], np.float32).reshape(-1, 3)
        self.reflectance = np.array([m.reflectance for m in materials], np.float32).reshape(-1, 3)
        self.shininess = np.array([m.shininess for m in materials], np.float32)
        self.transmission = np.array([m.transmission for m in materials], np.float32)
        self.ior = np.array([m.ior if m.ior > 0 else 1.0 for m in materials], np.float32)
        self.texture = [m.texture for m in materials]
        count = len(materials)
        self.texture_start = np.full(count, -1, np.int64)
        self.texture_width = np.zeros(count, np.int64)
        self.texture_height = np.zeros(count, np.int64)
        parts, start = [], 0
        for i, texture in enumerate(self.texture):
            if texture is None:
                continue
            h, w = texture.shape[:2]
            self.texture_start[i], self.texture_width[i], self.texture_height[i] = start, w, h
            parts.append(np.asarray(texture, np.float32).reshape(-1, 3))
            start += h * w
        self.texels = np.ascontiguousarray(np.concatenate(parts) if parts else np.ones((1, 3), np.float32))
