"""Registry and composition root: config names map to plugin factories; every request makes a
new instance; unknown names list the registered ones."""
import pytest

from engine.core import registry
from engine.core.errors import ConfigError
from engine.render import plugins


def test_builtins_are_registered_and_answer_both_queries():
    for name in plugins.traversal_names():
        plugin = plugins.make_traversal(name)
        assert callable(plugin.intersect) and callable(plugin.occluded) and plugin.name == name
    for name in plugins.frustum_names():
        assert callable(plugins.make_frustum(name).build)


def test_every_request_makes_a_new_instance():
    for name in plugins.traversal_names():
        assert plugins.make_traversal(name) is not plugins.make_traversal(name)
    assert all(isinstance(cls, type) for cls in registry.TRAVERSALS.values())


def test_options_go_to_the_new_instance_only():
    small = plugins.make_traversal("rayspace", {"pair_budget": 5})
    assert small.pair_budget == 5
    assert plugins.make_traversal("rayspace").pair_budget == 1 << 22
    assert plugins.make_traversal("embree", {"robust": False}).robust is False
    assert plugins.make_traversal("embree").robust is True


def test_unknown_options_name_the_allowed_ones():
    with pytest.raises(ConfigError, match=r"options\.rayspace: unknown key\(s\) \['budget'\]; allowed: pair_budget"):
        plugins.make_traversal("rayspace", {"budget": 5})
    with pytest.raises(ConfigError, match=r"options\.single: 'single' takes no options"):
        plugins.make_traversal("single", {"robust": True})
    with pytest.raises(ConfigError, match=r"options\.embree: robust must be true or false"):
        plugins.make_traversal("embree", {"robust": 1})


def test_registering_an_instance_is_refused():
    with pytest.raises(TypeError, match="register a class"):
        registry.register_traversal("instance")(object())
    assert "instance" not in registry.TRAVERSALS


def test_unknown_names_list_what_is_registered():
    with pytest.raises(ConfigError) as info:
        plugins.make_traversal("warp-drive")
    assert "single" in str(info.value) and "embree" in str(info.value)
    with pytest.raises(ConfigError, match="registered frustums: .*none"):
        plugins.make_frustum("cone")


def test_entry_points_are_loaded_only_when_asked(monkeypatch):
    class FakeEntry:
        name, value, group = "fake", "fake_plugin:Fake", "packetrt.traversals"

        def load(self):
            registry.register_traversal("fake-from-entry-point")(type("Fake", (), {
                "intersect": lambda *a: None, "occluded": lambda *a: None}))

    monkeypatch.setattr(registry.metadata, "entry_points",
                        lambda group: [FakeEntry()] if group == "packetrt.traversals" else [])
    assert "fake-from-entry-point" not in plugins.traversal_names()
    assert plugins.load_entry_points() == ["packetrt.traversals:fake"]
    assert "fake-from-entry-point" in plugins.traversal_names()
    registry.TRAVERSALS.pop("fake-from-entry-point")


@pytest.mark.parametrize("name", ["single", "simd", "masked", "ranged", "partition", "auto", "rayspace", "embree"])
def test_short_answer_arrays_are_refused_not_overrun(name):
    """Kernels index answers by ray without bounds checks: every traversal checks first."""
    import numpy as np

    from engine.core.bvh import build_bvh
    from engine.packet.layout import make_batch
    from engine.core.scene import make_triangles
    from engine.core.types import empty_hits

    tris = make_triangles(np.float32([[0, 0, 1], [1, 0, 1], [0, 1, 1]]), np.array([[0, 1, 2]]), 0)
    n = 16
    org = np.zeros((n, 3), np.float32)
    d = np.tile(np.float32([0.1, 0.1, 1]), (n, 1))
    rays, packets = make_batch("reflection", org, d, np.zeros(n), np.full(n, np.inf), np.arange(n, dtype=np.int32),
                               np.ones((n, 3)), 4, 4, 4)
    with pytest.raises(ValueError, match="one entry per ray"):
        plugins.make_traversal(name).intersect(build_bvh(tris), tris, rays, packets, None, empty_hits(n - 4), None)
