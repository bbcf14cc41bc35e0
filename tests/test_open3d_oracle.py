"""The second oracle (Open3D's RaycastingScene): agrees with Embree on real rays including
segments (tmin, tmax) and occlusion, says exactly what is missing when Open3D cannot load, and
`packetrt audit --oracle both` finds no mismatch against either oracle."""
import builtins
import json
import sys

import numpy as np
import pytest

from engine.core.bvh import build_bvh
from engine.cli import main
from engine.render.config import Config, with_overrides
from engine.core.triangle import safe_inverse
from engine.render.plugins import make_traversal
from engine.core.types import RayBatch, empty_hits
from scenes.catalog import load_named, scene_from_config
from validation.audit import audit
from validation.compare import compare_hits, compare_occlusion
from validation.open3d_oracle import Open3DOracle, Open3DUnavailable, explain_import_failure, load_open3d
from validation.oracle import EmbreeOracle

from conftest import primary_batch


@pytest.fixture(scope="module")
def bunny():
    from conftest import needs_shared_scenes

    needs_shared_scenes()
    return load_named("bunny", {"lod": 1})


def segment_batch(scene, n, seed):
    """Incoherent rays with random segments: some start past the first surface, some stop short,
    some are dead lanes (tmax < tmin), some are one-point segments."""
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds().astype(np.float64)
    size = hi - lo
    org = rng.uniform(lo - 0.3 * size, hi + 0.3 * size, size=(n, 3))
    target = rng.uniform(lo + 0.2 * size, hi - 0.2 * size, size=(n, 3))
    dirs = target - org
    dirs *= rng.uniform(0.2, 5.0, size=(n, 1))
    length = np.linalg.norm(target - org, axis=1) / np.linalg.norm(dirs, axis=1)  # t at the target
    tmin = np.where(rng.random(n) < 0.3, rng.uniform(0, 1.5, n) * length, 0)
    tmax = np.where(rng.random(n) < 0.5, tmin + rng.uniform(0, 2.0, n) * length, np.inf)
    dead = rng.random(n) < 0.05
    tmax[dead] = tmin[dead] - 1
    point = rng.random(n) < 0.02
    tmax[point] = tmin[point]
    org, dirs = org.astype(np.float32), dirs.astype(np.float32)
    return RayBatch(org, dirs, safe_inverse(dirs), tmin.astype(np.float32), tmax.astype(np.float32),
                    np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), "reflection")


def test_open3d_agrees_with_embree_on_primary_rays(bunny):
    rays, _ = primary_batch(bunny, 96, 96, 8)
    embree = EmbreeOracle(bunny.triangles).intersect(rays)
    open3d = Open3DOracle(bunny.triangles).intersect(rays)
    result = compare_hits(rays, open3d, embree, bunny.triangles)
    assert result.mismatch.sum() == 0
    assert (open3d.prim >= 0).sum() > 2000
    same = (open3d.prim == embree.prim) & (open3d.prim >= 0)
    assert same.sum() >= 0.99 * (open3d.prim >= 0).sum()
    # Same barycentric convention: hit = (1-u-v) v0 + u v1 + v v2.
    assert np.allclose(open3d.u[same], embree.u[same], atol=1e-5)
    assert np.allclose(open3d.v[same], embree.v[same], atol=1e-5)
    assert np.allclose(open3d.t[same], embree.t[same], rtol=1e-5)


def test_open3d_honours_segments_and_occlusion(bunny):
    rays = segment_batch(bunny, 20000, seed=11)
    embree, open3d = EmbreeOracle(bunny.triangles), Open3DOracle(bunny.triangles)
    hits_e, hits_o = embree.intersect(rays), open3d.intersect(rays)
    live = rays.tmin <= rays.tmax
    assert np.all(hits_o.prim[~live] == -1) and np.all(np.isinf(hits_o.t[~live]))
    hit = hits_o.prim >= 0
    assert np.all(hits_o.t[hit] >= rays.tmin[hit] * (1 - 1e-6)) and np.all(hits_o.t[hit] <= rays.tmax[hit] * (1 + 1e-6))
    assert compare_hits(rays, hits_o, hits_e, bunny.triangles).mismatch.sum() == 0
    # Embree's oracle moves origins to tmin like this one does; our kernel takes tmin as it is.
    ours = empty_hits(rays.org.shape[0])
    make_traversal("single").intersect(build_bvh(bunny.triangles), bunny.triangles, rays, None, None, ours, None)
    assert compare_hits(rays, ours, hits_o, bunny.triangles).mismatch.sum() == 0
    occ_e, occ_o = embree.occluded(rays), open3d.occluded(rays)
    assert not occ_o[~live].any()
    assert occ_o.sum() > 1000 and (~occ_o & live).sum() > 1000
    assert compare_occlusion(rays, occ_o, occ_e, bunny.triangles, hits_o, hits_e).mismatch.sum() == 0
    # Occlusion and closest hit tell the same story.
    assert compare_occlusion(rays, occ_o, hits_o.prim >= 0, bunny.triangles, hits_o, hits_o).mismatch.sum() == 0


def test_describe():
    scene = load_named("whitted")
    info = Open3DOracle(scene.triangles).describe()
    assert info["name"] == "open3d" and info["version"] and info["robust"] is True


# -- Open3D missing --------------------------------------------------------------------------
def _fail_import(monkeypatch, error):
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise error
        return real_import(name, *args, **kwargs)

    for module in [m for m in sys.modules if m == "open3d" or m.startswith("open3d.")]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setattr(builtins, "__import__", fake_import)


LIBUSB_ERROR = ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")


def test_missing_libusb_is_named_with_its_debian_package(monkeypatch):
    _fail_import(monkeypatch, LIBUSB_ERROR)
    with pytest.raises(Open3DUnavailable) as info:
        load_open3d()
    message = str(info.value)
    assert "libusb-1.0.so.0" in message and "apt-get install libusb-1.0-0" in message


def test_missing_open3d_package_and_other_failures():
    missing = ModuleNotFoundError("No module named 'open3d'", name="open3d")
    assert "pip install open3d" in explain_import_failure(missing)
    other = OSError("libfoo.so.3: cannot open shared object file")
    assert "libfoo.so.3" in explain_import_failure(other) and "apt-file search" in explain_import_failure(other)
    assert "boom" in explain_import_failure(ImportError("boom"))


def test_cli_reports_missing_open3d_in_one_line(monkeypatch, capsys):
    _fail_import(monkeypatch, LIBUSB_ERROR)
    assert main(["audit", "--size", "16x16", "--oracle", "open3d"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("packetrt: error:")
    assert "libusb-1.0.so.0" in err[0] and "apt-get install libusb-1.0-0" in err[0]
    # Embree alone still works without Open3D.
    assert main(["audit", "--size", "16x16", "--depth", "1", "--oracle", "embree"]) == 0


# -- audits against both oracles -------------------------------------------------------------
@pytest.mark.parametrize("scene,params,override", [
    ("cornell-box", [], "reflective"), ("cornell-box", [], "refractive"),
    ("bunny", ["--param", "lod=1"], "reflective"), ("bunny", ["--param", "lod=1"], "refractive")])
def test_audit_against_both_oracles_finds_no_mismatch(shared_scenes, tmp_path, capsys, scene, params, override):
    out = tmp_path / "audit.json"
    code = main(["audit", "--scene", scene, *params, "--size", "64x64", "--depth", "2", "--override", override,
                 "--oracle", "both", "--json", str(out)])
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    assert code == 0, data["mismatches"][:3]
    assert set(data["oracles"]) == {"embree", "open3d"}
    for name, sub in data["oracles"].items():
        assert sub["oracle"]["name"] == name
        assert sub["mismatch_count"] == 0 and sub["mismatches"] == []
        assert sub["rays_checked"] == data["rays_checked"] > 64 * 64
        assert sum(r["mismatches"] for r in sub["by_kind"].values()) == 0
    assert data["mismatch_count"] == 0 and data["agreement"] == 1.0
    assert data["rays_checked"] == sum(r["checked"] for r in data["by_kind"].values())
    for row in data["by_kind"].values():
        assert row["checked"] == row["agree"] + row["ties"] + row["mismatches"]
    between = data["oracle_disagreements"]
    assert between["between"] == ["embree", "open3d"]
    assert set(between["by_kind"]["primary"]) == {"checked", "agree", "ties", "disagreements"}
    assert between["count"] == sum(r["disagreements"] for r in between["by_kind"].values())
    kind = "reflection" if override == "reflective" else "refraction"
    assert data["by_kind"][kind]["checked"] > 0
    assert "against embree" in text and "against open3d" in text and "embree vs open3d" in text


def test_audit_against_open3d_alone_keeps_the_one_oracle_report():
    config = with_overrides(Config(), size=(32, 32), depth=1)
    scene = scene_from_config(config.scene, "reflective")
    report, _, _ = audit(scene, config, oracle="open3d")
    assert report["oracle"]["name"] == "open3d" and "oracles" not in report
    assert report["mismatch_count"] == 0 and report["rays_checked"] > 32 * 32


def test_oracle_disagreements_are_counted_and_shown():
    """Two oracles that disagree (one misses every fifth ray) show up as disagreements, with
    examples, without failing our own comparison against the honest one."""
    from validation.audit import AuditObserver
    from engine.render.whitted import WhittedRenderer

    config = with_overrides(Config(), size=(32, 32), depth=0, traversal=["single"], frustum=["none"])
    scene = scene_from_config(config.scene)

    class Blind(EmbreeOracle):
        name = "blind"

        def intersect(self, rays):
            hits = super().intersect(rays)
            drop = np.zeros(rays.org.shape[0], bool)
            drop[::5] = True
            return hits._replace(prim=np.where(drop, -1, hits.prim), t=np.where(drop, np.inf, hits.t))

        def describe(self):
            return {**super().describe(), "name": "blind"}

    renderer = WhittedRenderer(scene, config)
    observer = AuditObserver(scene, renderer.bvh, [EmbreeOracle(scene.triangles), Blind(scene.triangles)])
    renderer.observer = observer
    renderer.render()
    report = observer.report()
    assert report["oracles"]["embree"]["mismatch_count"] == 0
    assert report["oracles"]["blind"]["mismatch_count"] > 0
    between = report["oracle_disagreements"]
    assert between["by_kind"]["primary"]["disagreements"] == report["oracles"]["blind"]["mismatch_count"] > 0
    example = between["examples"][0]
    assert {"embree", "blind", "ours", "ray"} <= set(example) and example["blind"]["prim"] == -1
    assert report["mismatch_count"] == report["oracles"]["blind"]["mismatch_count"]
    assert report["mismatches"][0]["mismatch_against"] == ["blind"]
