"""``packetrt view``: an interactive Open3D window showing the live ray-traced image.

    packetrt view [CONFIG] [selectors]          (--size defaults to 256x256 here)

The window holds the Whitted render of the scene (re-rendered on a worker thread whenever
the camera or a setting changes) and a panel: a traversal and a frustum per ray kind, the
packet size and the recursion depth, and labels with the last frame's time, frames per
second and Mrays/s per ray kind.

Controls: drag on the image orbits the camera about its look-at point; the mouse wheel
zooms; the arrow keys orbit, + and - zoom, R resets the camera.

It needs a display (X11 or Wayland): without one it says so and exits with code 2 before
loading the GUI. Under a virtual X server it works as anywhere: ``xvfb-run packetrt view``.
Open3D draws its windows through Vulkan; on a machine without a GPU, Mesa's lavapipe driver
(Debian: libvulkan1, mesa-vulkan-drivers) does it on the CPU.

Hidden options for tests: ``--status-file PATH`` writes, after every frame, the panel's label
texts as shown plus the numbers behind them (JSON); ``--exit-after S`` closes the window
after S seconds.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import json
import math
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from engine.core.errors import PacketrtError
from engine.core.scene import Camera
from engine.core.types import RAY_KINDS

VIEW_SIZE = (256, 256)
DISPLAY_SIDE = 512          # the image is shown at least this big (nearest-neighbour upscale)
PANEL_WIDTH = 400
ORBIT_PER_PIXEL = 0.01      # radians of orbit per pixel of drag
KEY_ORBIT = math.radians(10)
ZOOM_STEP = 1.1
MAX_ELEVATION = math.radians(85)
DEPTH_LIMIT = 10


def display_problem() -> str | None:
    """Why no window can be opened here, or None when a display is available."""
    display = os.environ.get("DISPLAY", "")
    if not display:
        if os.environ.get("WAYLAND_DISPLAY"):
            return None
        return ("packetrt view needs a display (DISPLAY is not set); run it under Xvfb, "
                "e.g. xvfb-run packetrt view")
    name = ctypes.util.find_library("X11")
    if name is None:
        return None  # cannot check; let the GUI try
    try:
        xlib = ctypes.CDLL(name)
        xlib.XOpenDisplay.restype = ctypes.c_void_p
        xlib.XOpenDisplay.argtypes = [ctypes.c_char_p]
        xlib.XCloseDisplay.argtypes = [ctypes.c_void_p]
        handle = xlib.XOpenDisplay(display.encode())
    except (OSError, AttributeError):
        return None
    if not handle:
        return (f"packetrt view cannot open the display {display!r}; start an X server there or "
                f"run it under Xvfb, e.g. xvfb-run packetrt view")
    xlib.XCloseDisplay(handle)
    return None


# -- camera ----------------------------------------------------------------------------------

def orbit(camera: Camera, azimuth: float = 0.0, elevation: float = 0.0, zoom: float = 1.0) -> Camera:
    """A new Camera moved about its look-at point: ``azimuth`` radians about its up axis,
    ``elevation`` radians towards up (kept within +-85 degrees), distance times ``zoom``."""
    eye = np.asarray(camera.eye, np.float64)
    look = np.asarray(camera.look_at, np.float64)
    up = np.asarray(camera.up, np.float64)
    up /= np.linalg.norm(up)
    offset = eye - look
    distance = float(np.linalg.norm(offset)) * zoom
    direction = offset / np.linalg.norm(offset)
    height = float(np.clip(direction @ up, -1.0, 1.0))
    flat = direction - height * up
    if np.linalg.norm(flat) < 1e-9:  # looking straight along up: any horizontal direction
        flat = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 0, 1.0])
    flat /= np.linalg.norm(flat)
    side = np.cross(up, flat)
    flat = math.cos(azimuth) * flat + math.sin(azimuth) * side
    angle = float(np.clip(math.asin(height) + elevation, -MAX_ELEVATION, MAX_ELEVATION))
    direction = math.cos(angle) * flat + math.sin(angle) * up
    return Camera(tuple(float(c) for c in look + distance * direction), camera.look_at, camera.up, camera.fov)


# -- rendering worker ------------------------------------------------------------------------

class FrameSource:
    """Renders frames on a worker thread: the latest requested (config, camera) wins."""

    def __init__(self, scene, config, on_frame):
        self.scene = scene
        self.on_frame = on_frame
        self._lock = threading.Condition()
        self._wanted = (config, scene.camera)
        self._version = 1
        self._done = 0
        self._closing = False
        self._renderer = None
        self._renderer_config = None
        self.thread = threading.Thread(target=self._run, name="packetrt-view-render", daemon=True)

    def start(self):
        self.thread.start()

    def request(self, config=None, camera=None):
        with self._lock:
            old_config, old_camera = self._wanted
            self._wanted = (config or old_config, camera or old_camera)
            self._version += 1
            self._lock.notify()

    @property
    def wanted(self):
        with self._lock:
            return self._wanted

    def close(self):
        with self._lock:
            self._closing = True
            self._lock.notify()

    def _run(self):
        from engine.render.image import to_srgb8
        from engine.render.whitted import WhittedRenderer

        while True:
            with self._lock:
                while self._version == self._done and not self._closing:
                    self._lock.wait()
                if self._closing:
                    return
                version = self._version
                config, camera = self._wanted
            error = None
            try:
                if self._renderer is None or config != self._renderer_config:
                    self._renderer = WhittedRenderer(self.scene, config)
                    self._renderer_config = config
                # The BVH does not depend on the camera: only the scene's camera changes.
                self._renderer.scene = replace(self.scene, camera=camera)
                start = time.perf_counter()
                result = self._renderer.render()
                seconds = time.perf_counter() - start
                frame = to_srgb8(result.image)
            except PacketrtError as exc:
                error, result, seconds, frame = str(exc), None, 0.0, None
            except Exception as exc:  # noqa: BLE001 -- shown in the panel; the window stays usable
                error, result, seconds, frame = f"{type(exc).__name__}: {exc}", None, 0.0, None
            with self._lock:
                self._done = version
            self.on_frame(frame, result, seconds, config, camera, error)


# -- the window ------------------------------------------------------------------------------

class Viewer:
    """The Open3D window: image on the left, settings and numbers on the right."""

    def __init__(self, scene, config, status_file=None, exit_after=None):
        import open3d.visualization.gui as gui

        self.gui = gui
        self.scene = scene
        self.home = scene.camera
        self.status_file = status_file
        self.exit_after = exit_after
        self.frames = 0
        self.fps = 0.0
        self.last_frame_at = None
        self.drag_from = None
        self.started = time.perf_counter()
        self.app = gui.Application.instance
        self.app.initialize()
        w, h = config.render.width, config.render.height
        self.scale = max(1, int(math.ceil(DISPLAY_SIDE / max(w, h))))
        self.shown = (w * self.scale, h * self.scale)
        em = 14
        self.window = self.app.create_window(f"packetrt view - {scene.name}", self.shown[0] + PANEL_WIDTH + 3 * em // 2,
                                             max(self.shown[1], 640) + em)
        self.image = gui.ImageWidget()
        self.image.set_on_mouse(self._on_mouse)
        self.window.set_on_key(self._on_key)
        self.window.set_on_close(self._on_close)
        self.window.add_child(self.image)
        self.panel = self._build_panel(config)
        self.window.add_child(self.panel)
        self.window.set_on_layout(self._on_layout)
        self.window.set_on_tick_event(self._on_tick)
        self.source = FrameSource(scene, config, self._frame_ready)

    # layout and widgets
    def _build_panel(self, config):
        gui = self.gui
        from engine.packet.layout import PACKET_SIZES
        from engine.render.plugins import frustum_names, traversal_names

        em = 14
        panel = gui.Vert(4, gui.Margins(em // 2, em // 2, em // 2, em // 2))
        panel.add_child(gui.Label(f"{self.scene.name}: {self.scene.n_triangles:,} triangles, "
                                  f"{config.render.width}x{config.render.height}"))
        grid = gui.VGrid(3, 4)
        grid.add_child(gui.Label("ray kind"))
        grid.add_child(gui.Label("traversal"))
        grid.add_child(gui.Label("frustum"))
        self.traversal_boxes, self.frustum_boxes = {}, {}
        for kind in RAY_KINDS:
            grid.add_child(gui.Label(kind))
            for names, current, store, what in ((traversal_names(), config.traversal.get(kind), self.traversal_boxes,
                                                 "traversal"),
                                                (frustum_names(), config.frustum.get(kind), self.frustum_boxes,
                                                 "frustum")):
                box = gui.Combobox()
                for name in names:
                    box.add_item(name)
                if current in names:
                    box.selected_index = names.index(current)
                box.set_on_selection_changed(lambda text, index, k=kind, w=what: self._set_plugin(w, k, text))
                store[kind] = box
                grid.add_child(box)
        panel.add_child(grid)
        row = gui.Horiz(4)
        row.add_child(gui.Label("packet"))
        self.packet_box = gui.Combobox()
        for n in PACKET_SIZES:
            self.packet_box.add_item(f"{n}x{n}")
        self.packet_box.selected_index = list(PACKET_SIZES).index(config.render.packet)
        self.packet_box.set_on_selection_changed(lambda text, index: self._set_render(packet=PACKET_SIZES[index]))
        row.add_child(self.packet_box)
        row.add_child(gui.Label("depth"))
        self.depth_slider = gui.Slider(gui.Slider.INT)
        self.depth_slider.set_limits(0, max(DEPTH_LIMIT, config.render.max_depth))
        self.depth_slider.int_value = config.render.max_depth
        self.depth_slider.set_on_value_changed(lambda value: self._set_render(max_depth=int(value)))
        row.add_child(self.depth_slider)
        panel.add_child(row)
        self.frame_label = gui.Label("frame: rendering...")
        panel.add_child(self.frame_label)
        self.rate_labels = {}
        for kind in RAY_KINDS:
            self.rate_labels[kind] = gui.Label(f"{kind}: -")
            panel.add_child(self.rate_labels[kind])
        self.message = gui.Label("")
        panel.add_child(self.message)
        panel.add_child(gui.Label("drag: orbit   wheel: zoom\narrows: orbit   +/-: zoom   R: reset"))
        return panel

    def _on_layout(self, context):
        r = self.window.content_rect
        self.image.frame = self.gui.Rect(r.x, r.y, self.shown[0], self.shown[1])
        self.panel.frame = self.gui.Rect(r.x + self.shown[0], r.y, r.width - self.shown[0], r.height)

    # settings
    def _set_plugin(self, what, kind, name):
        from engine.render.config import PerKind, validate

        config = self.source.wanted[0]
        table = getattr(config, what)
        values = {k: table.get(k) for k in RAY_KINDS}
        values[kind] = name
        self._apply(lambda: validate(replace(config, **{what: PerKind(**values)})))

    def _set_render(self, **changes):
        from engine.render.config import validate

        config = self.source.wanted[0]
        self._apply(lambda: validate(replace(config, render=replace(config.render, **changes))))

    def _apply(self, make_config):
        try:
            config = make_config()
        except PacketrtError as exc:
            self.message.text = f"error: {exc}"
            return
        self.message.text = ""
        self.source.request(config=config)

    # camera
    def _move(self, **how):
        self.source.request(camera=orbit(self.source.wanted[1], **how))

    def _on_mouse(self, event):
        gui = self.gui
        kind = event.type
        if kind == gui.MouseEvent.Type.BUTTON_DOWN:
            self.drag_from = (event.x, event.y)
            return gui.Widget.EventCallbackResult.CONSUMED
        if kind == gui.MouseEvent.Type.DRAG and self.drag_from is not None:
            dx, dy = event.x - self.drag_from[0], event.y - self.drag_from[1]
            self.drag_from = (event.x, event.y)
            self._move(azimuth=-dx * ORBIT_PER_PIXEL, elevation=dy * ORBIT_PER_PIXEL)
            return gui.Widget.EventCallbackResult.CONSUMED
        if kind == gui.MouseEvent.Type.BUTTON_UP:
            self.drag_from = None
            return gui.Widget.EventCallbackResult.CONSUMED
        if kind == gui.MouseEvent.Type.WHEEL:
            # Wheel up (Open3D reports it as negative dy) brings the camera closer.
            self._move(zoom=ZOOM_STEP ** (-1 if event.wheel_dy < 0 else 1))
            return gui.Widget.EventCallbackResult.CONSUMED
        return gui.Widget.EventCallbackResult.IGNORED

    def _on_key(self, event):
        gui = self.gui
        if event.type != gui.KeyEvent.Type.DOWN:
            return gui.Widget.EventCallbackResult.IGNORED
        k = gui.KeyName
        moves = {k.LEFT: {"azimuth": KEY_ORBIT}, k.RIGHT: {"azimuth": -KEY_ORBIT},
                 k.UP: {"elevation": KEY_ORBIT}, k.DOWN: {"elevation": -KEY_ORBIT},
                 k.EQUALS: {"zoom": 1 / ZOOM_STEP}, k.PLUS: {"zoom": 1 / ZOOM_STEP},
                 k.MINUS: {"zoom": ZOOM_STEP}}
        if event.key in moves:
            self._move(**moves[event.key])
            return gui.Widget.EventCallbackResult.CONSUMED
        if event.key == k.R:
            self.source.request(camera=self.home)
            return gui.Widget.EventCallbackResult.CONSUMED
        return gui.Widget.EventCallbackResult.IGNORED

    # frames
    def _frame_ready(self, frame, result, seconds, config, camera, error):
        """Worker thread: hand the frame to the GUI thread."""
        self.app.post_to_main_thread(self.window, lambda: self._show(frame, result, seconds, config, camera, error))

    def _show(self, frame, result, seconds, config, camera, error):
        import open3d as o3d

        if error is not None:
            self.message.text = f"error: {error}"
            self.window.post_redraw()
            return
        if self.scale > 1:
            frame = np.repeat(np.repeat(frame, self.scale, axis=0), self.scale, axis=1)
        self.image.update_image(o3d.geometry.Image(np.ascontiguousarray(frame)))
        now = time.perf_counter()
        self.fps = 1.0 / seconds if seconds > 0 else 0.0
        self.frames += 1
        rates = result.mrays_per_s()
        self.frame_label.text = (f"frame {self.frames}: {seconds * 1000:.0f} ms, {self.fps:.1f} fps\n"
                                 f"{config.render.width}x{config.render.height}, packet {config.render.packet}, "
                                 f"depth {config.render.max_depth}")
        for kind in RAY_KINDS:
            if result.rays[kind]:
                self.rate_labels[kind].text = f"{kind}: {rates[kind]:.2f} Mrays/s ({result.rays[kind]:,} rays)"
            else:
                self.rate_labels[kind].text = f"{kind}: no rays"
        self.last_frame_at = now
        self.window.post_redraw()
        if self.status_file:
            self._write_status(result, seconds, config, camera)

    def _write_status(self, result, seconds, config, camera):
        r = self.image.frame
        status = {
            "frames": self.frames, "seconds": seconds, "fps": self.fps,
            "mrays_per_s": result.mrays_per_s(), "rays": result.rays,
            "camera": {"eye": list(camera.eye), "look_at": list(camera.look_at)},
            "config": config.to_dict(),
            "labels": [self.frame_label.text] + [self.rate_labels[k].text for k in RAY_KINDS] + [self.message.text],
            "image_frame": [r.x, r.y, r.width, r.height],
        }
        target = Path(self.status_file)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(status, indent=1, default=float))
        os.replace(tmp, target)

    def _on_tick(self):
        if self.exit_after is not None and time.perf_counter() - self.started > self.exit_after:
            self.window.close()
        return False

    def _on_close(self):
        self.source.close()
        return True

    def run(self):
        self.source.start()
        self.app.run()


def run_viewer(scene, config, status_file=None, exit_after=None) -> None:
    """Open the window on ``scene`` rendered with ``config`` and run until it is closed;
    PacketrtError when no window can be opened."""
    problem = display_problem()
    if problem:
        raise PacketrtError(problem)
    from engine.debug.show import import_open3d

    import_open3d()
    try:
        viewer = Viewer(scene, config, status_file=status_file, exit_after=exit_after)
    except RuntimeError as exc:
        hint = (" (Open3D draws through Vulkan: on Debian install libvulkan1 and mesa-vulkan-drivers)"
                if "vulkan" in str(exc).lower() else "")
        raise PacketrtError(f"Open3D could not open its window: {exc}{hint}") from None
    viewer.run()
