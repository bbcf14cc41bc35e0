"""Scene model: triangles with materials, point lights, a pinhole camera, a background.

Loaders (``scenes/``) describe a scene through ``SceneBuilder``; the renderer only sees
the finished ``Scene``. Materials follow the NFF/BART ``fm`` model plus explicit mirror
reflectance and transmission (the Whitted model):

    colour = ambient_light * ambient * texel
           + sum over visible lights of light * (diffuse * texel * max(0, n.l)
                                                 + specular * max(0, r.v) ** shininess)
           + reflectance * L(reflected ray) + transmission * L(refracted ray)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from engine.core import checked
from engine.core.checked import COORDINATE_LIMIT
from engine.core.errors import SceneError, SceneTypeError
from engine.core.types import Triangles


@dataclass
class Material:
    """Surface appearance. Colours are linear RGB triples in [0, inf)."""

    name: str = "default"
    ambient: tuple = (0.1, 0.1, 0.1)
    diffuse: tuple = (0.7, 0.7, 0.7)
    specular: tuple = (0.0, 0.0, 0.0)
    shininess: float = 16.0
    reflectance: tuple = (0.0, 0.0, 0.0)  # mirror reflection weight per channel
    transmission: float = 0.0             # refraction weight
    ior: float = 1.0                      # index of refraction inside the surface
    texture: Optional[np.ndarray] = None  # f32[H,W,3] linear RGB, multiplies ambient and diffuse
    texture_name: str = ""


@dataclass
class PointLight:
    position: tuple
    color: tuple = (1.0, 1.0, 1.0)


@dataclass
class Camera:
    """Pinhole camera; ``fov`` is the vertical field of view in degrees."""

    eye: tuple
    look_at: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 45.0

    def basis(self):
        """(eye, forward, right, up): f32[3] each, orthonormal, right-handed image plane."""
        eye = np.asarray(self.eye, np.float64)
        forward = np.asarray(self.look_at, np.float64) - eye
        norm = np.linalg.norm(forward)
        if not norm > 0:
            raise SceneError("camera eye and look_at coincide")
        forward /= norm
        right = np.cross(forward, np.asarray(self.up, np.float64))
        if np.linalg.norm(right) < 1e-12:  # up parallel to view: pick any perpendicular
            right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        return eye, forward, right, up


@dataclass
class Scene:
    """A renderable scene. ``triangles`` indexes ``materials`` through ``triangles.material``."""

    name: str
    triangles: Triangles
    materials: list
    lights: list
    camera: Camera
    background: tuple = (0.0, 0.0, 0.0)
    ambient_light: tuple = (1.0, 1.0, 1.0)
    source: str = "procedural"
    animated: bool = False
    time: float = 0.0
    info: dict = field(default_factory=dict)
    #: Where the scene's coordinate origin lies in its files' coordinates: a scene far from the
    #: origin is re-centred (``SceneBuilder.build``) and everything in it is relative to this.
    origin: tuple = (0.0, 0.0, 0.0)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.v0.shape[0])

    def bounds(self) -> np.ndarray:
        """f32[2,3]: (min, max) over all vertices."""
        t = self.triangles
        # Column by column: numpy's axis-0 reduction of an (N, 3) array is ~20x slower.
        lo = [min(v[:, a].min() for v in (t.v0, t.v1, t.v2)) for a in range(3)]
        hi = [max(v[:, a].max() for v in (t.v0, t.v1, t.v2)) for a in range(3)]
        return np.array([lo, hi], np.float32)


def checked_vertices(vertices, faces: np.ndarray, source: str) -> np.ndarray:
    """f64[V,3] ``vertices`` if every index of ``faces`` (i64[T,3]) names one of them and the
    vertices the faces use are finite and within float32's reach (+-COORDINATE_LIMIT); else a
    SceneError naming ``source``. A vertex no face uses is in no triangle and is not checked
    (as trimesh ignores it; ``used_corners`` keeps it out of the re-centring too)."""
    kind = np.asarray(vertices).dtype.kind
    if kind not in "iuf":  # float64 would drop an imaginary part or parse strings
        raise SceneTypeError(f"{source}: vertices must be real numbers (an integer or float array), "
                             f"got {np.asarray(vertices).dtype}")
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise SceneError(f"{source}: vertices must have shape (V, 3), got {vertices.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        outside = (faces < 0) | (faces >= len(vertices))
        row = int(np.flatnonzero(outside.any(axis=1))[0])
        index = int(faces[row][outside[row]][0])
        raise SceneError(f"{source}: face {row} refers to vertex {index}, but the vertices are "
                         f"0..{len(vertices) - 1}")
    used = np.zeros(len(vertices), np.bool_)
    used[faces.reshape(-1)] = True
    bad = used & ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        i = int(np.nonzero(bad)[0][0])
        raise SceneError(f"{source}: vertex {i} is not finite ({vertices[i].tolist()}); "
                         f"{int(bad.sum())} non-finite vertices in all")
    with np.errstate(invalid="ignore"):  # NaN in an unused vertex
        far = used & (np.abs(vertices).max(axis=1) > COORDINATE_LIMIT) if len(vertices) else used
    if far.any():
        i = int(np.nonzero(far)[0][0])
        raise SceneError(f"{source}: vertex {i} ({vertices[i].tolist()}) is beyond the supported "
                         f"+-{COORDINATE_LIMIT:.0e} (float32 cannot hold it)")
    return vertices


def used_corners(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """f64[3T,3]: the corners of the triangles, the only vertices that place a scene."""
    return vertices[faces.reshape(-1)]


def make_triangles(vertices, faces, material, normals=None, uvs=None, *, source="scene") -> Triangles:
    """Triangles from indexed geometry.

    vertices: f[V,3]; faces: i[T,3]; material: i[T] (or one int); normals: per-vertex f[V,3]
    or per-corner f[T,3,3] or None; uvs: per-vertex f[V,2] or per-corner f[T,3,2] or None.
    Non-finite vertices or out-of-range indices raise SceneError naming ``source``.
    Degenerate (zero-area) triangles are kept: they never report a hit.
    """
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    vertices = checked_vertices(vertices, faces, source)
    v0, v1, v2 = (np.ascontiguousarray(vertices[faces[:, k]].astype(np.float32)) for k in range(3))  # used ones only
    e1 = (v1 - v0).astype(np.float32)
    e2 = (v2 - v0).astype(np.float32)
    ng = np.cross(e1.astype(np.float64), e2.astype(np.float64))
    length = np.linalg.norm(ng, axis=1, keepdims=True)
    ng = np.where(length > 0, ng / np.where(length > 0, length, 1), 0).astype(np.float32)
    n = len(faces)
    mat = np.broadcast_to(np.asarray(material, np.int32), (n,)).copy()

    corner_normals = np.zeros((0, 3, 3), np.float32)
    if normals is not None:
        normals = _per_corner(normals, faces, len(vertices), 3, "normals", source)
        corner_normals = np.nan_to_num(normals, nan=0.0, posinf=0.0, neginf=0.0)
    corner_uvs = np.zeros((0, 3, 2), np.float32)
    if uvs is not None:
        corner_uvs = _per_corner(uvs, faces, len(vertices), 2, "uvs", source)
        if not np.isfinite(corner_uvs).all():  # a NaN uv would index the texture at -2**63
            row = int(np.flatnonzero(~np.isfinite(corner_uvs).reshape(n, -1).all(axis=1))[0])
            raise SceneError(f"{source}: triangle {row}'s texture coordinates {corner_uvs[row].tolist()} are not "
                             f"finite numbers")
    return Triangles(v0, np.ascontiguousarray(e1), np.ascontiguousarray(e2), np.ascontiguousarray(ng),
                     v1, v2, mat, np.ascontiguousarray(corner_normals, np.float32),
                     np.ascontiguousarray(corner_uvs, np.float32))


def _per_corner(values, faces, n_vertices: int, width: int, what: str, source: str) -> np.ndarray:
    """f32[T,3,width] per-corner ``values`` from per-vertex f[V,width] or per-corner f[T,3,width];
    any other shape is a SceneError naming ``what``."""
    try:
        values = np.asarray(values, np.float32)
    except (TypeError, ValueError):
        raise SceneError(f"{source}: {what} must be numbers, got {type(values).__name__}") from None
    if values.shape == (n_vertices, width):
        return values[faces]
    if values.shape == (len(faces), 3, width):
        return values
    raise SceneError(f"{source}: {what} must have shape ({n_vertices}, {width}) per vertex or "
                     f"({len(faces)}, 3, {width}) per corner, got {values.shape}")


def check_triangles(tris, source: str) -> Triangles:
    """``tris`` if it keeps the ``Triangles`` contract (``engine.core.types``): every per-triangle
    array float32 of T rows (T > 0) and the right width, finite corners, normals and uvs of T
    rows or none, materials int32 of T rows; else one SceneError naming ``source`` and the
    field. Triangles a user hands over are read by kernels that trust these shapes."""
    if not isinstance(tris, Triangles):
        raise SceneError(f"{source}: expected packetrt Triangles, got {type(tris).__name__}")
    n = np.shape(tris.v0)[0] if np.ndim(tris.v0) == 2 else -1
    if n <= 0:
        raise SceneError(f"{source}: Triangles.v0 must have shape (T, 3) with T > 0, got {np.shape(tris.v0)}")
    expected = {"v0": (n, 3), "e1": (n, 3), "e2": (n, 3), "ng": (n, 3), "v1": (n, 3), "v2": (n, 3),
                "material": (n,), "normals": ((n, 3, 3), (0, 3, 3)), "uvs": ((n, 3, 2), (0, 3, 2))}
    for name, shapes in expected.items():
        value = getattr(tris, name)
        shapes = shapes if isinstance(shapes[0], tuple) else (shapes,)
        dtype = np.int32 if name == "material" else np.float32
        if not isinstance(value, np.ndarray) or value.dtype != dtype or value.shape not in shapes:
            got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__
            raise SceneError(f"{source}: Triangles.{name} must be {np.dtype(dtype).name} of shape "
                             f"{' or '.join(map(str, shapes))}, got {got}")
        if name != "material" and not np.isfinite(value).all():
            raise SceneError(f"{source}: Triangles.{name} holds non-finite numbers")
    return Triangles(*(np.ascontiguousarray(a) for a in tris))


def concat_triangles(parts: list) -> Triangles:
    """One Triangles from several; optional normals/uvs are filled where a part lacks them
    (normals from the geometric normal, uvs with zeros)."""
    if not parts:
        raise SceneError("scene has no triangles")
    any_normals = any(p.normals.shape[0] for p in parts)
    any_uvs = any(p.uvs.shape[0] for p in parts)
    normals, uvs = [], []
    for p in parts:
        n = p.v0.shape[0]
        if any_normals:
            normals.append(p.normals if p.normals.shape[0] else np.repeat(p.ng[:, None, :], 3, axis=1))
        if any_uvs:
            uvs.append(p.uvs if p.uvs.shape[0] else np.zeros((n, 3, 2), np.float32))
    cat = lambda field_: np.ascontiguousarray(np.concatenate([getattr(p, field_) for p in parts]))
    return Triangles(cat("v0"), cat("e1"), cat("e2"), cat("ng"), cat("v1"), cat("v2"), cat("material"),
                     np.ascontiguousarray(np.concatenate(normals), np.float32) if any_normals
                     else np.zeros((0, 3, 3), np.float32),
                     np.ascontiguousarray(np.concatenate(uvs), np.float32) if any_uvs
                     else np.zeros((0, 3, 2), np.float32))


#: A scene whose centre is farther from the origin than this many times its size is re-centred:
#: float32 coordinates keep about 7 digits, so at 1e3 sizes away a triangle still has ~1e-4 of
#: its size in resolution; nearer scenes (every catalog scene) are left exactly as they are.
RECENTRE_RATIO = 1e3
#: After re-centring, every camera point and light must lie within this distance of the origin
#: on each axis, and the geometry within a tenth of it (so an auto-framed camera, ~3 scene radii
#: away, still fits): float32 rays, frusta and squared distances stay well inside their range.
MAX_CENTRED = 1e12
MAX_GEOMETRY = MAX_CENTRED / 10
#: The least size (the longest side of its box) of a scene with any extent: the watertight test
#: multiplies three coordinates, and below about 1e-12 those products leave float32's normal
#: range (a sphere of radius 1e-13 got hit distances 1e-3 off, at 1e-20 every ray missed, Embree's
#: as ours); 1e-10 keeps two decades from that. RayMeshIntersector rescales and has no limit.
MIN_GEOMETRY = 1e-10


def recentring(lo: np.ndarray, hi: np.ndarray) -> Optional[np.ndarray]:
    """The shift (f64[3], subtracted from every point) that re-centres geometry spanning the box
    lo..hi (f64[3] each) when it lies too far from the origin for float32, else None."""
    centre, size = (lo + hi) / 2, float((hi - lo).max())
    far = np.abs(centre).max() > RECENTRE_RATIO * size or max(np.abs(lo).max(), np.abs(hi).max()) > MAX_GEOMETRY
    return centre if far else None


class SceneBuilder:
    """Accumulates meshes and materials, then builds a Scene.

    >>> b = SceneBuilder("demo")
    >>> m = b.add_material(Material(name="red", diffuse=(1, 0, 0)))
    >>> b.add_mesh(vertices, faces, m)
    >>> scene = b.build(camera=..., lights=[...])

    Meshes are kept in float64 until ``build``, so a scene far from the origin can be re-centred
    before anything becomes float32 (the camera and lights move with it; ``Scene.origin`` says
    by how much).
    """

    def __init__(self, name: str, source: str = "procedural"):
        self.name = name
        self.source = source
        self.materials: list = []
        self._material_index: dict = {}
        self._parts: list = []  # ("mesh", (vertices f64, faces, material, normals, uvs, source)) | ("tris", Triangles)
        self._owned = False     # the only part is triangles build() may keep without a copy

    def add_material(self, material: Material, key=None) -> int:
        """Index of ``material``; a repeated ``key`` returns the first index."""
        if key is not None and key in self._material_index:
            return self._material_index[key]
        self.materials.append(material)
        index = len(self.materials) - 1
        if key is not None:
            self._material_index[key] = index
        return index

    def add_mesh(self, vertices, faces, material: int, normals=None, uvs=None, source=None) -> None:
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if len(faces) == 0:
            return
        source = source or self.source
        vertices = checked_vertices(vertices, faces, source)
        self._parts.append(("mesh", (vertices, faces, material, normals, uvs, source)))

    def add_triangles(self, tris: Triangles, owned: bool = False) -> None:
        """Finished float32 triangles (kept where they are: a scene with any is never re-centred).
        ``build`` copies them, unless they are the scene's only part and ``owned`` (the caller
        made these arrays for this scene and keeps no other use of them: an animation's frame)."""
        self._parts.append(("tris", tris))
        self._owned = owned and len(self._parts) == 1

    @property
    def n_triangles(self) -> int:
        return sum(len(p[1]) if kind == "mesh" else p.v0.shape[0] for kind, p in self._parts)

    def _offset(self) -> Optional[np.ndarray]:
        """The re-centring shift (f64[3]) of the meshes, or None to leave them where they are."""
        if any(kind == "tris" for kind, _ in self._parts):
            return None
        # The corners the faces use: a stray vertex 2e11 away moved the scene there, and every
        # hit of RayTracer((vertices, faces)) on it went wrong.
        corners = [used_corners(p[0], p[1]) for _, p in self._parts]
        lo = np.min([c.min(axis=0) for c in corners], axis=0)
        hi = np.max([c.max(axis=0) for c in corners], axis=0)
        return recentring(lo, hi)

    def build(self, *, camera: Optional[Camera] = None, lights=None, background=(0.0, 0.0, 0.0),
              ambient_light=(1.0, 1.0, 1.0), materials_checked: bool = False, **extra) -> Scene:
        """The Scene; a missing camera is framed automatically, missing lights get one. Every
        number is checked (``check_scene``; the materials too unless ``materials_checked``: an
        animation's frames share the objects its first frame checked); a scene far from the
        origin is re-centred."""
        if not self._parts:
            raise SceneError(f"{self.source}: the scene has no triangles")
        if not self.materials:
            self.add_material(Material())
        for kind, part in self._parts:
            used = np.asarray(part[2] if kind == "mesh" else part.material)
            if used.size and (used.min() < 0 or used.max() >= len(self.materials)):
                bad = int(used.min() if used.min() < 0 else used.max())
                raise SceneError(f"{part[5] if kind == 'mesh' else self.source}: material index {bad} does not exist "
                                 f"(the scene has {len(self.materials)} material(s): 0..{len(self.materials) - 1})")
        offset = self._offset()
        shift = (lambda p: p) if offset is None else (lambda p: tuple(np.asarray(p, np.float64) - offset))
        parts = [p if kind == "tris" else
                 make_triangles(p[0] if offset is None else p[0] - offset, *p[1:5], source=p[5])
                 for kind, p in self._parts]
        tris = parts[0] if self._owned and len(parts) == 1 else concat_triangles(parts)
        if camera is not None:
            checked_camera(camera, self.source)
            camera = replace(camera, eye=shift(camera.eye), look_at=shift(camera.look_at))
        lights = [replace(checked_light(light, self.source), position=shift(light.position))
                  for light in (lights or [])]
        scene = Scene(self.name, tris, list(self.materials), lights,
                      camera or Camera((0, 0, 1), (0, 0, 0)), tuple(background), tuple(ambient_light),
                      source=self.source, **extra)
        if offset is not None:
            scene.origin = tuple(float(x) for x in offset)
        if camera is None:
            scene.camera = auto_camera(scene.bounds(), side=open_side(tris))
        if not scene.lights:
            scene.lights = [default_light(scene.bounds(), scene.camera)]
        return check_scene(scene, materials=not materials_checked)


def checked_camera(camera: Camera, source: str) -> Camera:
    """``camera`` if its points are finite numbers within float32's reach, its eye and look_at
    differ and its field of view is in (0, 180) degrees; else a SceneError naming ``source``."""
    for name in ("eye", "look_at", "up"):
        checked.vector(getattr(camera, name), f"{source}: camera {name}", error=SceneError)
    checked.to_float(camera.fov, f"{source}: camera fov (degrees)", 0.001, 179.9, error=SceneError)
    if np.array_equal(np.asarray(camera.eye, np.float64), np.asarray(camera.look_at, np.float64)):
        raise SceneError(f"{source}: camera eye and look_at coincide ({list(camera.eye)}): the camera looks nowhere")
    return camera


def checked_light(light: PointLight, source: str) -> PointLight:
    """``light`` if its position and colour are finite (colour within 0..1e6)."""
    checked.vector(light.position, f"{source}: light position", error=SceneError)
    checked.vector(light.color, f"{source}: light colour", lo=0.0, hi=MAX_COLOUR, error=SceneError)
    return light


#: Colours, reflectances and light intensities: finite and within [0, MAX_COLOUR].
MAX_COLOUR = 1e6


def check_scene(scene: Scene, materials: bool = True) -> Scene:
    """``scene`` if every number in it makes sense -- materials (colours >= 0 and finite,
    shininess, transmission in [0, 1], ior > 0; skipped with ``materials=False``), lights,
    camera, background -- and its geometry, camera and lights lie within +-MAX_CENTRED of its
    (re-centred) origin; else one SceneError naming the scene's source and what is allowed."""
    where = scene.source
    for m in scene.materials if materials else ():
        named = f"{where}: material {m.name!r}"
        for key in ("ambient", "diffuse", "specular", "reflectance"):
            checked.vector(getattr(m, key), f"{named} {key}", lo=0.0, hi=MAX_COLOUR, error=SceneError)
        checked.to_float(m.shininess, f"{named} shininess", 0.0, MAX_COLOUR, error=SceneError)
        checked.to_float(m.transmission, f"{named} transmission", 0.0, 1.0, error=SceneError)
        checked.to_float(m.ior, f"{named} ior", 1e-3, 1e3, error=SceneError)
    # The geometry first: an auto-placed camera or light of a scene too large or too small
    # fails because of it, and the message should name the cause.
    bounds = np.asarray(scene.bounds(), np.float64)  # column scans of every corner: once
    reach = float(np.abs(bounds).max())
    if reach > MAX_GEOMETRY:
        raise SceneError(f"{where}: the geometry reaches {reach:.3g} from the scene's centre; packetrt supports "
                         f"geometry within +-{MAX_GEOMETRY:.0e} of it and cameras and lights within "
                         f"+-{MAX_CENTRED:.0e} (float32 rays; a scene merely far from the origin is re-centred)")
    size = float((bounds[1] - bounds[0]).max())
    if 0.0 < size < MIN_GEOMETRY:
        raise SceneError(f"{where}: the geometry is {size:.3g} across; packetrt's float32 kernels need a scene at "
                         f"least {MIN_GEOMETRY:.0e} across (scale it up, or query it through RayMeshIntersector, "
                         f"which rescales)")
    for light in scene.lights:
        checked_light(light, where)
    checked_camera(scene.camera, where)
    checked.vector(scene.background, f"{where}: background", lo=0.0, hi=MAX_COLOUR, error=SceneError)
    checked.vector(scene.ambient_light, f"{where}: ambient light", lo=0.0, hi=MAX_COLOUR, error=SceneError)
    points = {"camera eye": scene.camera.eye, "camera look_at": scene.camera.look_at,
              **{f"light {k + 1}": light.position for k, light in enumerate(scene.lights)}}
    for what, point in points.items():
        reach = float(np.abs(np.asarray(point, np.float64)).max())
        if reach > MAX_CENTRED:
            raise SceneError(f"{where}: the {what} lies {reach:.3g} from the scene's centre; packetrt supports "
                             f"cameras and lights within +-{MAX_CENTRED:.0e} of it and geometry within "
                             f"+-{MAX_GEOMETRY:.0e} (float32 rays; a scene merely far from the origin is re-centred)")
    return scene


#: How much of a scene's surface area must face one horizontal side, net, before the automatic
#: camera looks from that side instead of +z (a closed mesh faces every side equally: 0).
OPEN_SIDE_FRACTION = 0.1


def open_side(triangles) -> np.ndarray:
    """The horizontal axis (f64[3]: +-x or +-z) that the surfaces of ``triangles`` face, net,
    when their area vectors sum to at least OPEN_SIDE_FRACTION of their area along it; else +z.

    A room open on one side (the Cornell box: five walls facing in) faces its opening; seen
    from +z the camera looked at the outside of its back wall, which the light inside never
    reaches: a black image. Closed meshes and floors (whose net faces up) keep +z."""
    a = np.cross(np.asarray(triangles.e1, np.float64), np.asarray(triangles.e2, np.float64))
    total = float(np.linalg.norm(a, axis=1).sum())
    net = a.sum(axis=0)
    axes = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    best = axes[int(np.argmax(axes @ net))]
    return best if total > 0 and float(best @ net) >= OPEN_SIDE_FRACTION * total else axes[0]


def auto_camera(bounds: np.ndarray, fov: float = 40.0, side=(0.0, 0.0, 1.0)) -> Camera:
    """A camera looking at the box centre from the horizontal ``side`` (slightly above), framing
    the box."""
    lo, hi = np.asarray(bounds, np.float64)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    distance = radius / math.tan(math.radians(fov) / 2) * 1.1
    direction = np.asarray(side, np.float64) + np.array([0.0, 0.25, 0.0])
    direction /= np.linalg.norm(direction)
    return Camera(tuple(centre + direction * distance), tuple(centre), (0.0, 1.0, 0.0), fov)


def default_light(bounds: np.ndarray, camera: Camera) -> PointLight:
    """One white light above and to the side of the camera."""
    lo, hi = np.asarray(bounds, np.float64)
    size = float(np.linalg.norm(hi - lo))
    eye, forward, right, up = camera.basis()
    return PointLight(tuple(eye + (right + up * 1.5) * size * 0.5), (1.0, 1.0, 1.0))


def override_materials(scene: Scene, mode: str) -> Scene:
    """The first paper's Section 5 overrides: make every material reflective or refractive.

    "reflective": mirror reflectance 0.5 on top of the existing shading.
    "refractive": transmission 0.8 with index of refraction 1.5.
    """
    if mode == "none":
        return scene
    if mode == "reflective":
        mats = [replace(m, reflectance=(0.5, 0.5, 0.5)) for m in scene.materials]
    elif mode == "refractive":
        mats = [replace(m, transmission=0.8, ior=1.5, reflectance=(0.0, 0.0, 0.0)) for m in scene.materials]
    else:
        from engine.core.errors import ConfigError
        raise ConfigError(f"materials.override must be one of 'none', 'reflective', 'refractive'; got {mode!r}")
    return replace(scene, materials=mats)
