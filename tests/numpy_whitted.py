"""The Whitted loop as it was before its shading moved into numba: whole-batch numpy expressions,
secondary and shadow batches re-sorted into packets with ``engine.packet.layout.make_batch`` /
``packet_order``, the image accumulated with ``np.add.at``. Kept as the reference the numba
pipeline (``engine.render.whitted``) must match bit for bit; it traces through the renderer's own
Tracer, so only the shading and the batch bookkeeping differ.
"""
from __future__ import annotations

import numpy as np

from engine.core.offset import coordinate_magnitude, hit_points, offset_origin
from engine.packet.layout import gather_batch, make_batch, packet_order
from engine.render.camera import camera_rays
from engine.render.direct_light import SHADOW_TMAX_SCALE
from engine.render.spawn import MIN_WEIGHT


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _texel(texture, uv):
    h, w = texture.shape[:2]
    x = np.floor((uv[:, 0] % 1.0) * w).astype(np.int64) % w
    y = np.floor((1.0 - uv[:, 1] % 1.0) * h).astype(np.int64) % h
    return texture[y, x]


def render_reference(renderer, width, height):
    """f32[H,W,3]: the image the numpy loop makes with ``renderer``'s scene, config and plugins."""
    cfg, scene = renderer.config.render, renderer.scene
    n = cfg.packet
    image = np.zeros((width * height, 3), np.float32)
    org, dirs = camera_rays(scene, width, height)
    count = width * height
    batches = [make_batch("primary", org, dirs, np.zeros(count), np.full(count, np.inf),
                          np.arange(count, dtype=np.int32), np.ones((count, 3), np.float32), width, height, n)]
    for depth in range(cfg.max_depth + 1):
        children = {"reflection": [], "refraction": []}
        for rays, packets in batches:
            hits = renderer.tracer.trace(rays.kind, "intersect", rays, packets)
            spawned = _shade(renderer, rays, hits, image, depth < cfg.max_depth, depth < cfg.max_reflection_depth,
                             width, height, n)
            for kind, parts in spawned.items():
                children[kind].append(parts)
        batches = []
        for kind in ("reflection", "refraction"):
            parts = [p for p in children[kind] if len(p[0])]
            if parts:
                o, d, pix, w = (np.concatenate([p[i] for p in parts]) for i in range(4))
                batches.append(make_batch(kind, o, d, np.zeros(len(pix)), np.full(len(pix), np.inf), pix, w,
                                          width, height, n))
        if not batches:
            break
    return image.reshape(height, width, 3)


def _shade(renderer, rays, hits, image, spawn, reflect, width, height, n):
    scene, tris, m = renderer.scene, renderer.tris, renderer.materials
    live = rays.pixel >= 0
    miss = live & (hits.prim < 0)
    np.add.at(image, rays.pixel[miss], rays.weight[miss] * np.asarray(scene.background, np.float32))
    idx = np.flatnonzero(live & (hits.prim >= 0))
    empty = (np.zeros((0, 3), np.float32),) * 2 + (np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
    if idx.size == 0:
        return {"reflection": empty, "refraction": empty}
    prim = hits.prim[idx]
    d = rays.dir[idx]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    u, v = hits.u[idx][:, None], hits.v[idx][:, None]
    p = hit_points(tris, prim, hits.u[idx], hits.v[idx])
    magnitude = coordinate_magnitude(tris, prim, p, renderer.corner_magnitude)
    ng = tris.ng[prim]
    entering = _dot(ng, d) < 0
    ng_ff = np.where(entering[:, None], ng, -ng)
    if tris.normals.shape[0]:
        c = tris.normals[prim]
        ns = (1 - u - v) * c[:, 0] + u * c[:, 1] + v * c[:, 2]
        length = np.linalg.norm(ns, axis=1, keepdims=True)
        ns = np.where(length > 0, ns / np.where(length > 0, length, 1), ng)
        ns = np.where((_dot(ns, ng_ff) < 0)[:, None], -ns, ns)
    else:
        ns = ng_ff
    mat = tris.material[prim]
    weight, pixel = rays.weight[idx], rays.pixel[idx]
    texel = np.ones((idx.size, 3), np.float32)
    if tris.uvs.shape[0]:
        for mid in np.unique(mat):
            if m.texture[mid] is None:
                continue
            sel = mat == mid
            c = tris.uvs[prim[sel]]
            uv = (1 - u[sel] - v[sel]) * c[:, 0] + u[sel] * c[:, 1] + v[sel] * c[:, 2]
            texel[sel] = _texel(m.texture[mid], uv)
    color = np.asarray(scene.ambient_light, np.float32) * m.ambient[mat] * texel
    leave = offset_origin(p, ng_ff, magnitude)
    for light in scene.lights:
        to = np.asarray(light.position, np.float32) - leave
        dist = np.sqrt(_dot(to, to)).astype(np.float32)
        l = (to / np.maximum(dist, np.float32(1e-30))[:, None]).astype(np.float32)
        ndotl = _dot(ns, l)
        cand = np.flatnonzero((ndotl > 0) & (_dot(ng_ff, l) > 0))
        if cand.size == 0:
            continue
        gather, packets = packet_order(pixel[cand], width, height, n)
        shadow = gather_batch("shadow", np.where(gather >= 0, cand[np.maximum(gather, 0)], -1), leave, l,
                              np.zeros(idx.size, np.float32), dist * SHADOW_TMAX_SCALE, pixel,
                              np.ones((idx.size, 3), np.float32))
        occluded = renderer.tracer.trace("shadow", "occluded", shadow, packets)
        vis = cand[gather[(gather >= 0) & ~occluded]]
        r = 2 * ndotl[vis, None] * ns[vis] - l[vis]
        spec = np.maximum(-_dot(r, d[vis]), 0) ** m.shininess[mat[vis]]
        color[vis] += np.asarray(light.color, np.float32) * (
            m.diffuse[mat[vis]] * texel[vis] * ndotl[vis, None] + m.specular[mat[vis]] * spec[:, None])
    np.add.at(image, pixel, weight * color)
    if not spawn:
        return {"reflection": empty, "refraction": empty}
    cos_i = -_dot(d, ns)
    refl = d + 2 * cos_i[:, None] * ns
    bad = _dot(refl, ng_ff) <= 0
    cos_g = -_dot(d, ng_ff)
    refl[bad] = d[bad] + 2 * cos_g[bad, None] * ng_ff[bad]
    refl_w = weight * m.reflectance[mat]
    want_refl = (refl_w.max(axis=1) > MIN_WEIGHT) & reflect
    trans = m.transmission[mat]
    want_trans = (trans > 0) & (weight.max(axis=1) * trans > MIN_WEIGHT)
    eta = np.where(entering, 1.0 / m.ior[mat], m.ior[mat]).astype(np.float32)
    k = 1 - eta * eta * (1 - cos_i * cos_i)
    tir = want_trans & (k < 0)
    ok = want_trans & ~tir
    refr = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * ns
    refr_bad = ok & (_dot(refr, ng_ff) >= 0)
    refr[refr_bad] = d[refr_bad]
    trans_w = weight * trans[:, None]
    enter = offset_origin(p, -ng_ff, magnitude)
    r_sel, t_sel, o_sel = np.flatnonzero(want_refl), np.flatnonzero(tir), np.flatnonzero(ok)
    reflection = (np.concatenate([leave[r_sel], leave[t_sel]]), np.concatenate([refl[r_sel], refl[t_sel]]),
                  np.concatenate([pixel[r_sel], pixel[t_sel]]), np.concatenate([refl_w[r_sel], trans_w[t_sel]]))
    refraction = (enter[o_sel], refr[o_sel], pixel[o_sel], trans_w[o_sel])
    return {"reflection": reflection, "refraction": refraction}
