"""``fill_surface_lane`` eight lanes at a time (LLVM vector IR through ``engine.core.lanes8``).

``surface8(dirs, pixel, prim, u, v, records, texture_layout, has_normals, has_uvs, hit, point,
magnitude, view, normal, facing, entering, material, leave, texel_row, start)`` fills the Surface
rows of lanes start .. start+7 as
``engine.render.surface.shade_surface``'s first loop does lane by lane: ``hit`` for every lane,
``leave`` zero where nothing was hit, and on hit lanes the hit point (from the corners in double,
rounded once), the offset scale, the unit ray direction, the geometric and shading normals
turned to the ray, the material and the row of the texel -- the same operations in the same
order and precision, so the same bits. The other rows of lanes without a hit, which a Surface
leaves unset, get whatever the steps give for triangle 0. The background of the misses and the
texels stay with the caller.

Why: per hit lane this is two square roots, six divisions, a dozen double-precision products
and some 30 loads of the hit triangle's corners, normals and texture coordinates, all scalar:
the largest pass between two traversals (35 ms of the kitchen-paper frame on two threads).
The arithmetic is vector, and each hit triangle's fields (corners, normal, corner normals,
texture coordinates, material, offset scale) come from its one record
(``engine.render.surface_record``): one row start per lane, each field one load per lane, dealt
out into vectors by shuffles (``Lanes.gather_record``; one scalar load and insert per element
took three quarters of the step's instructions: kitchen primary batch, one thread, 19.1 -> 15.3
ms; eight separate triangle arrays instead of the record, 1.2-1.4x the loop's time). Arrays:
dirs, point, view, normal, facing, leave f32[R,3] with 12-byte rows; records f32[T, 32] with
contiguous rows (the caller checks both); pixel, prim, material, texel_row i32[R]; u, v,
magnitude f32[R]; hit, entering bool[R].
"""
from __future__ import annotations

from numba import types
from numba.extending import intrinsic

from engine.core.lanes8 import I64, Lanes, check_arguments
from engine.core.offset import MIN_MAGNITUDE, OFFSET_SCALE
from engine.render.surface_record import RECORD_FIELDS

_NAMES = ("dirs", "pixel", "prim", "u", "v", "records", "texture_layout", "has_normals", "has_uvs", "hit", "point",
          "magnitude", "view", "normal", "facing", "entering", "material", "leave", "texel_row", "start")


@intrinsic
def surface8(typingctx, dirs, pixel, prim, u, v, records, texture_layout, has_normals, has_uvs, hit, point,
             magnitude, view, normal, facing, entering, material, leave, texel_row, start):
    """Surface rows of lanes start .. start+7 (see the module doc)."""
    args_ = (dirs, pixel, prim, u, v, records, texture_layout, has_normals, has_uvs, hit, point, magnitude, view,
             normal, facing, entering, material, leave, texel_row, start)
    check_arguments(_NAMES, args_, {"has_normals": types.Boolean, "has_uvs": types.Boolean, "start": types.Integer})
    sig = types.void(*args_)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        a = {}
        for name, t, value in zip(_NAMES, signature.args, args):
            if name in ("has_normals", "has_uvs"):
                a[name] = context.cast(builder, value, t, types.boolean)
            elif name == "start":
                a[name] = lanes.index(t, value)
            else:
                a[name] = lanes.array(t, value)
        i = a["start"]
        prim_ = lanes.row(a["prim"], i)
        hits = (lanes.row(a["pixel"], i) >= 0) & (prim_ >= 0)
        p = lanes.where(hits, lanes.to_i64(prim_), 0)  # a valid row to gather on every lane

        # The hit triangles' records, each field one load per lane (``Lanes.gather_record``);
        # the corner normals and texture coordinates only where the branches below read them.
        starts = lanes.row_starts(a["records"], p)  # once, before the branches that read more fields
        fields = lambda *names: lanes.gather_record(a["records"], starts, {k: RECORD_FIELDS[k] for k in names})
        tri = fields("v0", "v1", "v2", "ng", "magnitude", "material")
        corners = {name: tri[name] for name in ("v0", "v1", "v2")}

        dx, dy, dz = lanes.rows3(a["dirs"], i)
        length = lanes.sqrt(dx * dx + dy * dy + dz * dz)
        view = (dx / length, dy / length, dz / length)
        u, v = lanes.row(a["u"], i), lanes.row(a["v"], i)
        # The hit point from the exact corners in double, rounded once.
        u64, v64 = lanes.to_f64(u), lanes.to_f64(v)
        w64 = 1.0 - u64 - v64
        point = []
        largest = lanes.splat(0.0)
        for k in range(3):
            x = lanes.to_f32(w64 * lanes.to_f64(corners["v0"][k]) + u64 * lanes.to_f64(corners["v1"][k])
                             + v64 * lanes.to_f64(corners["v2"][k]))
            point.append(x)
            largest = lanes.max(largest, lanes.fabs(x))
        magnitude = lanes.max(largest, tri["magnitude"][0])
        g = tri["ng"]
        front = g[0] * view[0] + g[1] * view[1] + g[2] * view[2] < 0.0
        facing = [lanes.where(front, g[k], -g[k]) for k in range(3)]
        w = 1.0 - u - v

        def interpolated_normal():
            corner_normals = fields("normals")["normals"]  # [corner, axis] row by row
            n = [w * corner_normals[k] + u * corner_normals[3 + k] + v * corner_normals[6 + k] for k in range(3)]
            size = lanes.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
            # degenerate interpolation: the geometric normal (then turned to the ray)
            n = [lanes.where(size > 0.0, n[k] / size, g[k]) for k in range(3)]
            away = n[0] * facing[0] + n[1] * facing[1] + n[2] * facing[2] < 0.0
            return [lanes.where(away, -n[k], n[k]) for k in range(3)]

        normal = lanes.choose(a["has_normals"], interpolated_normal, lambda: facing)
        m = lanes.as_i32(tri["material"][0])
        m64 = lanes.to_i64(m)
        layout = a["texture_layout"]
        first_texel = lanes.gather(layout, [0, m64])

        def texel_rows():
            st = fields("uvs")["uvs"]  # [corner, s or t] row by row
            s = w * st[0] + u * st[2] + v * st[4]
            t = w * st[1] + u * st[3] + v * st[5]
            width, height = lanes.gather(layout, [1, m64]), lanes.gather(layout, [2, m64])

            def wrap(q):  # q mod 1 in [0, 1), as numpy's float remainder gives it
                inside = (q >= 0.0) & (q < 1.0)
                return lanes.where(inside, q, q - lanes.floor(q))

            x = lanes.to_i64(lanes.floor(wrap(s) * lanes.to_f32_from_int(width)))
            y = lanes.to_i64(lanes.floor((1.0 - wrap(t)) * lanes.to_f32_from_int(height)))
            x = lanes.where(x >= width, x - width, x)
            y = lanes.where(y >= height, y - height, y)
            return [lanes.where(first_texel >= 0, first_texel + y * width + x, -1)]

        row = lanes.choose(a["has_uvs"], texel_rows, lambda: [lanes.splat(-1, I64)])[0]
        step = OFFSET_SCALE * lanes.max(magnitude, MIN_MAGNITUDE)
        leave = [lanes.where(hits, point[k] + step * facing[k], 0.0) for k in range(3)]

        # Rows of lanes without a hit are unset in a Surface, so every row is stored whole: a
        # masked row of three floats would be read, selected and written back, and the reads of
        # fresh pages doubled the first frame's page faults (default scene: 19 -> 56 ms).
        lanes.store_row(a["hit"], i, hits)
        lanes.store_rows3(a["leave"], i, leave)
        lanes.store_rows3(a["point"], i, point)
        lanes.store_row(a["magnitude"], i, magnitude)
        lanes.store_rows3(a["view"], i, view)
        lanes.store_rows3(a["normal"], i, normal)
        lanes.store_rows3(a["facing"], i, facing)
        lanes.store_row(a["entering"], i, front)
        lanes.store_row(a["material"], i, m)
        lanes.store_row(a["texel_row"], i, lanes.to_i32(row))
        return context.get_dummy_value()

    return sig, codegen
