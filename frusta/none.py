"""``none``: no frustum; every packet is traversed without culling."""
from __future__ import annotations

import numpy as np

from engine.core.registry import register_frustum
from engine.core.types import Frusta


@register_frustum("none")
class NoFrustum:
    """No culling: every packet's frustum is marked invalid."""

    def build(self, rays, packets, scene_bounds):
        k = len(packets.offsets) - 1
        return Frusta(np.zeros((k, 4, 4), np.float32), np.zeros(k, np.bool_))
