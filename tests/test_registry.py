"""Registry: config names map to plugins; unknown names list the registered ones."""
import pytest

from engine.core import registry
from engine.core.errors import ConfigError


def test_builtins_are_registered_and_answer_both_queries():
    for name in registry.traversal_names():
        plugin = registry.get_traversal(name)
        assert callable(plugin.intersect) and callable(plugin.occluded)
    for name in registry.frustum_names():
        assert callable(registry.get_frustum(name).build)


def test_unknown_names_list_what_is_registered():
    with pytest.raises(ConfigError) as info:
        registry.get_traversal("warp-drive")
    assert "single" in str(info.value) and "embree" in str(info.value)
    with pytest.raises(ConfigError, match="registered frustums: .*none"):
        registry.get_frustum("cone")


def test_entry_points_are_loaded_only_when_asked(monkeypatch):
    class FakeEntry:
        name, value, group = "fake", "fake_plugin:Fake", "packetrt.traversals"

        def load(self):
            registry.register_traversal("fake-from-entry-point")(type("Fake", (), {
                "intersect": lambda *a: None, "occluded": lambda *a: None}))

    monkeypatch.setattr(registry.metadata, "entry_points",
                        lambda group: [FakeEntry()] if group == "packetrt.traversals" else [])
    assert "fake-from-entry-point" not in registry.traversal_names()
    assert registry.load_entry_points() == ["packetrt.traversals:fake"]
    assert "fake-from-entry-point" in registry.traversal_names()
    registry.TRAVERSALS.pop("fake-from-entry-point")


@pytest.mark.parametrize("name", ["single", "simd", "masked", "ranged", "partition", "rayspace", "embree"])
def test_short_answer_arrays_are_refused_not_overrun(name):
    """Kernels index answers by ray without bounds checks: every traversal checks first."""
    import numpy as np

    from engine.core.bvh import build_bvh
    from engine.packet.layout import make_batch
    from engine.core.registry import get_traversal
    from engine.core.scene import make_triangles
    from engine.core.types import empty_hits

    tris = make_triangles(np.float32([[0, 0, 1], [1, 0, 1], [0, 1, 1]]), np.array([[0, 1, 2]]), 0)
    n = 16
    org = np.zeros((n, 3), np.float32)
    d = np.tile(np.float32([0.1, 0.1, 1]), (n, 1))
    rays, packets = make_batch("reflection", org, d, np.zeros(n), np.full(n, np.inf), np.arange(n, dtype=np.int32),
                               np.ones((n, 3)), 4, 4, 4)
    with pytest.raises(ValueError, match="one entry per ray"):
        get_traversal(name).intersect(build_bvh(tris), tris, rays, packets, None, empty_hits(n - 4), None)
