"""``tools/gpu_api_check.py`` runs only on a GPU machine with torch and CuPy; its ray sets are
made here, so a change to the camera or the scene API breaks this test rather than a lease."""

import numpy as np

from scenes.catalog import load_named
from tests.tools_loader import load_tool

def test_the_tools_ray_sets_are_float32_rays_of_the_asked_size():
    tool = load_tool("gpu_api_check")
    scene = load_named("whitted")
    for org, dirs in (tool.camera_rays(scene, 24), tool.incoherent_rays(scene, 576)):
        assert org.shape == dirs.shape == (576, 3)
        assert org.dtype == dirs.dtype == np.float32 and org.flags.c_contiguous and dirs.flags.c_contiguous
        assert np.isfinite(org).all() and (np.abs(dirs).sum(axis=1) > 0).all()
    org, dirs = tool.camera_rays(scene, 24)
    assert np.allclose(org, org[0])  # a pinhole camera: one origin
    lo, hi = scene.triangles.v0.min(axis=0), scene.triangles.v0.max(axis=0)
    org, _ = tool.incoherent_rays(scene, 576)
    assert (org >= lo).all() and (org <= hi).all()
