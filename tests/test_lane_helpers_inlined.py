"""The per-lane helpers that the CPU shading kernels share with the GPU frame must be inlined
into those kernels: called as functions (dozens of array arguments each) they made the kitchen
frame's shading 2.6x slower (111 ms -> 294 ms, commit faec2e9), with identical images, so no
image test could notice. numba's inliner also refuses calls of more than 30 arguments, so the
helpers' signatures must stay under that."""
import inspect

import pytest

from engine.render.direct_light import add_light_lane, light_direction_lane
from engine.render.spawn import spawn_lane
from engine.render.surface import fill_surface_lane, texel_color_lane

LANE_HELPERS = [fill_surface_lane, texel_color_lane, light_direction_lane, add_light_lane, spawn_lane]


@pytest.mark.parametrize("helper", LANE_HELPERS, ids=lambda h: h.py_func.__name__)
def test_lane_helper_is_inlined(helper):
    assert helper.targetoptions.get("inline") == "always"


@pytest.mark.parametrize("helper", LANE_HELPERS, ids=lambda h: h.py_func.__name__)
def test_lane_helper_takes_at_most_30_arguments(helper):
    assert len(inspect.signature(helper.py_func).parameters) <= 30
