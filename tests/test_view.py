"""``packetrt view``: the interactive window, driven for real on a virtual X server (Xvfb): it
opens, a mouse drag orbits the camera, the image changes and the panel shows its numbers. And
without a display it says so in one line and exits with code 2."""
import json
import math
import os
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from engine.core.scene import Camera
from engine.debug.view import orbit

ROOT = Path(__file__).resolve().parents[1]
NO_DISPLAY = ("packetrt: error: packetrt view needs a display (DISPLAY is not set); run it under Xvfb, "
              "e.g. xvfb-run packetrt view")


def run_view(env, *args, timeout=60):
    return subprocess.run([sys.executable, "-m", "engine.cli", "view", *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=timeout)


def test_no_display_is_a_one_line_error():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    start = time.perf_counter()
    run = run_view(env)
    assert run.returncode == 2
    assert run.stderr.strip() == NO_DISPLAY
    assert time.perf_counter() - start < 15  # refused before any scene, render or GUI work


def test_unreachable_display_is_a_one_line_error():
    env = {**{k: v for k, v in os.environ.items() if k != "WAYLAND_DISPLAY"}, "DISPLAY": ":4095"}
    run = run_view(env)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "cannot open the display ':4095'" in run.stderr


def test_orbit_keeps_distance_and_look_at():
    cam = Camera((0.0, 2.6, 7.5), (0.0, 0.9, 0.0), (0.0, 1.0, 0.0), 42.0)
    moved = orbit(cam, azimuth=0.7, elevation=0.2)
    assert moved is not cam and cam.eye == (0.0, 2.6, 7.5)
    assert moved.look_at == cam.look_at and moved.fov == cam.fov
    dist = lambda c: np.linalg.norm(np.subtract(c.eye, c.look_at))
    assert dist(moved) == pytest.approx(dist(cam))
    assert orbit(cam, zoom=2.0).eye == pytest.approx(tuple(np.add(cam.look_at, 2 * np.subtract(cam.eye, cam.look_at))))
    top = orbit(cam, elevation=10.0)  # clamped short of the pole
    height = (np.subtract(top.eye, top.look_at) @ np.array([0, 1.0, 0])) / dist(top)
    assert height == pytest.approx(math.sin(math.radians(85)))


def test_frame_source_renders_the_latest_request():
    """The render worker behind the window (no GUI): a camera or panel change is a new frame
    with that camera and config; a bad setting comes back as an error, not a dead worker."""
    import threading
    from dataclasses import replace

    from engine.render.config import Config, with_overrides
    from engine.debug.view import FrameSource
    from scenes.catalog import scene_from_config

    config = with_overrides(Config(), size=(32, 32), packet=8, depth=1)
    scene = scene_from_config(config.scene, "none")
    frames, arrived = [], threading.Event()

    def on_frame(*frame):
        frames.append(frame)
        arrived.set()

    source = FrameSource(scene, config, on_frame)
    source.start()

    def next_frame():
        assert arrived.wait(30)
        arrived.clear()
        return frames[-1]

    image, result, seconds, used, camera, error = next_frame()
    assert error is None and image.shape == (32, 32, 3) and result.rays["primary"] == 32 * 32
    source.request(camera=orbit(camera, azimuth=1.0))
    moved = next_frame()
    assert moved[4] != camera and not np.array_equal(moved[0], image)
    source.request(config=with_overrides(config, traversal=["primary=single"], packet=4))
    switched = next_frame()
    assert switched[3].traversal.primary == "single" and switched[3].render.packet == 4
    assert switched[4] == moved[4]  # the camera stays where it was
    source.request(config=replace(config, traversal=replace(config.traversal, primary="nope")))
    assert "nope" in next_frame()[5]
    source.request(config=config)
    assert next_frame()[5] is None
    source.close()
    source.thread.join(10)
    assert not source.thread.is_alive()


# -- the real window ---------------------------------------------------------------------------

def _tools():
    missing = [tool for tool in ("Xvfb", "xdotool") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"{' and '.join(missing)} not installed (Debian: xvfb, xdotool; see .ci/system-deps)")
    from PIL import features

    if not features.check("xcb"):
        pytest.skip("Pillow was built without XCB: it cannot take X screenshots")


@pytest.fixture
def xvfb():
    """A fresh virtual X server on a free display (Xvfb picks it and tells us); yields ':N'."""
    _tools()
    read_end, write_end = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write_end), "-screen", "0", "1280x1024x24",
                               "-nolisten", "tcp"], pass_fds=(write_end,), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    os.close(write_end)
    # Xvfb writes the number and then a newline: read both, and keep the pipe open while it runs
    # (closing it early turns its second write into a fatal error).
    received = b""
    deadline = time.monotonic() + 10
    while not received.endswith(b"\n") and time.monotonic() < deadline:
        ready, _, _ = select.select([read_end], [], [], max(deadline - time.monotonic(), 0))
        chunk = os.read(read_end, 64) if ready else b""
        if not chunk:
            break
        received += chunk
    number = received.decode().strip()
    if not received.endswith(b"\n") or not number.isdigit():
        server.kill()
        os.close(read_end)
        pytest.fail(f"Xvfb did not report a display number within 10 s (got {received!r})")
    try:
        yield f":{number}"
    finally:
        server.terminate()
        server.wait(10)
        os.close(read_end)


def _status(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _wait_for(predicate, timeout, what):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    pytest.fail(f"timed out after {timeout} s waiting for {what}")


def _screenshot(display, box):
    from PIL import ImageGrab

    return np.asarray(ImageGrab.grab(bbox=box, xdisplay=display).convert("RGB")).astype(np.int16)


def test_view_orbits_and_shows_its_numbers_under_xvfb(xvfb, tmp_path):
    status_file = tmp_path / "status.json"
    env = {**os.environ, "DISPLAY": xvfb}
    env.pop("WAYLAND_DISPLAY", None)
    log = open(tmp_path / "view.log", "w")
    app = subprocess.Popen([sys.executable, "-m", "engine.cli", "view", "--size", "128x128",
                            "--status-file", str(status_file), "--exit-after", "60"],
                           env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    xdo = lambda *a: subprocess.run(["xdotool", *a], env=env, capture_output=True, text=True, timeout=30)
    try:
        found = xdo("search", "--sync", "--onlyvisible", "--name", "packetrt view")
        assert found.stdout.split(), f"no window: {found.stderr} {(tmp_path / 'view.log').read_text()}"
        window = found.stdout.split()[0]
        first = _wait_for(lambda: (s := _status(status_file)) and s["frames"] >= 1 and s, 30, "the first frame")
        geometry = dict(line.split("=") for line in xdo("getwindowgeometry", "--shell", window).stdout.split())
        x, y, w, h = first["image_frame"]
        left, top = int(geometry["X"]) + x, int(geometry["Y"]) + y
        box = (left, top, left + w, top + h)
        time.sleep(0.5)  # the frame is posted; let the window draw it
        before = _screenshot(xvfb, box)
        assert before.std() > 10, "the image area is blank"

        cx, cy = left + w // 2, top + h // 2
        xdo("mousemove", str(cx), str(cy), "mousedown", "1", "sleep", "0.1",
            "mousemove", str(cx + 40), str(cy), "sleep", "0.1", "mousemove", str(cx + 120), str(cy + 30),
            "sleep", "0.1", "mouseup", "1")
        moved = _wait_for(lambda: (s := _status(status_file)) and s["camera"] != first["camera"] and s, 20,
                          "a frame from the moved camera")
        assert moved["camera"]["look_at"] == first["camera"]["look_at"]
        # The status file says the frame was posted; the window draws it when its loop comes round,
        # which on a loaded 2-core host took longer than a fixed half second (a clean clone's run
        # failed so while another suite ran beside it). So look until it shows, for 60 s at most
        # (20 s were not enough in a clean clone's cold-cache run, the other pytest worker compiling
        # every kernel beside it, Mesa's CPU Vulkan driver sharing the two cores; session 31).
        after = _wait_for(lambda: (shot := _screenshot(xvfb, box)) is not None
                          and np.abs(shot - before).mean() > 5 and [shot], 60,
                          "the window to show the moved camera's frame")[0]
        assert np.abs(after - before).mean() > 5, "the image did not change after the drag"

        # The panel's labels, as the window shows them: frame time, fps, Mrays/s per ray kind.
        frame_label, *rate_labels = moved["labels"][:5]
        assert re.match(r"frame \d+: \d+ ms, \d+\.\d fps", frame_label)
        assert float(re.search(r"([\d.]+) fps", frame_label).group(1)) > 0
        for kind, label in zip(("primary", "shadow", "reflection", "refraction"), rate_labels):
            rate = re.match(rf"{kind}: ([\d.]+) Mrays/s \(([\d,]+) rays\)", label)
            assert rate and float(rate.group(1)) > 0 and int(rate.group(2).replace(",", "")) > 0, label
        assert moved["fps"] > 0 and all(v > 0 for v in moved["mrays_per_s"].values())
    finally:
        app.terminate()
        try:
            app.wait(10)
        except subprocess.TimeoutExpired:
            app.kill()
        log.close()


def test_the_commands_own_mistakes_come_before_the_missing_display():
    """``view --device cuda`` is refused as ``show`` refuses it, display or none (the missing
    display was named first, and fixing it only led to the next error)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    run = run_view(env, "--device", "cuda")
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "device 'cuda' is not supported here" in run.stderr
