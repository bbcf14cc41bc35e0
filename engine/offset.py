"""Robust secondary-ray origins.

Moves a hit point off its surface along the geometric normal by a few float32 ulps
(scaled with the magnitude of the coordinates), after Wald's method in "Ray Tracing
Gems" ch. 6: far from the origin the offset is an integer number of ulps, near it a
small fixed distance. The side is chosen by the caller: towards the incoming ray for
reflections and shadow rays, away from it for refraction.
"""
import numpy as np

ORIGIN_ZONE = np.float32(1.0 / 32.0)
FLOAT_SCALE = np.float32(1.0 / 65536.0)
INT_SCALE = np.float32(256.0)


def offset_origin(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """points, normals: f32[M,3] (normals point to the side to leave towards) -> f32[M,3]."""
    p = np.ascontiguousarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    ulps = (INT_SCALE * n).astype(np.int32)
    bits = p.view(np.int32)
    moved = np.where(p < 0, bits - ulps, bits + ulps).astype(np.int32).view(np.float32)
    near_origin = np.abs(p) < ORIGIN_ZONE
    return np.where(near_origin, p + FLOAT_SCALE * n, moved).astype(np.float32)
