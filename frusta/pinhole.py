"""``pinhole``: frusta for primary rays, which all leave one eye point.

Overbeck, Ramamoorthi, Mark 2008, Section 4: the packet's frustum is bounded by its corner
rays. Here the corners are not taken from the tile's corner pixels but from the extremal rays:
along the packet's dominant axis, every live ray's direction slopes (u/w, v/w) are bounded, and
the four rays through the corners of that slope rectangle span the four side planes through
the eye. So the frustum holds every ray of the packet whatever the camera model, and is
widened by the margin of ``engine.packet.frustum_build``.

Invalid (no culling) for a packet whose live rays do not share one origin, whose directions
have no common dominant axis sign, or that has no live ray.
"""
from __future__ import annotations

from engine.core.registry import register_frustum
from engine.packet.frustum_builders import PINHOLE
from engine.packet.plugin import PacketFrustum


@register_frustum("pinhole")
class PinholeFrustum(PacketFrustum):
    """Primary rays from one eye: four planes through the eye and the packet's extremal rays."""

    builder = PINHOLE
