"""The trimmed Mitsuba zip for the GPU machine (tools/gpu_wheels.py, tools/gpu_unpack.py), on
made-up wheels (no network): what is kept and dropped, the drjit pin read from METADATA, and an
unpack that lands whole, restores modes, replaces an old folder, and refuses a zip built for
another Python or one whose paths climb out of the folder."""
import json
import sys
import zipfile

import pytest

from engine.core.errors import PacketrtError
from tests.tools_loader import load_tool

wheels = load_tool("gpu_wheels")
unpacker = load_tool("gpu_unpack")
HERE = f"{sys.version_info.major}.{sys.version_info.minor}"
VARIANTS = ("cuda_ad_rgb", "scalar_rgb")

KEPT = ["mitsuba/__init__.py", "mitsuba/config.py", "mitsuba/py.typed", "mitsuba/python/ad/optimizers.py",
        "mitsuba/libmitsuba.so", "mitsuba/libembree3.so", "mitsuba/libIlmImf-mitsuba.so",
        "mitsuba/mitsuba_ext.cpython-312-x86_64-linux-gnu.so", "mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so",
        "mitsuba/scalar_rgb.cpython-312-x86_64-linux-gnu.so", "mitsuba/plugins/diffuse.so",
        "mitsuba/plugins/uniform.so", "mitsuba/plugins/perspective.so", "mitsuba-3.9.1.dist-info/METADATA",
        "mitsuba-3.9.1.dist-info/licenses/LICENSE", "drjit/__init__.py", "drjit/cuda/__init__.py",
        "drjit/_drjit_ext.cpython-312-x86_64-linux-gnu.so", "drjit-1.5.0.dist-info/RECORD"]
DROPPED = ["mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so", "mitsuba/cuda_ad_spectral.cpython-312-x86_64-linux-gnu.so",
           "mitsuba/plugins/sphere.so", "mitsuba/plugins/obj.so", "mitsuba/data/srgb.coeff",
           "mitsuba/data/ior/Au.k.spd", "mitsuba/include/mitsuba/core/fwd.h", "mitsuba/__init__.pyi",
           "mitsuba/mitsuba", "mitsuba/cmake/mitsubaConfig.cmake", "share/doc/mitsuba/README.md",
           "mitsuba-3.9.1.dist-info/RECORD", "mitsuba-3.9.1.dist-info/entry_points.txt", "mitsuba/python/"]


def test_kept_and_dropped():
    assert [n for n in KEPT if not wheels.kept(n, VARIANTS)] == []
    assert [n for n in DROPPED if wheels.kept(n, VARIANTS)] == []
    assert wheels.kept("mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so", ("llvm_ad_rgb",))


def fake_wheel(path, names, metadata=""):
    with zipfile.ZipFile(path, "w") as z:
        for name in names:
            info = zipfile.ZipInfo(name)
            info.external_attr = (0o755 if name.endswith(".so") else 0o644) << 16
            z.writestr(info, f"contents of {name}")
        if metadata:
            z.writestr("mitsuba-3.9.1.dist-info/METADATA", metadata)
    return path


def test_the_drjit_pin_is_read_from_metadata(tmp_path):
    meta = "Name: mitsuba\nVersion: 3.9.1\nRequires-Dist: drjit==1.5.0\nRequires-Dist: numpy; extra == 'x'\n"
    assert wheels.required_drjit(fake_wheel(tmp_path / "m.whl", [], meta)) == "drjit==1.5.0"
    with pytest.raises(PacketrtError, match="no pinned drjit"):
        wheels.required_drjit(fake_wheel(tmp_path / "n.whl", [], "Name: mitsuba\nRequires-Dist: drjit>=1\n"))


@pytest.fixture
def packed(tmp_path):
    mitsuba = fake_wheel(tmp_path / "mitsuba.whl", [n for n in KEPT + DROPPED if not n.startswith("drjit")])
    drjit = fake_wheel(tmp_path / "drjit.whl", [n for n in KEPT if n.startswith("drjit")])
    out = tmp_path / "carry" / "mitsuba.zip"
    manifest = wheels.pack([mitsuba, drjit], out, VARIANTS, HERE)
    return out, manifest


def test_pack_then_unpack(packed, tmp_path):
    out, manifest = packed
    with zipfile.ZipFile(out) as z:
        names = set(z.namelist())
    assert names == set(KEPT) | {wheels.MANIFEST}
    assert manifest["files"] == len(KEPT) and manifest["python"] == HERE
    folder = tmp_path / "site"
    (folder / "stale").mkdir(parents=True)
    (folder / "stale" / "old.py").write_text("x")
    assert unpacker.unpack(out, folder)["variants"] == list(VARIANTS)
    assert not (folder / "stale").exists()  # the old folder was replaced whole
    assert (folder / "mitsuba" / "libmitsuba.so").read_text() == "contents of mitsuba/libmitsuba.so"
    assert (folder / "mitsuba" / "plugins" / "diffuse.so").stat().st_mode & 0o777 == 0o755
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".site")]  # no scratch left


def test_a_zip_for_another_python_is_refused(tmp_path, capsys):
    other = "2.7"
    out = tmp_path / "other.zip"
    with zipfile.ZipFile(out, "w") as z:
        z.writestr(unpacker.MANIFEST, json.dumps({"python": other}))
        z.writestr("mitsuba/__init__.py", "")
    folder = tmp_path / "site"
    assert unpacker.main([str(out), str(folder)]) == 2
    assert f"built for CPython {other}, this is {HERE}" in capsys.readouterr().err
    assert not folder.exists()


def test_a_path_out_of_the_folder_is_refused(tmp_path):
    out = tmp_path / "evil.zip"
    with zipfile.ZipFile(out, "w") as z:
        z.writestr("../escaped.py", "")
    with pytest.raises(ValueError, match="outside"):
        unpacker.unpack(out, tmp_path / "site")
    assert not (tmp_path / "escaped.py").exists() and not (tmp_path / "site").exists()


carry = load_tool("gpu_carry")


def test_carry_zips_scene_folders_relative_to_the_search_path(tmp_path):
    """The scenes travel as one zip that unpacks into a search path of its own."""
    search = tmp_path / "scenes"
    (search / "box" / "sub").mkdir(parents=True)
    (search / "box" / "box.obj").write_text("v 0 0 0\n")
    (search / "box" / "sub" / "tex.ppm").write_bytes(b"P6 1 1 255\n\0\0\0")
    (search / "other").mkdir()
    (search / "other" / "left.txt").write_text("not carried")
    out = tmp_path / "carry" / "scenes.zip"
    assert carry.zip_scenes(search, ["box"], out) == 2
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == ["box/box.obj", "box/sub/tex.ppm"]
        assert z.read("box/sub/tex.ppm") == b"P6 1 1 255\n\0\0\0"
    with pytest.raises(PacketrtError, match="no scene folder"):
        carry.zip_scenes(search, ["box", "missing"], tmp_path / "x.zip")


def test_carry_refuses_what_one_device_call_cannot_take():
    carry.check_size(60 * 2**20, 4 * 2**20)          # exactly the limit: fits
    with pytest.raises(PacketrtError, match="64 MiB"):
        carry.check_size(60 * 2**20, 4 * 2**20 + 1)
    assert carry.tracked_bytes() > 0
