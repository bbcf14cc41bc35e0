"""The shared kernels: watertight triangle test and conservative slab tests."""
import numpy as np
import trimesh

from engine.core.bvh import build_bvh
from engine.core.triangle import intersect_triangle, ray_shear, safe_inverse, slab_test
from engine.packet.layout import gather_batch
from engine.render.plugins import make_traversal
from engine.core.scene import make_triangles
from engine.core.types import empty_hits


def closed_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.3)
    return mesh, make_triangles(mesh.vertices, mesh.faces, 0)


def rays_at(targets, rng):
    """Rays aimed exactly at points on the sphere mesh from outside, within 30 degrees of the
    outward normal, so each ray truly enters the surface there (a ray aimed at a silhouette
    vertex only touches the mesh and may rightly miss)."""
    normal = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    tangent = np.cross(normal, rng.normal(size=targets.shape))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    origins = targets + 3.0 * normal + rng.uniform(0, 1.5, (len(targets), 1)) * tangent
    return origins.astype(np.float32), (targets - origins).astype(np.float32)


def trace(tris, org, d):
    n = len(org)
    gather = np.arange(n)
    rays = gather_batch("primary", gather, org, d, np.zeros(n), np.full(n, np.inf), np.arange(n),
                        np.ones((n, 3)), )
    hits = empty_hits(n)
    make_traversal("single").intersect(build_bvh(tris), tris, rays, None, None, hits, None)
    return hits


def test_rays_at_shared_vertices_and_edges_never_miss():
    rng = np.random.default_rng(7)
    mesh, tris = closed_mesh()
    v = mesh.vertices.astype(np.float32)
    edges = mesh.edges_unique
    s = rng.random((len(edges), 1)).astype(np.float32)
    on_edges = v[edges[:, 0]] + s * (v[edges[:, 1]] - v[edges[:, 0]])
    midpoints = (v[edges[:, 0]] + v[edges[:, 1]]) * np.float32(0.5)
    for targets in (v, on_edges, midpoints, v, on_edges):
        org, d = rays_at(targets.astype(np.float32), rng)
        hits = trace(tris, org, d)
        assert (hits.prim >= 0).all(), f"{int((hits.prim < 0).sum())} rays slipped through the mesh"


def test_triangle_kernel_returns_barycentrics_and_respects_the_segment():
    tris = make_triangles([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], 0)
    o = np.array([0.25, 0.5, -2.0], np.float32)
    kx, ky, kz, sx, sy, sz = ray_shear(np.float32(0), np.float32(0), np.float32(1))
    args = (o[kx], o[ky], o[kz], kx, ky, kz, sx, sy, sz)
    t, u, v = intersect_triangle(*args, np.float32(0), np.float32(np.inf), tris.v0, tris.v1, tris.v2, 0)
    assert np.isclose(t, 2.0) and np.isclose(u, 0.25) and np.isclose(v, 0.5)
    t, _, _ = intersect_triangle(*args, np.float32(0), np.float32(1.5), tris.v0, tris.v1, tris.v2, 0)
    assert np.isinf(t)
    degenerate = make_triangles([[0, 0, 0], [1, 1, 0], [2, 2, 0]], [[0, 1, 2]], 0)
    t, _, _ = intersect_triangle(*args, np.float32(0), np.float32(np.inf), degenerate.v0, degenerate.v1,
                                 degenerate.v2, 0)
    assert np.isinf(t)


def test_slab_test_handles_axis_parallel_rays():
    rng = np.random.default_rng(3)
    bmin = np.array([[0, 0, 0]], np.float32)
    bmax = np.array([[1, 1, 1]], np.float32)
    org = rng.uniform(-2, 3, (64, 3)).astype(np.float32)
    d = rng.normal(size=(64, 3)).astype(np.float32)
    d[::4, 1:] = 0  # axis-parallel rays: inv_dir must stay finite
    inv = safe_inverse(d)
    assert np.isfinite(inv).all()
    tmin = np.zeros(64, np.float32)
    tmax = np.full(64, np.inf, np.float32)
    for r in range(64):
        single = slab_test(*org[r], *inv[r], tmin[r], tmax[r], bmin, bmax, 0)
        # Brute force: sample the ray densely and see whether it enters the box.
        ts = np.linspace(0, 10, 4001, dtype=np.float32)
        pts = org[r] + ts[:, None] * d[r]
        inside = ((pts >= -1e-4) & (pts <= 1 + 1e-4)).all(axis=1).any()
        if inside:
            assert np.isfinite(single)
