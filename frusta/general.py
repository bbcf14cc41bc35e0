"""``general``: frusta for reflection and refraction rays, which share no origin.

Overbeck, Ramamoorthi, Mark 2008, Section 4 (their new bound for secondary packets): along the
packet's dominant axis w, a near plane is put through the nearest segment start (so it lies
before the box of the ray origins) and a far plane beyond the scene box. Every live ray crosses
both; the extremal (u, v) of the crossings on each plane give the corner origins (on the near
plane) and corner directions (to the far plane) of four side planes, which hold every ray over
the whole stretch where it can meet geometry. Widened by the margin of ``engine.packet.frustum_build``.

Invalid (no culling) when the directions have no common dominant axis sign, a direction is
zero, or no ray is live.
"""
from __future__ import annotations

from engine.core.registry import register_frustum
from engine.packet.frustum_builders import GENERAL
from engine.packet.plugin import PacketFrustum


@register_frustum("general")
class GeneralFrustum(PacketFrustum):
    """Reflection / refraction rays: side planes between a near plane before the origins and a far
    plane beyond the scene."""

    builder = GENERAL
