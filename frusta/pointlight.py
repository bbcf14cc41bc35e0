"""``pointlight``: frusta for shadow rays towards one point light.

Overbeck, Ramamoorthi, Mark 2008, Section 4: shadow rays to a point light share the light as a
common point, so their frustum is the pinhole frustum seen from the light. In packetrt a shadow
ray starts at the surface and runs towards the light, stopping at tmax just short of it, so the
light is recovered as the end point org + tmax dir of the packet's first live ray. From it,
along the dominant axis of the vectors light -> segment start, the extremal (u, v) slopes at unit
distance give the four corner rays and the side planes through the light. The planes are widened
by the spread of the end points around the light (the rays stop a little short, by different
amounts) on top of the margin of ``engine.packet.frustum_build``.

Invalid (no culling) when the rays do not meet at one point (end points more than END_SPREAD of
the shortest ray from the first one, or an infinite tmax), have no common dominant axis sign, are
degenerate (a ray starting at the light), or none is live. The kernel and END_SPREAD are in
``engine.packet.frustum_builders``.
"""
from __future__ import annotations

from engine.core.registry import register_frustum
from engine.packet.frustum_builders import POINTLIGHT
from engine.packet.plugin import PacketFrustum


@register_frustum("pointlight")
class PointLightFrustum(PacketFrustum):
    """Shadow rays towards one point light: four planes through the light and the extremal rays."""

    builder = POINTLIGHT
