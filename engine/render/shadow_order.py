"""Which end of its shadow rays a light's packets are walked from.

A shadow ray needs any blocker on its segment, so the walk stops at the first one it meets, and
the order in which it takes a node's children decides how soon that is. The packet walk takes
the near child first (from the surface towards the light); with ``from_end`` it takes the far
one (from the light: ``engine.packet.plugin.walk_batch``). Neither changes an answer, only how
many nodes a blocked ray visits before it stops; rays that reach the light visit the same nodes
either way.

Which end is better depends on the scene, and not simply on where the blockers lie. Counted
over a whole frame's shadow rays (nodes visited, walked from the surface / from the light):
BART Kitchen (kitchen-paper) 622,991 / 539,353 (-13%; its shadow trace 54-56 against 49-50 ms),
the default scene 70,595 / 54,183 (-23%), the bunny 48,578 / 47,060, the ERW6 stand-in 21,661 /
21,557, the Cornell box 14,135 / 16,246 (+15%). On the kitchen 87% of the blocked rays stop in
the surface half of their segment whichever end they are walked from, yet the light end is
cheaper: near a surface the tree is dense, near the lamp it is empty. A rule on the blockers'
positions chose wrongly there, and a timed trial was biased by whichever group ran first, so
``"auto"`` counts.

``ShadowOrder`` chooses per light and per kind of the rays whose hits cast the shadow rays
(primary, reflection, refraction): on the default scene the camera rays' shadow rays cost the
same from either end (0.1347 / 0.1332 nodes a ray) while those of reflection and refraction
hits cost 0.29 / 0.13, 0.62 / 0.25 and so on, batch by batch. ``"surface"`` and ``"light"``
fix the end; ``"auto"`` (the default) makes trials of an undecided (light, kind)'s batches of
at least ``engine.packet.plugin.TRIAL_PACKETS`` packets: a trial walks the packets in four
interleaved groups, two from each end, each walk counting the nodes it visits (every packet
walk counts them: a register increment a node, one addition a packet). Once both ends have
walked ``TRIAL_RAYS`` live rays of that (light, kind), the end with fewer visits per ray by at
least ``MARGIN`` is used from then on (the surface on a closer call). Every packet is still
walked once, so a trial costs three more launches. The counts do not depend on timing or
threads: the same scene always chooses the same ends. Images never depend on the choice.

State lives in the renderer that owns the ``ShadowOrder``: a second renderer chooses afresh.
"""
from __future__ import annotations

#: The config's choices (``[render] shadow_order``).
SHADOW_ORDERS = ("auto", "surface", "light")
#: A (light, kind) is decided once each end has walked this many of its live rays in trials.
TRIAL_RAYS = 8192
#: The light end is chosen when its node visits per live ray are below (1 - MARGIN) of the
#: surface's; otherwise the surface (the walk's usual order).
MARGIN = 0.03


class ShadowOrder:
    """Per (light index in the scene, kind of the rays whose hits cast the shadow rays), whether
    to walk the shadow rays from the light end (see the module doc). ``mode``: one of
    ``SHADOW_ORDERS``."""

    def __init__(self, mode: str = "auto"):
        if mode not in SHADOW_ORDERS:
            raise ValueError(f"shadow order must be one of {', '.join(SHADOW_ORDERS)}, got {mode!r}")
        self.mode = mode
        self._from_light: dict = {}
        #: (light, kind) pairs whose shadow rays a packet walk took (``record``), for ``chosen``
        self.walked: set = set()
        #: (light, kind) -> {"surface": [nodes, rays], "light": [nodes, rays]} summed over its trials
        self.trials: dict = {}

    def from_light(self, light: int, kind: str) -> bool:
        """Walk the next shadow batch of (light, kind) from the light end?"""
        if self.mode != "auto":
            return self.mode == "light"
        return self._from_light.get((light, kind), False)

    def wants_trial(self, light: int, kind: str) -> bool:
        """Whether the next shadow batch of (light, kind) should be a trial (mode "auto", not yet
        decided)."""
        return self.mode == "auto" and (light, kind) not in self._from_light

    def add_trial(self, light: int, kind: str, trial: dict) -> None:
        """Add a trial of (light, kind): {"surface": (nodes visited, live rays), "light": (nodes
        visited, live rays)}, as ``PacketTraversal.occluded`` fills it (empty, from a batch too
        small or a traversal that cannot split: nothing learnt), and decide once there is enough."""
        if not trial:
            return
        summed = self.trials.setdefault((light, kind), {"surface": [0, 0], "light": [0, 0]})
        for end in ("surface", "light"):
            summed[end][0] += trial[end][0]
            summed[end][1] += trial[end][1]
        (surface_nodes, surface_rays), (light_nodes, light_rays) = summed["surface"], summed["light"]
        if min(surface_rays, light_rays) < TRIAL_RAYS:
            return
        self._from_light[(light, kind)] = light_nodes / light_rays < (1.0 - MARGIN) * surface_nodes / surface_rays

    def record(self, light: int, kind: str) -> None:
        """A packet walk (a traversal that orders its any-hit walk) took a shadow batch of (light, kind)."""
        self.walked.add((light, kind))

    def chosen(self) -> dict:
        """{"LIGHT/KIND": "light" | "surface" | "undecided"} for every (light, kind) a packet walk
        took or a trial decided: the fixed end of mode "surface" or "light"; under "auto" the end
        decided, or "undecided" (its batches so far walked in trials, or from the surface when
        too small for one)."""
        def end(pair):
            if self.mode != "auto":
                return self.mode
            if pair in self._from_light:
                return "light" if self._from_light[pair] else "surface"
            return "undecided"
        return {f"{light}/{kind}": end((light, kind)) for light, kind in sorted(self.walked | set(self._from_light))}
