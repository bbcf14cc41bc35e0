"""Mesh files (OBJ + MTL, PLY, STL, OFF) through trimesh, as scenes.

A mesh file carries no camera or light, so the scene gets an auto-framed camera and a
default point light; a material named like an emitter (MTL ``Ka`` > 1, as in the Cornell
box's "light") instead places the point light just below that emitter's centre.

MTL mapping (read by this module, since trimesh keeps only part of MTL):

=========  ==============================================================
``Ka``     ambient colour
``Kd``     diffuse colour (``map_Kd`` texture multiplies it)
``Ks``     specular colour; also the mirror reflectance when ``illum 3``
``Ns``     Phong exponent
``Ni``     index of refraction
``d``      dissolve: transmission = 1 - d (``Tr`` = transmission directly)
``illum``  3 = mirror (reflectance = Ks, or 0.8 if Ks is black);
           4, 6, 7 = refractive (transmission = max(1 - d, 0.9), reflectance 0.1)
=========  ==============================================================
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from engine.core import checked
from engine.core.errors import SceneError
from engine.core.scene import MAX_COLOUR, Material, PointLight, SceneBuilder

from .catalog import scene_loader

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb", ".gltf"}


#: Each MTL number's allowed range (colours, exponent, index of refraction, dissolve, model).
MTL_RANGES = {"Ka": (0.0, MAX_COLOUR), "Kd": (0.0, MAX_COLOUR), "Ks": (0.0, MAX_COLOUR), "Ns": (0.0, MAX_COLOUR),
              "Ni": (0.0, 1000.0), "d": (0.0, 1.0), "Tr": (0.0, 1.0)}
ILLUM_MODELS = (0, 10)
#: MTL keys whose values are a colour: "Kd r g b", or "Kd v" for grey.
COLOUR_KEYS = ("Ka", "Kd", "Ks")


def parse_mtl(path: Path, warnings: list) -> dict:
    """{material name: Material} from an MTL file; a bad number names file, line and range.
    A texture that does not exist is a line added to ``warnings`` (the material is untextured)."""
    materials: dict = {}
    current = None
    props: dict = {}

    def finish():
        if current is not None:
            materials[current] = material_from_mtl(current, props)

    for number, raw in enumerate(path.read_text(encoding="utf-8-sig", errors="replace").splitlines(), 1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        key, args = words[0], words[1:]
        where = f"{path}:{number}: {key!r}"
        if key == "newmtl":
            finish()
            current, props = (args[0] if args else f"material{len(materials)}"), {}
            continue
        if key in MTL_RANGES or key == "illum":
            if not args:
                raise SceneError(f"{path}:{number}: {key!r} needs a value")
            if key == "illum":
                props[key] = [checked.parse_int(args[0], where, *ILLUM_MODELS, error=SceneError)]
            elif key in COLOUR_KEYS and len(args) == 2:  # was padded to (a, b, a): a made-up colour
                raise SceneError(f"{path}:{number}: {key!r} takes one value (grey) or three (r g b), got "
                                 f"{' '.join(args)!r}")
            else:
                props[key] = [checked.parse_float(a, where, *MTL_RANGES[key], error=SceneError) for a in args[:3]]
        elif key == "map_Kd" and args:
            texture = path.parent / args[-1]
            if texture.is_file():
                props["map_Kd"] = (texture, f"{path}:{number}")
            else:
                warnings.append(f"{path}:{number}: texture {args[-1]!r} not found (looked for {texture}); "
                                f"the material is drawn untextured")
    finish()
    return materials


def read_texture(path: Path, where: str) -> np.ndarray:
    """f32[H,W,3] linear RGB of an image file; a file Pillow cannot read is a SceneError
    naming the file and the MTL line that named it."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"), np.float32) / 255.0
    except Exception as exc:  # Pillow raises many types (OSError, SyntaxError, DecompressionBombError ...)
        raise SceneError(f"{where}: cannot read texture {str(path)!r}: {exc}") from None


def material_from_mtl(name: str, p: dict) -> Material:
    rgb = lambda key, default: tuple((p[key] * 3)[:3]) if key in p else default
    illum = int(p.get("illum", [2])[0])
    ks = rgb("Ks", (0.0, 0.0, 0.0))
    transmission = 1.0 - p["d"][0] if "d" in p else (p["Tr"][0] if "Tr" in p else 0.0)
    reflectance = (0.0, 0.0, 0.0)
    if illum == 3:
        reflectance = ks if max(ks) > 0 else (0.8, 0.8, 0.8)
    if illum in (4, 6, 7):
        transmission = max(transmission, 0.9)
        reflectance = (0.1, 0.1, 0.1)
    texture = read_texture(*p["map_Kd"]) if "map_Kd" in p else None
    ior = float(p.get("Ni", [1.5 if transmission > 0 else 1.0])[0])
    return Material(name=name, ambient=rgb("Ka", (0.1, 0.1, 0.1)), diffuse=rgb("Kd", (0.7, 0.7, 0.7)),
                    specular=ks, shininess=float(p.get("Ns", [16.0])[0]), reflectance=reflectance,
                    transmission=float(min(max(transmission, 0.0), 1.0)),
                    ior=ior if ior > 0 else 1.0,  # "Ni 0" in exported files means "not set"
                    texture=texture, texture_name=str(p["map_Kd"][0]) if "map_Kd" in p else "")


#: OBJ lines of numbers: the word, what it is called in a message, and how many it needs.
OBJ_NUMBERS = {"v": ("vertex", 3), "vn": ("normal", 3), "vt": ("texture coordinate", 1)}


def checked_obj_text(path: Path) -> str:
    """The OBJ's text with every relative (negative) face index made absolute; a malformed
    line is rejected with file:line before trimesh sees it.

    trimesh resolves a negative index against the wrong vertex list once a file has several
    objects (the Cornell box's ``f -4 -3 -2 -1`` put walls onto the blocks), so it only ever
    sees absolute indices.
    """
    counts = {"v": 0, "vt": 0, "vn": 0}
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    for number, raw in enumerate(lines, 1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        key = words[0]
        if key in OBJ_NUMBERS:
            what, least = OBJ_NUMBERS[key]
            if len(words) < 1 + least:
                raise SceneError(f"{path}:{number}: {what} {raw.strip()!r} has fewer than {least} coordinates")
            # Every coordinate, used by a face or not (a NaN normal was read without a word).
            for w in words[1:4]:
                try:
                    float(w)
                except ValueError:
                    raise SceneError(f"{path}:{number}: bad {what} {raw.strip()!r}: expected {least} numbers") from None
                checked.parse_float(w, f"{path}:{number}: {what} {raw.strip()!r}", error=SceneError)
        if key in counts:
            counts[key] += 1
            lines[number - 1] = " ".join(words)  # trimesh reads "v\t0\t0\t0" as no vertex at all
        elif key == "f":
            if len(words) < 4:
                raise SceneError(f"{path}:{number}: face {raw.strip()!r} has fewer than 3 vertices")
            corners = [_absolute_corner(path, number, raw, word, counts) for word in words[1:]]
            lines[number - 1] = "\n".join("f " + " ".join(c) for c in face_triangles(corners))
    return "\n".join(lines) + "\n"


def face_triangles(corners: list) -> list:
    """The corners of one OBJ face as trimesh gets them: a triangle, a polygon without texture
    coordinates as it is (trimesh splits it), and a polygon with them split here into a fan,
    (a, b, c), (c, d, a) for a quad as trimesh splits one: trimesh, keeping the file's vertex
    order, drops the texture coordinates of every mesh that has a polygon with them, and the
    quads of a textured export were drawn untextured."""
    if len(corners) == 3 or not any(c.count("/") and c.split("/")[1] for c in corners):
        return [corners]
    if len(corners) == 4:
        a, b, c, d = corners
        return [[a, b, c], [c, d, a]]
    return [[corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1)]


def bom_free_resolver(path: Path):
    """trimesh's resolver of the files an OBJ names (its MTL), with a UTF-8 byte order mark cut
    off: trimesh read "\ufeffnewmtl red" as no material, and the mesh went grey unsaid."""
    import trimesh

    class BomFree(trimesh.resolvers.FilePathResolver):
        def get(self, name):
            data = super().get(name)
            return data[3:] if isinstance(data, bytes) and data.startswith(b"\xef\xbb\xbf") else data

    return BomFree(str(path))


def unknown_materials(path: Path, obj_text: str, mtl: dict) -> list:
    """Warning lines for the ``usemtl`` names of an OBJ that its material libraries do not
    define (drawn default grey; was silent, even under --strict). An OBJ that loads no library
    is left alone: there every material is the default by design."""
    if not mtl:
        return []
    named = dict.fromkeys(line.split(None, 1)[1].strip() for line in obj_text.splitlines()
                          if line.startswith("usemtl") and len(line.split(None, 1)) == 2)
    return [f"{path}: usemtl {name!r} names no material of its material libraries; it is drawn in the default grey"
            for name in named if name not in mtl]


def check_off(path: Path) -> None:
    """An OFF file's header, checked before trimesh reads it (trimesh's own errors on a bad one
    are numpy's: "cannot reshape array of size 3 into shape (99999999999,3)"): the word OFF, then
    the vertex, face and edge counts, and at least three numbers a vertex after them."""
    words = [w for line in path.read_text(encoding="utf-8-sig", errors="replace").splitlines() for w in line.split("#", 1)[0].split()]
    if not words or not words[0].upper().endswith("OFF"):
        raise SceneError(f"{path}: not an OFF file: expected the word OFF first, got "
                         f"{words[0][:20]!r}" if words else f"{path}: not an OFF file: it is empty")
    counts = words[1:4]
    if len(counts) < 3 or not all(w.isdigit() for w in counts):
        raise SceneError(f"{path}: expected three counts (vertices faces edges) after OFF, got {' '.join(counts)!r}")
    vertices = int(counts[0])
    if len(words) - 4 < 3 * vertices:
        raise SceneError(f"{path}: the header declares {vertices:,} vertices, but the file holds "
                         f"{len(words) - 4:,} numbers after it")
    # The faces, line by line after the vertices' lines: each "n i1 .. in" whole (a file cut
    # short in its faces loaded what was left, without a word).
    rows = [line.split("#", 1)[0].split() for line in path.read_text(encoding="utf-8-sig", errors="replace").splitlines()]
    rows = [r for r in rows if r]
    header = 1 if len(rows[0]) >= 4 else 2      # "OFF V F E" on one line, or OFF then the counts
    faces = rows[header + vertices:]
    declared = int(counts[1])
    whole = sum(1 for r in faces[:declared] if r[0].isdigit() and len(r) >= 1 + int(r[0]))
    if whole < declared:
        raise SceneError(f"{path}: the header declares {declared:,} faces, but the file holds {whole:,} whole face "
                         f"lines after the vertices: is it cut short?")


def check_stl(path: Path) -> None:
    """An STL file is whole: a binary one holds the 50 bytes of every triangle its header counts,
    an ASCII one closes every facet it opens (trimesh reads either cut short as a file without
    triangles: "the file holds no triangles", which hid the cause)."""
    data = path.read_bytes()
    head = data[:512].lstrip()
    if head[:5].lower() == b"solid" and (b"facet" in head or b"endsolid" in head or len(data) < 84):
        text = data.decode("utf-8", errors="replace")
        opened, closed = text.count("facet normal"), text.count("endfacet")
        if opened != closed or "endsolid" not in text[-4096:]:
            raise SceneError(f"{path}: the ASCII STL opens {opened:,} facets and closes {closed:,}"
                             + ("" if "endsolid" in text[-4096:] else ", and has no 'endsolid' line")
                             + ": is it cut short?")
        return
    if len(data) < 84:
        raise SceneError(f"{path}: a binary STL starts with an 84-byte header; the file has {len(data):,} bytes")
    declared = int.from_bytes(data[80:84], "little")
    wanted = 84 + 50 * declared
    if len(data) < wanted:
        raise SceneError(f"{path}: the binary STL header counts {declared:,} triangles ({wanted:,} bytes), but the "
                         f"file has {len(data):,} bytes: is it cut short?")


def check_ascii_ply(path: Path) -> None:
    """An ASCII PLY holds a line for every element its header declares (trimesh reads a file cut
    short as one without faces: "the file holds no triangles"); other PLY files pass unread."""
    with open(path, "rb") as file:
        head = file.read(4096)
    if b"format ascii" not in head.split(b"end_header", 1)[0]:
        return
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    try:
        end = next(i for i, line in enumerate(lines) if line.strip() == "end_header")
    except StopIteration:
        raise SceneError(f"{path}: the PLY header has no end_header line") from None
    declared = []
    for line in lines[:end]:
        words = line.split()
        if len(words) == 3 and words[0] == "element":
            if not words[2].isdigit():
                raise SceneError(f"{path}: element {words[1]!r} has count {words[2]!r}; expected a whole number")
            declared.append((words[1], int(words[2])))
    rows = [line.split() for line in lines[end + 1:] if line.strip()]
    wanted = sum(count for _, count in declared)
    if len(rows) < wanted:
        counts = ", ".join(f"{name} {count:,}" for name, count in declared)
        raise SceneError(f"{path}: the header declares element {counts} ({wanted:,} lines), but the file holds "
                         f"{len(rows):,} lines after it: is it cut short?")
    # The face lines whole: "n i1 .. in" (a last line cut to "3 435 423" lost its face unsaid).
    start = 0
    for name, count in declared:
        if name == "face":
            for k, words in enumerate(rows[start:start + count]):
                if not words[0].isdigit() or len(words) < 1 + int(words[0]):
                    raise SceneError(f"{path}: face {k:,} ({' '.join(words)!r}) lists fewer corners than it "
                                     f"declares: is the file cut short?")
        start += count


def _absolute_corner(path: Path, number: int, raw: str, word: str, counts: dict) -> str:
    """One face corner ``v[/vt][/vn]`` with negative indices counted back from the lists so far."""
    parts = word.split("/")
    for slot, (part, kind) in enumerate(zip(parts, ("v", "vt", "vn"))):
        if part == "" and slot > 0:
            continue
        try:
            index = int(part)
        except ValueError:
            raise SceneError(f"{path}:{number}: bad face index {word!r} in {raw.strip()!r}") from None
        have = counts[kind]
        if index == 0 or index > have or index < -have:
            names = {"v": "vertices", "vt": "texture coordinates", "vn": "normals"}
            raise SceneError(f"{path}:{number}: face index {index} out of range (1..{have} {names[kind]} so far)")
        parts[slot] = str(index + have + 1 if index < 0 else index)
    return "/".join(parts)


def read_mtllibs(path: Path, warnings: list) -> dict:
    """{material name: Material} from every ``mtllib`` of OBJ ``path``; an MTL file that does
    not exist is a line added to ``warnings``, an ``mtllib`` without a file name a SceneError."""
    mtl = {}
    for number, line in enumerate(path.read_text(encoding="utf-8-sig", errors="replace").splitlines(), 1):
        words = line.split("#", 1)[0].split(None, 1)
        if not words or words[0] != "mtllib":
            continue
        if len(words) < 2:
            raise SceneError(f"{path}:{number}: 'mtllib' needs a file name")
        lib = path.parent / words[1].strip()
        if lib.is_file():
            mtl.update(parse_mtl(lib, warnings))
        else:
            warnings.append(f"{path}:{number}: material library {words[1].strip()!r} not found (looked for "
                            f"{lib}); its materials are drawn in the default grey")
    return mtl


def colour_of(rgba, default=(1.0, 1.0, 1.0)) -> tuple:
    """Linear RGB in [0, 1] of a trimesh colour (uint8 0..255 or float 0..1 RGB[A]); None: default."""
    if rgba is None:
        return default
    rgba = np.asarray(rgba, np.float64).ravel()
    if rgba.size < 3 or not np.all(np.isfinite(rgba[:3])):
        return default
    scale = 255.0 if np.asarray(rgba).dtype.kind in "ui" or rgba[:3].max() > 1.0 else 1.0
    return tuple(float(min(max(c / scale, 0.0), 1.0)) for c in rgba[:3])


def texture_of(image, where: str):
    """f32[H,W,3] of a PIL image a trimesh material holds (None: no texture)."""
    if image is None:
        return None
    try:
        return np.asarray(image.convert("RGB"), np.float32) / 255.0
    except Exception as exc:  # a broken embedded image: Pillow raises many types
        raise SceneError(f"{where}: cannot read its texture: {exc}") from None


def material_from_visual(visual, name: str, where: str) -> Material:
    """The Material of a mesh read from a glTF, PLY, STL or OFF file, from trimesh's visuals.

    glTF (``PBRMaterial``): base colour -> diffuse, base colour texture -> texture; a metallic
    (>= 0.5), smooth (roughness <= 0.25) surface is a mirror of its base colour; a blended
    alpha below 1 transmits 1 - alpha (index 1.5). ``SimpleMaterial``: diffuse, ambient,
    specular, glossiness (Phong exponent) and image. Vertex or face colours (a PLY's): their
    mean as diffuse (one material a mesh). A mesh without any keeps the default material."""
    from trimesh.visual.material import PBRMaterial, SimpleMaterial

    kind = getattr(visual, "kind", None)
    if kind in ("vertex", "face"):
        colours = visual.vertex_colors if kind == "vertex" else visual.face_colors
        return Material(name=name, diffuse=colour_of(np.asarray(colours, np.float64).mean(axis=0)))
    material = getattr(visual, "material", None)
    if kind != "texture" or material is None:
        return Material(name=name)
    if isinstance(material, PBRMaterial):
        base = colour_of(material.baseColorFactor)
        metallic = 1.0 if material.metallicFactor is None else float(material.metallicFactor)
        roughness = 1.0 if material.roughnessFactor is None else float(material.roughnessFactor)
        factor = material.baseColorFactor
        alpha = 1.0 if factor is None or np.asarray(factor).size < 4 else \
            float(np.asarray(factor, np.float64).ravel()[3]) / (255.0 if np.asarray(factor).dtype.kind in "ui" else 1.0)
        blended = str(getattr(material, "alphaMode", "") or "").upper() == "BLEND"
        transmission = min(max(1.0 - alpha, 0.0), 1.0) if blended and np.isfinite(alpha) else 0.0
        mirror = metallic >= 0.5 and roughness <= 0.25
        texture = texture_of(material.baseColorTexture, where)
        return Material(name=name, diffuse=base, reflectance=base if mirror else (0.0, 0.0, 0.0),
                        transmission=transmission, ior=1.5 if transmission > 0 else 1.0, texture=texture,
                        texture_name="baseColorTexture" if texture is not None else "")
    if isinstance(material, SimpleMaterial):
        texture = texture_of(material.image, where)
        shininess = float(material.glossiness) if material.glossiness is not None else 16.0
        return Material(name=name, ambient=colour_of(material.ambient, (0.1, 0.1, 0.1)),
                        diffuse=colour_of(material.diffuse, (0.7, 0.7, 0.7)),
                        specular=colour_of(material.specular, (0.0, 0.0, 0.0)),
                        shininess=shininess if np.isfinite(shininess) and 0 <= shininess <= MAX_COLOUR else 16.0,
                        texture=texture, texture_name="image" if texture is not None else "")
    return Material(name=name)


def placed_geometries(loaded, name: str) -> list:
    """[(name, geometry, vertices f64[V,3], faces i64[F,3])]: every placement of every mesh with
    faces in what ``trimesh.load`` gave (a Trimesh, or a Scene), its vertices moved by its node's
    transform in the scene graph. A glTF's nodes place (and instance) their meshes; taking the
    meshes alone put every one at its own origin, once. A mirroring transform reverses the
    faces' winding, so that their front faces still face out (trimesh does the same)."""
    import trimesh

    if not isinstance(loaded, trimesh.Scene):
        items = [(name, loaded, [np.eye(4)])]
    else:
        graph = loaded.graph
        items = [(key, geom, [graph.get(node)[0] for node in graph.geometry_nodes.get(key, [])] or [np.eye(4)])
                 for key, geom in loaded.geometry.items()]
    placed = []
    for key, geom, transforms in items:
        if not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue
        corners = np.asarray(geom.vertices, np.float64)
        faces = np.asarray(geom.faces)
        for matrix in transforms:
            matrix = np.asarray(matrix, np.float64)
            if np.array_equal(matrix, np.eye(4)):
                placed.append((key, geom, corners, faces))
                continue
            moved = corners @ matrix[:3, :3].T + matrix[:3, 3]
            placed.append((key, geom, moved, faces[:, ::-1] if np.linalg.det(matrix[:3, :3]) < 0 else faces))
    return placed


@scene_loader("mesh")
def load_mesh_scene(files, params, time):
    """Load the first of ``files`` as a mesh scene."""
    import trimesh

    path = Path(files[0])
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise SceneError(f"{path}: unsupported mesh format {suffix!r}; "
                         f"supported: {', '.join(sorted(MESH_SUFFIXES))} and .aff")
    mtl, warnings = {}, []
    if suffix == ".obj":
        obj_text = checked_obj_text(path)
        mtl = read_mtllibs(path, warnings)
        warnings.extend(unknown_materials(path, obj_text, mtl))
    elif suffix == ".off":
        check_off(path)
    elif suffix == ".ply":
        check_ascii_ply(path)
    elif suffix == ".stl":
        check_stl(path)
    try:
        if suffix == ".obj":
            loaded = trimesh.load(io.StringIO(obj_text), file_type="obj", process=False, maintain_order=True,
                                  resolver=bom_free_resolver(path))
        else:
            loaded = trimesh.load(str(path), process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for a malformed file
        raise SceneError(f"{path}: cannot read mesh: {exc}") from None
    builder = SceneBuilder(path.stem, source=str(path))
    emitters = []
    for name, geom, vertices, faces in placed_geometries(loaded, path.stem):
        mat_name = getattr(getattr(geom.visual, "material", None), "name", None) or name
        if suffix == ".obj":  # materials from the MTL as read above (trimesh keeps only part of it)
            material = mtl.get(mat_name) or mtl.get(name) or Material(name=mat_name)
        else:
            material = material_from_visual(geom.visual, mat_name, f"{path}: mesh {name!r}")
        index = builder.add_material(material, key=material.name)
        uvs = None
        if material.texture is not None and getattr(geom.visual, "uv", None) is not None:
            uvs = np.asarray(geom.visual.uv, np.float32)
        builder.add_mesh(vertices, faces, index, uvs=uvs, source=str(path))
        if max(material.ambient) > 1.0:
            # The corners its faces use: with maintain_order every geometry of an OBJ carries the
            # whole file's vertex list, and their mean put the Cornell box's light in the tall block.
            emitters.append((vertices[np.unique(faces)], material))
    if builder.n_triangles == 0:
        raise SceneError(f"{path}: the file holds no triangles")
    lights = None
    if emitters:
        lights = []
        scene_size = None
        for verts, material in emitters:
            centre = verts.mean(axis=0)
            lights.append((centre, material))
        probe = builder.build()
        scene_size = float(np.linalg.norm(probe.bounds()[1] - probe.bounds()[0]))
        centre_all = probe.bounds().mean(axis=0) + np.asarray(probe.origin)  # in the file's coordinates
        placed = []
        for centre, material in lights:
            # Just inside the room from the emitter, towards the scene centre.
            towards = centre_all - centre
            towards /= max(np.linalg.norm(towards), 1e-9)
            placed.append(PointLight(tuple(centre + towards * 0.02 * scene_size), (1.0, 1.0, 1.0)))
        lights = placed
    scene = builder.build(lights=lights)
    scene.info["warnings"] = warnings
    return scene
