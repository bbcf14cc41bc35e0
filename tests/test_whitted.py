"""The Whitted loop: every ray kind is cast, and Embree as the traversal gives the same image."""
import numpy as np

from engine.render.config import Config, with_overrides
from engine.render.image import save_png, to_srgb8
from engine.render.whitted import WhittedRenderer
from scenes.catalog import load_named


def render(traversal, size=(96, 72), depth=4, count=False):
    config = with_overrides(Config(), traversal=[traversal], frustum=["none"], size=size, depth=depth)
    return WhittedRenderer(load_named("whitted"), config, count=count).render()


def test_default_scene_casts_every_ray_kind_and_shows_shadows():
    result = render("single", count=True)
    for kind in ("primary", "shadow", "reflection", "refraction"):
        assert result.rays[kind] > 0, kind
        assert result.seconds["trace"][kind] > 0
    assert result.rays["primary"] == 96 * 72
    assert result.counters["ray_tri"]["primary"] > 0 and result.counters["ray_aabb"]["shadow"] > 0
    assert result.image.shape == (72, 96, 3) and result.image.dtype == np.float32


def test_spheres_cast_shadows_on_the_floor():
    answers = []
    config = with_overrides(Config(), traversal=["single"], frustum=["none"], size=(96, 72), depth=0)
    renderer = WhittedRenderer(load_named("whitted"), config,
                               observer=lambda kind, query, rays, packets, answer:
                               answers.append(answer[rays.tmin <= rays.tmax]) if kind == "shadow" else None)
    renderer.render()
    occluded = np.concatenate(answers)
    assert 0.02 < occluded.mean() < 0.5


def test_single_and_embree_render_the_same_image():
    a = to_srgb8(render("single").image).astype(int)
    b = to_srgb8(render("embree").image).astype(int)
    differ = np.abs(a - b).max(axis=2) > 2
    assert differ.mean() < 0.001, f"{differ.sum()} pixels differ"


def test_depth_zero_has_no_secondary_rays():
    result = render("single", depth=0)
    assert result.rays["reflection"] == result.rays["refraction"] == 0
    assert result.rays["shadow"] > 0


def test_png_is_gamma_encoded_and_clamped(tmp_path):
    image = np.array([[[0.0, 0.5, 4.0]]], np.float32)
    assert to_srgb8(image).tolist() == [[[0, round(0.5 ** (1 / 2.2) * 255), 255]]]
    save_png(image, str(tmp_path / "sub" / "x.png"))
    assert (tmp_path / "sub" / "x.png").stat().st_size > 0


def test_counting_render_sums_plugin_stats_over_every_batch():
    """Reflection rays come in one batch per depth: the rayspace record must hold them all,
    not just the last batch's."""
    config = with_overrides(Config(), traversal=["single", "reflection=rayspace"], frustum=["none"],
                            size=(64, 48), depth=3)
    calls = []
    renderer = WhittedRenderer(load_named("whitted"), config, count=True,
                               observer=lambda kind, query, rays, packets, answer:
                               calls.append(int((rays.tmin <= rays.tmax).sum())) if kind == "reflection" else None)
    result = renderer.render()
    record = result.extra["reflection"]["rayspace"]
    assert len(calls) >= 2
    assert record["calls"] == len(calls)
    assert record["rays"] == sum(calls) == result.rays["reflection"]


def test_counters_sum_over_batches_and_threads():
    one = render("single", count=True)
    per_depth = one.counters_by_depth["ray_tri"]["reflection"]
    assert sum(per_depth) == one.counters["ray_tri"]["reflection"] > 0


def test_options_of_one_config_do_not_reach_the_next():
    """Plugins are new instances per renderer: a small pair_budget and Embree robust off in one
    config, then the defaults in the same process, and the second render used the defaults."""
    from engine.render.config import from_dict

    scene = load_named("whitted")
    tables = {"render": {"width": 48, "height": 48, "max_depth": 2},
              "traversal": {"primary": "embree", "shadow": "embree", "reflection": "rayspace",
                            "refraction": "rayspace"}}

    def rendered(options):
        config = from_dict(dict(tables, options=options) if options else tables)
        renderer = WhittedRenderer(scene, config)
        result = renderer.with_counters(renderer.render())
        return renderer, result.extra

    _, before = rendered(None)
    full = before["reflection"]["rayspace"]
    assert full["batches"] == full["calls"] and before["primary"]["embree"]["robust"] is True
    small_budget = max(full["peak_pairs"] // 5, 1)
    small, tweaked = rendered({"rayspace": {"pair_budget": small_budget}, "embree": {"robust": False}})
    assert small.traversal["reflection"].pair_budget == small_budget
    assert tweaked["reflection"]["rayspace"]["batches"] > full["calls"] and tweaked["primary"]["embree"]["robust"] is False
    again, after = rendered(None)
    assert again.traversal["reflection"].pair_budget == 1 << 22 and again.traversal["primary"].robust is True
    assert after["reflection"]["rayspace"]["batches"] == full["calls"] and after["primary"]["embree"]["robust"] is True
    assert after["reflection"]["rayspace"]["peak_pairs"] == full["peak_pairs"]


def test_a_renderer_reusing_its_arrays_renders_what_a_fresh_one_does():
    """Answer and per-lane arrays are reused from frame to frame and not reset before a packet
    walk (it writes every answer): a frame after a larger one, and after a different camera
    batch layout, equals the same frame from a fresh renderer."""
    scene = load_named("whitted")
    config = with_overrides(Config(), packet=8)
    renderer = WhittedRenderer(scene, config)
    renderer.render(size=(80, 64))
    reused = renderer.render(size=(40, 56)).image
    fresh = WhittedRenderer(scene, config).render(size=(40, 56)).image
    assert np.array_equal(reused, fresh)
