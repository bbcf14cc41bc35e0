"""BART ``.aff`` scenes (Lext, Assarsson, Möller, *A Benchmark for Animated Ray Tracing*, 2001).

AFF is Eric Haines' NFF with meshes, textures, includes and keyframe animation. This loader
parses a scene and its scene graph; ``scenes.aff_animation`` places it at any instant ``time``
(seconds of the animation) as a static ``Scene``, once per frame along the animation path.

Directives (``#`` and ``%`` start a comment; tokens may wrap across lines)::

    v  from x y z  at x y z  up x y z  angle deg  hither h  resolution w h   camera
    b  r g b                          background colour
    l  x y z [r g b]                  point light (white when no colour)
    am r g b                          ambient light
    fm ar ag ab  dr dg db  sr sg sb  phong transmission ior     material (AFF)
    f  r g b  kd ks phong transmission ior                      material (NFF)
    m  vertices V ...  [normals N ...]  [texturecoords U file.ppm ...]  triangles T
       i0 i1 i2 [n0 n1 n2] [t0 t1 t2] ...                       indexed mesh
    p  n  x y z ...                   polygon, fan-triangulated
    pp n  x y z nx ny nz ...          polygon with vertex normals
    tt  file.ppm  3 x (x y z u v)     textured triangle
    ttp file.ppm  3 x (x y z nx ny nz u v)
    s  x y z r                        sphere, tessellated: 12 R^2 triangles (R = tessellation)
    c  bx by bz br  ax ay az ar       open cone/cylinder, tessellated: 8 R triangles
    xs sx sy sz  ax ay az deg  tx ty tz  { ... }   static transform T R S of a block
    x  name { ... }                   animated transform ``name`` (a ``k`` block) of a block;
                                      without a ``k name`` it is the identity (listed in
                                      ``scene.info["unkeyed_transforms"]``)
    k  name { transl K (t x y z T C B)*K  rot K (t ax ay az deg T C B)*K
              scale K (t sx sy sz T C B)*K }     keyframes, Kochanek-Bartels splines
    tpa K  (t  3 x (x y z nx ny nz))*K           animated triangle (keys linearly blended)
    a  start end frames               animation range
    i  level file.aff                 include, relative to the including file

Materials: ``fm`` maps ambient/diffuse/specular/phong/transmission/ior straight onto
``engine.core.scene.Material``; the specular colour is also the mirror reflectance, as in NFF.
NFF ``f`` has no ambient term (ambient = 0), diffuse = kd * colour, specular = reflectance = ks.
A material stays current until the next ``fm``/``f`` (NFF state, not scoped by blocks).
Textures (binary PPM, read with Pillow) are looked up next to the including file, then in
``TextureFiles`` beside the scene's ``aff`` folder.

Animation: translation and scale keys are Kochanek-Bartels (tension, continuity, bias) Hermite
splines over non-uniformly spaced keys. Rotation keys are absolute axis-angle orientations, made
quaternions; consecutive keys are joined the shorter way (a gun keyed every 90 degrees up to 720
keeps turning one way), and each segment is a Hermite spline in the log space of the rotation
relative to its first key, with KB tangents built from the neighbouring relative rotations (exact
for rotation about one axis). Times before the first or after the last key hold the end key.
Later keys win: a key at or before an earlier key's time replaces it and the keys after it
(the Robots data restart one list this way; repeated first/last keys are common). A keyframe block
named ``camera`` animates the camera: eye = M (0,0,0), looking along M (0,0,-1), up M (0,1,0);
the ``v`` angle stays the vertical field of view.

Parameters: ``tessellation`` (R above, default 3), ``camera`` ("auto": the animated camera when
the scene has ``k camera``, else ``v``; "static": always ``v``), ``lights`` ("all", the default, or
an integer N >= 0: keep the first N point lights in file order, the order the walk meets ``l``
directives, includes followed where they stand; 0 keeps none, and then no point light is made up
either; an N larger than the file's count is a ConfigError naming the count, not a silent "all").
``scene.info["file_lights"]`` is the file's count.

Kept but not applied: ``hither`` and ``resolution`` go to ``scene.info`` (the renderer's config
sets the image size); the detail level of ``i`` is read and ignored. Choices where the format
leaves room: ``tpa`` keys are blended linearly (vertices and normals); spline end keys use the
chord to their neighbour as tangent; NFF cones stay open (no caps), as in NFF.

Malformed input raises ``SceneError`` with ``FILE:LINE: what was expected``.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.errors import ConfigError, SceneError
from engine.core import checked
from engine.core.scene import Camera, Material, SceneBuilder

#: An 'a' line's times must lie within a day, as ``--time`` (engine.render.config.MAX_TIME), and its
#: frame count within ``packetrt animate``'s limit (engine.render.animation.MAX_FRAMES).
ANIMATION_TIME_LIMIT = 86400.0
ANIMATION_FRAME_LIMIT = 100_000
_COMMENT = re.compile(r"[#%][^\n]*")

DIRECTIVES = ("v", "b", "l", "am", "fm", "f", "m", "p", "pp", "tt", "ttp", "s", "c", "xs", "x", "k",
              "tpa", "a", "i", "}")


# --------------------------------------------------------------------------------------------
# Tokens
# --------------------------------------------------------------------------------------------

#: Which of the 256 latin-1 characters ``str.split()`` splits at (its whitespace).
_SPLITS_AT = np.array([chr(code).isspace() for code in range(256)])


def words_and_lines(text: str) -> tuple:
    """(words, line_of, last_line) of latin-1 ``text`` (every character below 256): its words
    as ``text.split()`` gives them, the 1-based line of each word as i32[W] (lines end at
    "\\n"), and the number of lines. A word's line is one more than the newlines before its
    first character, counted in one numpy pass over the bytes; a ``split()`` per line, as
    before, took twice as long over the BART files (0.40 against 0.20 s for all 110)."""
    words = text.split()
    codes = np.frombuffer(text.encode("latin-1"), np.uint8)
    gap = _SPLITS_AT[codes]
    starts = ~gap
    starts[1:] &= gap[:-1]
    line_of = (np.cumsum(codes == ord("\n"), dtype=np.int64)[starts] + 1).astype(np.int32)
    return words, line_of, text.count("\n") + 1


class Tokens:
    """Whitespace-separated words of one file, comments removed, with their line numbers.

    words: list[str] of W words; line_of: i32[W] (1-based line of each word).
    Every read that fails raises SceneError("FILE:LINE: expected ...").
    """

    def __init__(self, path: Path, text: str):
        self.path = path
        self.words, self.line_of, self.last_line = words_and_lines(_COMMENT.sub("", text))
        self.pos = 0

    def at_end(self) -> bool:
        return self.pos >= len(self.words)

    def line(self, pos: Optional[int] = None) -> int:
        """Line of the word at ``pos`` (default: the next word; the last line at the end)."""
        pos = self.pos if pos is None else pos
        return int(self.line_of[pos]) if pos < len(self.words) else self.last_line

    def error(self, message: str, pos: Optional[int] = None) -> SceneError:
        return SceneError(f"{self.path}:{self.line(pos)}: {message}")

    def peek(self) -> Optional[str]:
        return self.words[self.pos] if self.pos < len(self.words) else None

    def word(self, what: str) -> str:
        if self.at_end():
            raise self.error(f"expected {what}, got end of file")
        self.pos += 1
        return self.words[self.pos - 1]

    def keyword(self, expected: str, what: str) -> None:
        pos = self.pos
        got = self.word(f"{expected!r} ({what})")
        if got != expected:
            raise self.error(f"expected {expected!r} ({what}), got {got!r}", pos)

    def _block(self, n: int, what: str, kind: str):
        start = self.pos
        if n < 0:
            raise self.error(f"expected a non-negative count for {what}, got {n}")
        if start + n > len(self.words):
            got = len(self.words) - start
            raise self.error(f"expected {n} {kind}s for {what}, but the file ends after {got}",
                             len(self.words) - 1 if self.words else None)
        self.pos += n
        return start, self.words[start:start + n]

    def numbers(self, n: int, what: str) -> np.ndarray:
        """f64[n] from the next n words."""
        start, words = self._block(n, what, "number")
        try:
            values = np.array(words, dtype=np.float64)
        except ValueError:
            for k, w in enumerate(words):
                try:
                    float(w)
                except ValueError:
                    raise self.error(f"expected a number for {what}, got {w!r}", start + k) from None
            raise  # pragma: no cover - numpy and float() agree on what a number is
        # NaN, infinities and numbers beyond float32's reach are rejected where they stand.
        return checked.array(values, lambda k: f"{self.path}:{self.line(start + k)}: {what}", error=SceneError)

    def integers(self, n: int, what: str) -> np.ndarray:
        """i64[n] from the next n words (decimal integers only, within int64)."""
        start, words = self._block(n, what, "integer")
        try:
            return np.array(words, dtype=np.int64)
        except (ValueError, OverflowError):
            for k, w in enumerate(words):
                try:
                    value = int(w)
                except ValueError:
                    raise self.error(f"expected an integer for {what}, got {w!r}", start + k) from None
                if not -2 ** 63 <= value < 2 ** 63:
                    raise self.error(f"expected an integer for {what}, got {w!r}, which is too large",
                                     start + k) from None
            raise  # pragma: no cover

    def number(self, what: str) -> float:
        return float(self.numbers(1, what)[0])

    def count(self, what: str) -> int:
        """A count (a non-negative integer) from the next word."""
        value = int(self.integers(1, what)[0])
        if value < 0:
            raise self.error(f"expected a non-negative count for {what}, got {value}", self.pos - 1)
        return value

    def next_is_number(self) -> bool:
        word = self.peek()
        if word is None:
            return False
        try:
            float(word)
        except ValueError:
            return False
        return True


# --------------------------------------------------------------------------------------------
# Geometry helpers (also used by the procedural SPD generators)
# --------------------------------------------------------------------------------------------

def sphere_triangles(centre, radius: float, resolution: int):
    """A sphere as a subdivided, inflated cube: (corners f64[12R^2,3,3], normals f64[12R^2,3,3]).

    Each cube face is an R x R grid of quads (two triangles each), projected onto the sphere;
    normals are the exact sphere normals at the corners. Winding is counter-clockwise seen from
    outside.
    """
    r = int(resolution)
    s = np.linspace(-1.0, 1.0, r + 1)
    a, b = np.meshgrid(s, s, indexing="ij")                                   # [R+1, R+1]
    quads = []
    # (axis, sign) for the six faces; (u, v) chosen so that u x v points outwards.
    for axis in range(3):
        for sign in (1.0, -1.0):
            u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
            grid = np.zeros((r + 1, r + 1, 3))
            grid[..., axis] = sign
            grid[..., u_axis] = a
            grid[..., v_axis] = b * sign
            q = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], axis=2)
            quads.append(q.reshape(-1, 4, 3))
    quads = np.concatenate(quads)                                             # [6R^2, 4, 3]
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])          # [12R^2, 3, 3]
    normals = tris / np.linalg.norm(tris, axis=2, keepdims=True)
    return np.asarray(centre, np.float64) + radius * normals, normals


def cone_triangles(base, base_radius: float, apex, apex_radius: float, resolution: int):
    """An open cone or cylinder (NFF ``c``) with 4R sides: (corners f64[8R,3,3], normals f64[8R,3,3]).

    Degenerate axes (base == apex) give zero-area triangles so the count stays 8R.
    """
    sides = 4 * int(resolution)
    base = np.asarray(base, np.float64)
    apex = np.asarray(apex, np.float64)
    axis = apex - base
    height = float(np.linalg.norm(axis))
    w = axis / height if height > 0 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(w, helper)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    angles = np.arange(sides + 1) * (2 * math.pi / sides)
    radial = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v        # [S+1, 3]
    lower = base + base_radius * radial
    upper = apex + apex_radius * radial
    normal = radial * height + w * (base_radius - apex_radius)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    i = np.arange(sides)
    corners = np.concatenate([np.stack([lower[i], lower[i + 1], upper[i + 1]], 1),
                              np.stack([lower[i], upper[i + 1], upper[i]], 1)])
    normals = np.concatenate([np.stack([normal[i], normal[i + 1], normal[i + 1]], 1),
                              np.stack([normal[i], normal[i + 1], normal[i]], 1)])
    return corners, normals


def fan(n: int) -> np.ndarray:
    """i64[n-2, 3]: fan triangulation (0, k, k+1) of an n-gon."""
    k = np.arange(1, n - 1)
    return np.stack([np.zeros_like(k), k, k + 1], axis=1)


# --------------------------------------------------------------------------------------------
# Rotations and Kochanek-Bartels splines
# --------------------------------------------------------------------------------------------

def axis_angle_matrix(axis, degrees: float) -> np.ndarray:
    """f64[3,3] right-handed rotation by ``degrees`` about ``axis`` (any length; zero = identity)."""
    a = np.asarray(axis, np.float64)
    n = np.linalg.norm(a)
    if n == 0 or degrees == 0:
        return np.eye(3)
    a = a / n
    t = math.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def static_transform(scale, axis, degrees, translation) -> np.ndarray:
    """f64[4,4] = Translate * Rotate * Scale, the order of ``xs``."""
    m = np.eye(4)
    m[:3, :3] = axis_angle_matrix(axis, degrees) * np.asarray(scale, np.float64)[None, :]
    m[:3, 3] = translation
    return m


def _cross3(a, b) -> np.ndarray:
    """np.cross of two f64[3], term for term (the same roundings), without its general-case
    set-up, which was a third of BART Robots' keyframe evaluation."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _qmul(p, q):
    """Hamilton product of quaternions (w, x, y, z)."""
    pw, pv = p[0], p[1:]
    qw, qv = q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + _cross3(pv, qv)])


def _qconj(q):
    return np.concatenate([[q[0]], -q[1:]])


def _qexp(v):
    """Unit quaternion exp(v) for a pure vector v (half-angle times axis)."""
    theta = float(np.linalg.norm(v))
    if theta < 1e-12:
        return np.concatenate([[1.0], v])
    return np.concatenate([[math.cos(theta)], math.sin(theta) / theta * v])


def _qlog(q):
    """Pure vector v with exp(v) = +-q, the shorter of the two (|v| <= pi/2)."""
    if q[0] < 0:
        q = -q
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-12:
        return np.zeros(3)
    return math.atan2(s, q[0]) / s * q[1:]


def _qmatrix(q) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _kb_tangents(before, after, h_before, h_after, tcb):
    """Kochanek-Bartels (outgoing, incoming) tangents at a key, in per-segment parameter units.

    before, after: f64[D] differences to the previous / next key (None at an end);
    h_before, h_after: the time spans of the adjacent segments; tcb: (tension, continuity, bias).
    """
    t, c, b = tcb
    if before is None and after is None:
        return None, None
    if before is None:
        return (1 - t) * after, (1 - t) * after
    if after is None:
        return (1 - t) * before, (1 - t) * before
    out = (1 - t) * (1 + c) * (1 + b) / 2 * before + (1 - t) * (1 - c) * (1 - b) / 2 * after
    inc = (1 - t) * (1 - c) * (1 + b) / 2 * before + (1 - t) * (1 + c) * (1 - b) / 2 * after
    span = h_before + h_after
    return out * (2 * h_after / span), inc * (2 * h_before / span)


def _hermite(u: float):
    u2, u3 = u * u, u * u * u
    return 2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2


@dataclass
class Track:
    """Keys of one channel.

    times: f64[K] (strictly increasing after dropping repeats); values: f64[K,D] (D = 3 for
    translation/scale, 4 = axis + degrees for rotation); tcb: f64[K,3].
    """

    kind: str
    times: np.ndarray
    values: np.ndarray
    tcb: np.ndarray

    def __post_init__(self):
        # Later keys win: a key at or before an earlier key's time replaces it and every key
        # after it (Robots' gun_rot1 restarts its list at 42 s this way).
        order: list = []
        for k, t in enumerate(self.times):
            while order and self.times[order[-1]] >= t:
                order.pop()
            order.append(k)
        self.times, self.values, self.tcb = self.times[order], self.values[order], self.tcb[order]
        self._spans = np.diff(self.times)                                    # [K-1]
        # A key's quaternion, the rotation from it to the next key and its tangents depend on
        # the keys only: each is made the first time a time between its keys is asked for and
        # kept, not per frame (BART Robots evaluates some 190 tracks a frame), nor for every key
        # up front (its tracks hold 13,632 keys; a scene at one time needs two a track, and
        # making all of them was 0.9 s of a 1.5 s load).
        keys = len(self.times)
        self._key_tangents: list = [None] * keys
        if self.kind == "rot":
            self._quats: list = [None] * keys
            self._rot_deltas: list = [None] * (keys - 1)
            self._diffs = None
        else:
            self._diffs = np.diff(self.values, axis=0)                       # [K-1, D]

    def _quat(self, k: int) -> np.ndarray:
        """f64[4]: the unit quaternion of rotation key k (axis, degrees)."""
        if self._quats[k] is None:
            self._quats[k] = _qexp(math.radians(self.values[k, 3]) / 2 * _unit(self.values[k, :3]))
        return self._quats[k]

    def _delta(self, k: int) -> np.ndarray:
        """The step from key k to key k + 1: f64[D], or for rotations the f64[3] log of q_k^-1 q_k+1."""
        if self._diffs is not None:
            return self._diffs[k]
        if self._rot_deltas[k] is None:
            self._rot_deltas[k] = _qlog(_qmul(_qconj(self._quat(k)), self._quat(k + 1)))
        return self._rot_deltas[k]

    def _tangents(self, k: int):
        """(outgoing, incoming) tangents at key k (see ``_kb_tangents``), made once."""
        if self._key_tangents[k] is None:
            h, last = self._spans, len(self.times) - 1
            before = self._delta(k - 1) if k > 0 else None
            after = self._delta(k) if k < last else None
            self._key_tangents[k] = _kb_tangents(before, after, h[k - 1] if k > 0 else 0.0,
                                                 h[k] if k < last else 0.0, self.tcb[k])
        return self._key_tangents[k]

    def at(self, time: float) -> np.ndarray:
        """The channel's value at ``time``: f64[3] (translation/scale) or f64[4] quaternion."""
        k_last = len(self.times) - 1
        if k_last == 0 or time <= self.times[0] or time >= self.times[-1]:
            k = 0 if k_last == 0 or time <= self.times[0] else k_last
            return self._quat(k) if self.kind == "rot" else self.values[k]
        k = int(np.searchsorted(self.times, time, side="right")) - 1
        u = (time - self.times[k]) / (self.times[k + 1] - self.times[k])
        out_k, _ = self._tangents(k)
        _, in_next = self._tangents(k + 1)
        h00, h10, h01, h11 = _hermite(u)
        if self.kind == "rot":
            # Hermite in the log space of q_k^-1 q(t): 0 at u = 0, delta at u = 1.
            local = h10 * out_k + h01 * self._delta(k) + h11 * in_next
            return _qmul(self._quat(k), _qexp(local))
        return h00 * self.values[k] + h10 * out_k + h01 * self.values[k + 1] + h11 * in_next


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.zeros(3)


@dataclass
class Keyframes:
    """A named ``k`` block: optional translation, rotation and scale tracks."""

    name: str
    tracks: dict = field(default_factory=dict)   # "transl" | "rot" | "scale" -> Track

    def matrix(self, time: float) -> np.ndarray:
        """f64[4,4] = Translate * Rotate * Scale at ``time``."""
        m = np.eye(4)
        rotation = _qmatrix(self.tracks["rot"].at(time)) if "rot" in self.tracks else np.eye(3)
        scale = self.tracks["scale"].at(time) if "scale" in self.tracks else np.ones(3)
        m[:3, :3] = rotation * scale[None, :]
        if "transl" in self.tracks:
            m[:3, 3] = self.tracks["transl"].at(time)
        return m


# --------------------------------------------------------------------------------------------
# Parsing: one file -> a list of operations, cached per file
# --------------------------------------------------------------------------------------------

@dataclass
class Geometry:
    """Triangles in the coordinates of their block.

    corners: f64[T,3,3]; normals: f64[T,3,3] or None; uvs: f64[T,3,2] or None;
    texture: texture file name or None; kind: the directive that made them.
    """

    kind: str
    corners: np.ndarray
    normals: Optional[np.ndarray] = None
    uvs: Optional[np.ndarray] = None
    texture: Optional[str] = None


@dataclass
class AnimatedTriangle:
    """``tpa``: times f64[K], corners f64[K,3,3], normals f64[K,3,3]."""

    times: np.ndarray
    corners: np.ndarray
    normals: np.ndarray

    def at(self, time: float):
        """(corners f64[3,3], normals f64[3,3]) linearly blended between the bracketing keys."""
        t = self.times
        if time <= t[0] or len(t) == 1:
            return self.corners[0], self.normals[0]
        if time >= t[-1]:
            return self.corners[-1], self.normals[-1]
        k = int(np.searchsorted(t, time, side="right")) - 1
        w = (time - t[k]) / (t[k + 1] - t[k])
        return ((1 - w) * self.corners[k] + w * self.corners[k + 1],
                (1 - w) * self.normals[k] + w * self.normals[k + 1])


@dataclass
class ParsedFile:
    """Operations of one file in order: ("material", Material), ("geometry", Geometry, line),
    ("tpa", AnimatedTriangle, line), ("push", 4x4 matrix | name, line), ("pop",),
    ("include", Path, line), ("light", position, colour), ("view", dict), ("background", rgb),
    ("ambient", rgb), ("animation", (start, end, frames)). Keyframe blocks go to ``keyframes``."""

    path: Path
    ops: list
    keyframes: dict


def _ior(value: float) -> float:
    """NFF's ior 0 means none given (an opaque surface): 1. Anything else is kept as written, so
    that ``check_scene`` refuses a negative one instead of it turning into 1 unsaid."""
    return 1.0 if value == 0 else value


def _material_fm(values: np.ndarray, name: str) -> Material:
    amb, dif, spe = _floats(values[0:3]), _floats(values[3:6]), _floats(values[6:9])
    phong, transmission, ior = float(values[9]), float(values[10]), float(values[11])
    return Material(name=name, ambient=amb, diffuse=dif, specular=spe, shininess=phong,
                    reflectance=spe, transmission=transmission, ior=_ior(ior))


def _material_f(values: np.ndarray, name: str) -> Material:
    colour = values[0:3]
    kd, ks, phong, transmission, ior = (float(x) for x in values[3:8])
    return Material(name=name, ambient=(0.0, 0.0, 0.0), diffuse=_floats(kd * colour),
                    specular=(ks, ks, ks), shininess=phong, reflectance=(ks, ks, ks),
                    transmission=transmission, ior=_ior(ior))


class Parser:
    """Turns one .aff file into a ParsedFile; spheres and cones are tessellated here."""

    def __init__(self, path: Path, tessellation: int):
        self.path = path
        self.tessellation = tessellation
        try:
            text = path.read_bytes().decode("latin-1")
        except OSError as exc:
            raise SceneError(f"{path}: cannot read: {exc.strerror or exc}") from None
        self.tok = Tokens(path, text)
        self.ops: list = []
        self.keyframes: dict = {}
        self.open_blocks: list = []        # line of each open '{'

    def parse(self) -> ParsedFile:
        tok = self.tok
        handlers = {"v": self._view, "b": self._background, "l": self._light, "am": self._ambient,
                    "fm": self._fm, "f": self._f, "m": self._mesh, "p": self._polygon,
                    "pp": self._polygon_patch, "tt": self._textured_triangle,
                    "ttp": self._textured_triangle_patch, "s": self._sphere, "c": self._cone,
                    "xs": self._static_transform, "x": self._animated_transform,
                    "k": self._keyframes, "tpa": self._animated_triangle, "a": self._animation,
                    "i": self._include, "}": self._close}
        while not tok.at_end():
            start = tok.pos
            word = tok.word("a directive")
            handler = handlers.get(word)
            if handler is None:
                raise tok.error(f"unknown directive {word!r}; expected one of "
                                f"{', '.join(DIRECTIVES)}", start)
            handler(tok.line(start))
        if self.open_blocks:
            raise SceneError(f"{self.path}:{self.open_blocks[-1]}: the block opened here is not closed "
                             f"by '}}' before the end of the file")
        return ParsedFile(self.path, self.ops, self.keyframes)

    # -- scene settings ------------------------------------------------------------------
    def _view(self, line):
        tok = self.tok
        view = {}
        sizes = {"from": 3, "at": 3, "up": 3, "angle": 1, "hither": 1}
        while tok.peek() in ("from", "at", "up", "angle", "hither", "resolution"):
            key = tok.word("a view parameter")
            if key == "resolution":
                view[key] = tuple(int(x) for x in tok.integers(2, "'resolution' (width height)"))
            else:
                view[key] = tok.numbers(sizes[key], f"view {key!r}")
        missing = [k for k in ("from", "at", "up", "angle") if k not in view]
        if missing:
            raise SceneError(f"{self.path}:{line}: view 'v' needs from, at, up and angle; "
                             f"missing {', '.join(missing)}")
        self.ops.append(("view", view))

    def _background(self, line):
        self.ops.append(("background", _floats(self.tok.numbers(3, "'b' (background r g b)"))))

    def _ambient(self, line):
        self.ops.append(("ambient", _floats(self.tok.numbers(3, "'am' (ambient light r g b)"))))

    def _light(self, line):
        tok = self.tok
        position = tok.numbers(3, "'l' (light position x y z)")
        colour = _floats(tok.numbers(3, "'l' light colour (r g b)")) if tok.next_is_number() else (1.0, 1.0, 1.0)
        self.ops.append(("light", position, colour))

    def _animation(self, line):
        start, end, frames = self.tok.numbers(3, "'a' (start time, end time, frame count)")
        where = f"{self.path}:{line}: 'a'"
        for value, what in ((start, "start time"), (end, "end time")):
            if not -ANIMATION_TIME_LIMIT <= value <= ANIMATION_TIME_LIMIT:
                raise SceneError(f"{where} {what} must be within +-{ANIMATION_TIME_LIMIT:g} s, got {value:g}")
        if end < start:
            raise SceneError(f"{where} end time {end:g} is before the start time {start:g}")
        if frames != int(frames) or not 1 <= frames <= ANIMATION_FRAME_LIMIT:
            raise SceneError(f"{where} frame count must be a whole number in 1..{ANIMATION_FRAME_LIMIT:,}, "
                             f"got {frames:g}")
        self.ops.append(("animation", (float(start), float(end), int(frames))))

    # -- materials -----------------------------------------------------------------------
    def _fm(self, line):
        values = self.tok.numbers(12, "'fm' (ambient rgb, diffuse rgb, specular rgb, phong, "
                                      "transmission, ior)")
        self.ops.append(("material", _material_fm(values, f"{self.path.stem}:{line}")))

    def _f(self, line):
        values = self.tok.numbers(8, "'f' (r g b kd ks phong transmission ior)")
        self.ops.append(("material", _material_f(values, f"{self.path.stem}:{line}")))

    # -- geometry ------------------------------------------------------------------------
    def _mesh(self, line):
        tok = self.tok
        tok.keyword("vertices", "a mesh 'm' starts with 'vertices V'")
        n_vertices = tok.count("the vertex count")
        vertices = tok.numbers(3 * n_vertices, f"'vertices {n_vertices}'").reshape(-1, 3)
        normals = uvs = texture = None
        while tok.peek() in ("normals", "texturecoords"):
            key = tok.word("'normals' or 'texturecoords'")
            n = tok.count(f"the {key} count")
            if key == "normals":
                normals = tok.numbers(3 * n, f"'normals {n}'").reshape(-1, 3)
            else:
                texture = tok.word("the texture file name after 'texturecoords'")
                uvs = tok.numbers(2 * n, f"'texturecoords {n}'").reshape(-1, 2)
        tok.keyword("triangles", "a mesh ends with 'triangles T'")
        n_tris = tok.count("the triangle count")
        groups = 1 + (normals is not None) + (uvs is not None)
        what = "triangle indices (vertex" + (", normal" if normals is not None else "") + \
               (", texture" if uvs is not None else "") + f" triples) of 'triangles {n_tris}'"
        index = tok.integers(3 * groups * n_tris, what).reshape(n_tris, groups, 3)
        faces = index[:, 0]
        self._check_range(faces, len(vertices), "vertex", line)
        corners = vertices[faces]
        corner_normals = corner_uvs = None
        if normals is not None:
            self._check_range(index[:, 1], len(normals), "normal", line)
            corner_normals = normals[index[:, 1]]
        if uvs is not None:
            self._check_range(index[:, -1], len(uvs), "texture coordinate", line)
            corner_uvs = uvs[index[:, -1]]
        self.ops.append(("geometry", Geometry("m", corners, corner_normals, corner_uvs, texture), line))

    def _check_range(self, index, size, what, line):
        if index.size and (index.min() < 0 or index.max() >= size):
            bad = int(index.max()) if index.max() >= size else int(index.min())
            plural = {"vertex": "vertices"}.get(what, what + "s")
            raise SceneError(f"{self.path}:{line}: mesh refers to {what} {bad}, but it has {size} "
                             f"{plural} (indices start at 0)")

    def _polygon(self, line):
        tok = self.tok
        n = tok.count("the vertex count of 'p'")
        if n < 3:
            raise SceneError(f"{self.path}:{line}: a polygon needs at least 3 vertices, got {n}")
        vertices = tok.numbers(3 * n, f"'p {n}' vertices").reshape(n, 3)
        self.ops.append(("geometry", Geometry("p", vertices[fan(n)]), line))

    def _polygon_patch(self, line):
        tok = self.tok
        n = tok.count("the vertex count of 'pp'")
        if n < 3:
            raise SceneError(f"{self.path}:{line}: a polygon needs at least 3 vertices, got {n}")
        data = tok.numbers(6 * n, f"'pp {n}' vertices and normals").reshape(n, 6)
        f = fan(n)
        self.ops.append(("geometry", Geometry("pp", data[:, :3][f], data[:, 3:][f]), line))

    def _textured_triangle(self, line):
        texture = self.tok.word("the texture file name after 'tt'")
        data = self.tok.numbers(15, "'tt' (three vertices x y z u v)").reshape(1, 3, 5)
        self.ops.append(("geometry", Geometry("tt", data[..., :3], None, data[..., 3:], texture), line))

    def _textured_triangle_patch(self, line):
        texture = self.tok.word("the texture file name after 'ttp'")
        data = self.tok.numbers(24, "'ttp' (three vertices x y z nx ny nz u v)").reshape(1, 3, 8)
        self.ops.append(("geometry", Geometry("ttp", data[..., :3], data[..., 3:6], data[..., 6:], texture),
                         line))

    def _sphere(self, line):
        x, y, z, r = self.tok.numbers(4, "'s' (centre x y z, radius)")
        if r < 0:
            raise SceneError(f"{self.path}:{line}: 's' radius must be >= 0, got {r:g}")
        corners, normals = sphere_triangles((x, y, z), r, self.tessellation)
        self.ops.append(("geometry", Geometry("s", corners, normals), line))

    def _cone(self, line):
        v = self.tok.numbers(8, "'c' (base x y z, base radius, apex x y z, apex radius)")
        if v[3] < 0 or v[7] < 0:
            raise SceneError(f"{self.path}:{line}: 'c' radii must be >= 0, got {v[3]:g} and {v[7]:g}")
        corners, normals = cone_triangles(v[0:3], v[3], v[4:7], v[7], self.tessellation)
        self.ops.append(("geometry", Geometry("c", corners, normals), line))

    def _animated_triangle(self, line):
        tok = self.tok
        n = tok.count("the key count of 'tpa'")
        if n < 1:
            raise SceneError(f"{self.path}:{line}: 'tpa' needs at least one key, got {n}")
        data = tok.numbers(19 * n, f"'tpa {n}' keys (time, then 3 x (x y z nx ny nz))").reshape(n, 19)
        times = data[:, 0]
        if np.any(np.diff(times) <= 0):
            raise SceneError(f"{self.path}:{line}: 'tpa' key times must increase, got {times.tolist()}")
        vertex = data[:, 1:].reshape(n, 3, 6)
        self.ops.append(("tpa", AnimatedTriangle(times, vertex[..., :3].copy(), vertex[..., 3:].copy()), line))

    # -- blocks and animation ------------------------------------------------------------
    def _open(self):
        tok = self.tok
        pos = tok.pos
        word = tok.word("'{' opening the transformed block")
        if word != "{":
            raise tok.error(f"expected '{{' opening the transformed block, got {word!r}", pos)
        self.open_blocks.append(tok.line(pos))

    def _static_transform(self, line):
        v = self.tok.numbers(10, "'xs' (scale x y z, rotation axis x y z and degrees, translation x y z)")
        self._open()
        self.ops.append(("push", static_transform(v[0:3], v[3:6], v[6], v[7:10]), line))

    def _animated_transform(self, line):
        name = self.tok.word("the name of the animated transform after 'x'")
        self._open()
        self.ops.append(("push", name, line))

    def _close(self, line):
        if not self.open_blocks:
            raise SceneError(f"{self.path}:{line}: '}}' closes no block")
        self.open_blocks.pop()
        self.ops.append(("pop",))

    def _keyframes(self, line):
        tok = self.tok
        name = tok.word("the name of the keyframe block after 'k'")
        pos = tok.pos
        if tok.word("'{' opening the keyframes") != "{":
            raise tok.error(f"expected '{{' after 'k {name}'", pos)
        frames = Keyframes(name)
        widths = {"transl": 3, "rot": 4, "scale": 3}
        while True:
            pos = tok.pos
            key = tok.word(f"'transl', 'rot', 'scale' or '}}' in keyframes {name!r}")
            if key == "}":
                break
            if key not in widths:
                raise tok.error(f"expected 'transl', 'rot', 'scale' or '}}' in keyframes {name!r}, "
                                f"got {key!r}", pos)
            n = tok.count(f"the number of {key!r} keys")
            if n < 1:
                raise tok.error(f"{key!r} in keyframes {name!r} needs at least one key", pos)
            width = widths[key]
            data = tok.numbers(n * (width + 4), f"'{key} {n}' keys (time, {width} values, tension, "
                                                f"continuity, bias)").reshape(n, width + 4)
            frames.tracks[key] = Track(key, data[:, 0].copy(), data[:, 1:1 + width].copy(),
                                       data[:, 1 + width:].copy())
        self.keyframes[name] = frames

    def _include(self, line):
        tok = self.tok
        tok.number("the detail level of 'i'")
        name = tok.word("the file name of 'i'")
        self.ops.append(("include", (self.path.parent / name), line))


# --------------------------------------------------------------------------------------------
# Evaluation at one time
# --------------------------------------------------------------------------------------------

class Loader:
    """Walks the parsed files from the root, keeping the NFF state (material, transform stack),
    then places everything at ``time``."""

    def __init__(self, root: Path, time: float, tessellation: int):
        self.root = root
        self.time = float(time)
        self.tessellation = tessellation
        self.parsed: dict = {}
        self.builder = SceneBuilder(root.stem, source=str(root))
        self.textures: dict = {}
        # Each path resolved and each texture found once per load: BART Robots names a texture
        # on each of its 1,660 animated triangles and includes files 836 times, and resolving
        # (an lstat per path component) took 0.5 s of its 1.6 s load.
        self.resolved: dict = {}      # Path -> Path.resolve()
        self.texture_paths: dict = {}  # (texture name, folder of the naming file) -> resolved file
        self.keyframes: dict = {}
        self.settings = {"view": None, "background": (0.0, 0.0, 0.0), "ambient": (1.0, 1.0, 1.0),
                         "animation": None}
        # Transform tree: node 0 is the identity; node k has parent[k] and local[k] (a matrix
        # or the name of an animated transform, with the file and line that named it).
        self.parent = [-1]
        self.local: list = [np.eye(4)]
        self.instances: list = []    # (node, Geometry, material index)
        self.animated_tris: list = []  # (node, AnimatedTriangle, material index)
        self.lights: list = []       # (node, position, colour)
        self.counts = {k: 0 for k in ("m", "p", "pp", "tt", "ttp", "s", "c", "tpa")}
        self.current_material: Optional[Material] = None
        self.default_material = Material(name="aff-default")

    def resolve(self, path: Path) -> Path:
        if path not in self.resolved:
            self.resolved[path] = path.resolve()
        return self.resolved[path]

    def parse(self, path: Path) -> ParsedFile:
        key = self.resolve(path)
        if key not in self.parsed:
            self.parsed[key] = Parser(path, self.tessellation).parse()
        return self.parsed[key]

    def walk(self, path: Path, node: int = 0, stack: tuple = ()) -> None:
        parsed = self.parse(path)
        self.keyframes.update(parsed.keyframes)
        nodes = [node]
        for op in parsed.ops:
            kind = op[0]
            if kind == "geometry":
                geometry = op[1]
                self.counts[geometry.kind] += 1
                index = self._material_index(geometry.texture, path, op[2])
                self.instances.append((nodes[-1], geometry, index))
            elif kind == "material":
                self.current_material = op[1]
            elif kind == "push":
                self.parent.append(nodes[-1])
                self.local.append(op[1] if isinstance(op[1], np.ndarray) else (op[1], path, op[2]))
                nodes.append(len(self.parent) - 1)
            elif kind == "pop":
                nodes.pop()
            elif kind == "include":
                target, line = op[1], op[2]
                if not target.is_file():
                    raise SceneError(f"{path}:{line}: included file {target.name!r} not found "
                                     f"(looked for {target})")
                if self.resolve(target) in stack:
                    raise SceneError(f"{path}:{line}: {target.name!r} includes itself (through "
                                     f"{' -> '.join(p.name for p in stack)})")
                self.walk(target, nodes[-1], stack + (self.resolve(path),))
            elif kind == "tpa":
                self.counts["tpa"] += 1
                self.animated_tris.append((nodes[-1], op[1], self._material_index(None, path, op[2])))
            elif kind == "light":
                self.lights.append((nodes[-1], op[1], op[2]))
            else:                                       # view, background, ambient, animation
                self.settings[kind] = op[1]

    def _material_index(self, texture: Optional[str], path: Path, line: int) -> int:
        material = self.current_material or self.default_material
        texture_path = self._find_texture(texture, path, line) if texture else None
        key = (id(material), texture_path)   # parsed files are cached, so ids are stable
        if texture_path is not None:
            material = Material(**{**material.__dict__, "texture": self._texture(texture_path),
                                   "texture_name": texture_path.name})
        return self.builder.add_material(material, key=key)

    def _find_texture(self, name: str, path: Path, line: int) -> Path:
        found = self.texture_paths.get((name, path.parent))
        if found is not None:
            return found
        candidates = [path.parent / name, path.parent.parent / "TextureFiles" / name,
                      self.root.parent / name, self.root.parent.parent / "TextureFiles" / name]
        for candidate in candidates:
            if candidate.is_file():
                found = self.texture_paths[(name, path.parent)] = candidate.resolve()
                return found
        raise SceneError(f"{path}:{line}: texture {name!r} not found (looked in "
                         f"{', '.join(sorted({str(c.parent) for c in candidates}))})")

    def _texture(self, path: Path) -> np.ndarray:
        if path not in self.textures:
            from PIL import Image
            try:
                with Image.open(path) as image:
                    self.textures[path] = np.asarray(image.convert("RGB"), np.float32) / 255.0
            except (OSError, ValueError, Image.DecompressionBombError) as exc:
                raise SceneError(f"{path}: cannot read texture: {exc}") from None
        return self.textures[path]

    def world_matrices(self, time: Optional[float] = None) -> list:
        """f64[4,4] per transform node at ``time`` (default: the loader's; parents come before
        children).

        An ``x name`` without a ``k name`` block stays the identity (the BART Robots data has five
        such transforms); the names are kept in ``self.unkeyed``.
        """
        world = [np.eye(4)]
        self.unkeyed = set()
        for k in range(1, len(self.parent)):
            local = self.local[k]
            if not isinstance(local, np.ndarray):
                name = local[0]
                if name in self.keyframes:
                    local = self.keyframes[name].matrix(self.time if time is None else time)
                else:
                    self.unkeyed.add(name)
                    local = np.eye(4)
            world.append(world[self.parent[k]] @ local)
        return world

    def animated_nodes(self) -> np.ndarray:
        """bool[nodes]: the node or one of its ancestors is an animated transform."""
        flags = np.zeros(len(self.parent), bool)
        for k in range(1, len(self.parent)):
            flags[k] = flags[self.parent[k]] or not isinstance(self.local[k], np.ndarray)
        return flags


def _transform(matrix: np.ndarray, corners: np.ndarray, normals: Optional[np.ndarray]):
    """Apply f64[4,4] to corners f64[T,3,3] and (inverse-transpose, renormalised) normals."""
    a, b = matrix[:3, :3], matrix[:3, 3]
    placed = corners @ a.T + b
    if normals is None:
        return placed, None
    try:
        inv = np.linalg.inv(a)
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(a)
    n = normals @ inv
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return placed, np.where(length > 0, n / np.where(length > 0, length, 1), 0.0)


def _face_normals(corners: np.ndarray) -> np.ndarray:
    """f64[T,3,3]: each triangle's unit geometric normal, repeated at its corners."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.where(length > 0, length, 1), 0.0)
    return np.repeat(n[:, None, :], 3, axis=1)


def _floats(values) -> tuple:
    return tuple(float(x) for x in values)


def _camera_from(view: Optional[dict], keyframes: dict, time: float, mode: str, source: str = "the scene"):
    """(Camera or None, "animated" | "static" | "auto-framed") at ``time``; a camera keyframe
    whose matrix has no forward or up direction (a scale of 0) is a SceneError naming ``source``."""
    fov = float(view["angle"][0]) if view else 45.0
    if mode == "auto" and "camera" in keyframes:
        m = keyframes["camera"].matrix(time)
        eye = m[:3, 3]
        forward = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
        up = m[:3, :3] @ np.array([0.0, 1.0, 0.0])
        # Checked here: the division below printed numpy's warnings before the NaN camera's error.
        if not (np.linalg.norm(forward) > 0 and np.linalg.norm(up) > 0 and np.isfinite(m).all()):
            raise SceneError(f"{source}: the camera keyframes at time {time:g} give no view direction (a scale "
                             f"of 0 or a non-finite transform); the camera needs a non-zero scale")
        return Camera(_floats(eye), _floats(eye + forward / np.linalg.norm(forward)),
                      _floats(up / np.linalg.norm(up)), fov), "animated"
    if view:
        return Camera(_floats(view["from"]), _floats(view["at"]), _floats(view["up"]), fov), "static"
    return None, "auto-framed"


def check_params(params: dict) -> tuple:
    """(tessellation, camera, lights) from loader parameters, lights None for "all"; bad values
    raise ConfigError. Whether the file has that many lights is checked when it is read."""
    tessellation = params.get("tessellation", 3)
    if isinstance(tessellation, bool) or not isinstance(tessellation, int) or not 1 <= tessellation <= 64:
        raise ConfigError(f"tessellation must be an integer in 1..64, got {tessellation!r}")
    camera = params.get("camera", "auto")
    if camera not in ("auto", "static"):
        raise ConfigError(f"camera must be 'auto' (animated when the scene has one) or 'static', "
                          f"got {camera!r}")
    lights = params.get("lights", "all")
    if lights == "all" and isinstance(lights, str):
        lights = None
    elif isinstance(lights, bool) or not isinstance(lights, int) or lights < 0:
        raise ConfigError(f"scene parameter lights must be \"all\" or an integer >= 0 (keep the first N point "
                          f"lights in file order), got {lights!r}")
    return tessellation, camera, lights
