"""The CUDA device without a GPU: every GPU kernel of the frame runs on numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``, in a child process, since the simulator replaces numba.cuda for
the whole process) on a tiny scene, and is compared with the CPU renderer and with Embree.

Speed is never asserted here: the simulator runs each GPU thread as a Python thread.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from cudasim import ROOT, simulated


@pytest.fixture(scope="module")
def frame_check():
    run = simulated("-m", "tests.gpu_sim_frame_check", "13", "11", "bvh", "3")
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_gpu_frame_casts_the_cpu_frames_rays(frame_check):
    # The same rays of every kind: the queues hold what the CPU packets hold.
    assert frame_check["rays_gpu"] == frame_check["rays_cpu"]
    assert frame_check["rays_cpu"]["shadow"] > 0
    assert frame_check["rays_cpu"]["reflection"] > 0 and frame_check["rays_cpu"]["refraction"] > 0


def test_gpu_image_equals_the_cpu_image(frame_check):
    # The simulator runs the shared per-lane functions as Python: the images agree to the
    # rounding of the per-pixel sums (the GPU adds a pixel's contributions in any order).
    assert frame_check["image_nonzero"] == 13 * 11
    assert frame_check["max_abs_difference"] <= 1e-5
    assert frame_check["pixels_over_1_255"] == 0


def test_every_gpu_ray_agrees_with_embree(frame_check):
    total = sum(frame_check["rays_gpu"].values())
    assert frame_check["audit_checked"] == total
    assert frame_check["audit_mismatches"] == 0
    assert frame_check["traversal"] == dict.fromkeys(("primary", "shadow", "reflection", "refraction"), "bvh")
    assert frame_check["shadow_far_first"] is True  # "auto": shadow rays walked from the light's end


def test_shadow_rays_walked_from_the_surface_end_give_the_same_frame(frame_check):
    """``shadow_order = "surface"``: the device walk takes the near child first; the same rays,
    image and audit as the far-first default."""
    run = simulated("-m", "tests.gpu_sim_frame_check", "13", "11", "bvh", "3", "surface")
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["shadow_far_first"] is False
    assert result["rays_gpu"] == frame_check["rays_gpu"]
    assert result["max_abs_difference"] <= 1e-5 and result["pixels_over_1_255"] == 0
    assert result["audit_mismatches"] == 0 and result["audit_checked"] == frame_check["audit_checked"]


def test_gpu_benchmark_runs_on_the_simulator(tmp_path):
    matrix = tmp_path / "gpu-tiny.toml"
    matrix.write_text('kind = "gpu"\nname = "gpu-tiny"\nresolution = 8\nrepeat_rays = 1\nrepeat_frames = 1\n'
                      '[[scene]]\nname = "whitted"\nparams = {checks = 2, subdivisions = 0}\n'
                      'recursion = "kitchen-full"\nrays = ["primary", "shadow-all", "bounce"]\n'
                      '[[variant]]\nlabel = "bvh"\ntraversal = "bvh"\n'
                      '[[variant]]\nlabel = "raster"\nrays = false\ntraversal = {primary = "bvh", '
                      'shadow = "rayspace", reflection = "rayspace", refraction = "rayspace"}\n')
    run = simulated("-m", "engine.cli", "bench", str(matrix), "--device", "cuda", "--out", str(tmp_path / "out"))
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads((tmp_path / "out" / "gpu.json").read_text())
    assert [r["rays"] for r in result["rays"]] == ["primary", "shadow-all", "bounce"]
    assert all(r["bvh"]["embree"]["mismatches"] == 0 for r in result["rays"])
    assert result["audits"][0]["mismatches"] == 0 and result["audits"][0]["checked"] > 64
    # A traversal per ray kind (camera rays by bvh, the rest by rayspace): its frame, audited.
    raster = [a for a in result["audits"] if a["variant"] == "raster"]
    assert len(raster) == 1 and raster[0]["mismatches"] == 0 and raster[0]["checked"] == result["audits"][0]["checked"]
    assert [r for r in result["rays"] if "raster" in r] == []
    assert result["images"][0]["over_1_255"] == 0
    assert "| whitted |" in (tmp_path / "out" / "gpu.md").read_text()


def test_device_cuda_without_a_gpu_is_one_clean_line():
    from numba import cuda

    if cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    run = subprocess.run([sys.executable, "-m", "engine.cli", "render", "--device", "cuda", "--size", "8x8",
                          "-o", os.devnull], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "device 'cuda'" in lines[0] and "Traceback" not in run.stderr


def test_device_names_are_checked_without_cuda():
    from engine.core.errors import ConfigError
    from engine.render import config as cfg

    with pytest.raises(ConfigError, match="render.device must be one of cpu, cuda"):
        cfg.from_dict({"render": {"device": "tpu"}})
    with pytest.raises(ConfigError, match="'embree' has no CUDA version"):
        cfg.from_dict({"render": {"device": "cuda"}, "traversal": {"shadow": "embree"}})
    # CPU BVH traversal names run as the device's bvh; the config stays as written.
    config = cfg.from_dict({"render": {"device": "cuda"}, "traversal": {"primary": "ranged"}})
    from engine.render.device_names import device_traversal_name

    assert device_traversal_name(config.traversal.primary) == "bvh"
    assert device_traversal_name("rayspace") == "rayspace"
    assert device_traversal_name("wide") == "wide"  # the 8-wide tree on both targets


def test_cpu_only_commands_refuse_the_gpu(tmp_path):
    run = subprocess.run([sys.executable, "-m", "engine.cli", "show", "--device", "cuda", "-o",
                          str(tmp_path / "s.png")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "not supported here" in run.stderr


def test_ray_tracer_on_the_device_answers_as_the_cpu_does():
    run = simulated("-m", "tests.gpu_sim_api_check")
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["hits"] > 10
    assert result["host_equal"] and result["host_types"] == ["ndarray"] * 4
    assert result["device_equal"] and result["device_stays_on_device"]
    assert result["occluded_equal"]
    assert result["scalar_bounds_equal"] == [True] * 21
    assert 1 <= result["bounds_kept"] <= 4  # DeviceQueries.KEPT_BOUNDS
    assert result["host_tensor_equal"]  # a CPU tensor's answers are not allocated on its library's device
    assert result["errors"] == ["DeviceQueryError", "DeviceQueryError", "ApiArgumentError"]
    assert result["render_device"] == "cuda" and result["render_difference"] <= 1e-5
    assert result["bvh_named_traversal"] == "bvh" and result["bvh_named_difference"] <= 1e-5
    assert result["trimesh_names"] == [True] * 4
    # The device keeps no counters: the stats say so instead of claiming a counting pass.
    assert result["counters_from"].startswith("none: the GPU's kernels keep no traversal counters")


def test_gpu_frame_with_textures_equals_the_cpu_frame(frame_check):
    """Textured materials and wrapping texture coordinates: the texel lookup twin (an integer
    index on the device, where math.floor gives a float) picks the CPU's texels."""
    run = simulated("-m", "tests.gpu_sim_frame_check", "13", "11", "bvh", "3", "textured")
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert abs(result["image_mean"] - frame_check["image_mean"]) > 1e-3  # the textures are seen
    assert result["max_abs_difference"] <= 1e-5 and result["pixels_over_1_255"] == 0
    assert result["audit_mismatches"] == 0


@pytest.mark.parametrize("width, height, traversal, depth", [(9, 7, "rayspace", 2), (13, 11, "wide", 3)])
def test_gpu_frame_with_another_device_traversal(width, height, traversal, depth):
    """The same frame with ``rayspace`` for every ray kind (hierarchies built per generation on
    the device, shadow rays reversed to leave the one light), or with ``wide`` (the CPU's 8-wide
    tree, one thread a ray): the same rays, image and audit as the CPU frame."""
    run = simulated("-m", "tests.gpu_sim_frame_check", str(width), str(height), traversal, str(depth))
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["traversal"] == dict.fromkeys(("primary", "shadow", "reflection", "refraction"), traversal)
    assert result["rays_gpu"] == result["rays_cpu"] and result["rays_cpu"]["shadow"] > 0
    assert result["max_abs_difference"] <= 1e-5 and result["pixels_over_1_255"] == 0
    assert result["audit_mismatches"] == 0 and result["audit_checked"] == sum(result["rays_gpu"].values())


def render_with_free_memory(free: int, args: list, timeout: int):
    """``packetrt render --device cuda ARGS`` on the simulator, which is told the GPU has
    ``free`` bytes free (it reports infinite memory of its own)."""
    return simulated("-c", "import sys\n"
                     "from numba import cuda\n"
                     f"class Info:\n    free = {free}\n    total = {free}\n"
                     "type(cuda.current_context()).get_memory_info = lambda self: Info\n"
                     "from engine.cli import main\n"
                     f"sys.exit(main(['render', '--device', 'cuda', *{args!r}]))", timeout=timeout)


def test_a_frame_larger_than_the_free_gpu_memory_is_one_line(tmp_path):
    """Checked before any allocation, from the device's free memory (faked here: the
    simulator reports infinite memory)."""
    out = tmp_path / "never.png"
    run = render_with_free_memory(2**16, ["--size", "64x64", "--param", "subdivisions=0", "-o", str(out)], 120)
    assert run.returncode == 2, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "GiB of GPU memory" in lines[0] and "render smaller" in lines[0]
    assert not out.exists()


def test_rayspace_pair_buffers_larger_than_the_free_gpu_memory_are_one_line(tmp_path):
    """The frame fits, but the ray-space stream's pair buffers (they hold the pair budget: 4M
    pairs, 64 MiB, by default) do not: one line naming the budget, exit 2, no image."""
    out = tmp_path / "never.png"
    run = render_with_free_memory(8 * 2**20, ["--traversal", "rayspace", "--size", "16x16", "--param",
                                              "subdivisions=0", "-o", str(out)], 300)
    assert run.returncode == 2, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert "GiB of GPU memory" in lines[0] and "pair_budget (now 4,194,304 pairs" in lines[0], lines[0]
    assert not out.exists()


def test_bench_device_cuda_on_a_cpu_matrix_is_one_line(tmp_path, capsys):
    from engine.cli import main

    assert main(["bench", str(ROOT / "benchmarks" / "smoke.toml"), "--device", "cuda", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'runs matrices of kind = "gpu"' in err[0]
