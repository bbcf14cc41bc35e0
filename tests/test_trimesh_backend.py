"""engine.RayMeshIntersector as trimesh's ``mesh.ray``: the same answers as trimesh's default
(embreex) backend and as geometry, with trimesh's defaults, dtypes and ordering; every hit in
distance order; contains on watertight meshes; float64 locations far from the origin; answers
that follow the mesh; bad rays as misses; named errors."""
import copy
import pickle
import warnings

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector as EmbreeIntersector

from engine import RayMeshIntersector
from engine.query.contains import DIRECTIONS
from engine.query.errors import BadRayWarning, QueryInputError, QueryTypeError


# -- helpers ---------------------------------------------------------------------------------
def rays_at(mesh, n, seed, spread=2.0):
    """Incoherent rays from around the mesh, most aimed through it (directions of any length)."""
    rng = np.random.default_rng(seed)
    center, size = mesh.bounds.mean(axis=0), mesh.extents.max()
    origins = center + rng.normal(size=(n, 3)) * spread * size
    targets = center + rng.uniform(-0.4, 0.4, size=(n, 3)) * mesh.extents
    directions = (targets - origins) * 10.0 ** rng.uniform(-2, 2, size=(n, 1))
    return origins, directions


def plane_distance(mesh, origins, directions, index_ray, index_tri):
    """f64[m]: distance along each (unit) ray to its hit triangle's plane, in float64."""
    unit = directions[index_ray] / np.linalg.norm(directions[index_ray], axis=1, keepdims=True)
    normal = mesh.face_normals[index_tri]
    corner = mesh.triangles[index_tri, 0]
    return np.einsum("ij,ij->i", corner - origins[index_ray], normal) / np.einsum("ij,ij->i", unit, normal)


def assert_same_first_hits(mesh, ours, theirs, origins, directions):
    """Equal triangle indices, except where the two hit points coincide (a ray through an edge)."""
    assert ours.dtype == theirs.dtype
    assert np.array_equal(ours >= 0, theirs >= 0)
    differ = np.flatnonzero((ours != theirs) & (ours >= 0))
    assert len(differ) <= 0.005 * len(ours)
    if len(differ):
        a = plane_distance(mesh, origins, directions, differ, ours[differ])
        b = plane_distance(mesh, origins, directions, differ, theirs[differ])
        np.testing.assert_allclose(a, b, atol=1e-5 * mesh.scale)


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=2.0)


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.fixture(scope="module")
def bunny():
    from conftest import SHARED_SCENES, needs_shared_scenes

    needs_shared_scenes()
    return trimesh.load(SHARED_SCENES / "stanford-bunny" / "bun_zipper_res2.ply", force="mesh")


# -- first and any hit -----------------------------------------------------------------------
@pytest.mark.parametrize("which,order", [("sphere", "input"), ("bunny", "input"), ("bunny", "morton")])
def test_first_and_any_hit_equal_trimesh_default_backend(which, order, request):
    mesh = request.getfixturevalue(which)
    origins, directions = rays_at(mesh, 20000, seed=1)
    ours, theirs = RayMeshIntersector(mesh, order=order), EmbreeIntersector(mesh)
    first = ours.intersects_first(origins, directions)
    assert_same_first_hits(mesh, first, theirs.intersects_first(origins, directions), origins, directions)
    assert (first >= 0).sum() > 5000
    anyhit = ours.intersects_any(origins, directions)
    assert anyhit.dtype == np.bool_ and np.array_equal(anyhit, theirs.intersects_any(origins, directions))
    # multiple_hits=False: the first hit per ray, in ray order, as trimesh answers it.
    index_tri, index_ray = ours.intersects_id(origins, directions, multiple_hits=False)
    assert np.array_equal(index_ray, np.flatnonzero(first >= 0)) and np.array_equal(index_tri, first[index_ray])
    assert index_tri.dtype == index_ray.dtype == np.int64


def pinhole_rays(mesh, side, bad=0):
    """Camera rays (f64) of a side x side image looking at the mesh from outside, row by row;
    ``bad`` of them get a NaN or zero direction."""
    center, size = mesh.bounds.mean(axis=0), mesh.extents.max()
    eye = center + np.array([0.3, 0.4, 2.5]) * size
    ys, xs = np.meshgrid(np.linspace(-0.4, 0.4, side), np.linspace(-0.4, 0.4, side), indexing="ij")
    forward = (center - eye) / np.linalg.norm(center - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    directions = forward + xs.reshape(-1, 1) * right + ys.reshape(-1, 1) * up
    origins = np.repeat(eye[None], side * side, axis=0)
    directions[:bad:2] = np.nan
    directions[1:bad:2] = 0.0
    return origins, directions


@pytest.mark.parametrize("which", ["sphere", "bunny"])
def test_coherent_rays_take_the_packet_walk_with_the_per_ray_walks_answers(which, request, monkeypatch):
    """Camera rays go through the packet walk (engine.query.coherent) and answer exactly as the
    per-ray walk does; scattered rays stay on the per-ray walk."""
    import engine.query.coherent as coherent
    import engine.query.intersector as intersector

    mesh = request.getfixturevalue(which)
    origins, directions = pinhole_rays(mesh, 96, bad=6)
    scattered = rays_at(mesh, 20000, seed=4)
    assert coherent.is_coherent(origins, directions, mesh.extents.max())
    assert not coherent.is_coherent(*scattered, mesh.extents.max())
    calls = []
    monkeypatch.setattr(intersector, "packet_first_hits",
                        lambda *a: calls.append(1) or coherent.packet_first_hits(*a))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        packed = RayMeshIntersector(mesh).intersects_first(origins, directions)
        packed_any = RayMeshIntersector(mesh).intersects_any(origins, directions)
    assert len(calls) == 2 and all(issubclass(w.category, BadRayWarning) for w in caught) and len(caught) == 2
    monkeypatch.setattr(intersector, "packing", lambda *a: coherent.PACK_NONE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BadRayWarning)
        per_ray = RayMeshIntersector(mesh).intersects_first(origins, directions)
        per_ray_any = RayMeshIntersector(mesh).intersects_any(origins, directions)
    assert np.array_equal(packed, per_ray) and np.array_equal(packed_any, per_ray_any)
    assert (packed[:6] == -1).all() and (packed >= 0).sum() > 1000
    assert len(calls) == 2



@pytest.mark.parametrize("which", ["sphere", "bunny"])
def test_shuffled_rays_from_one_eye_are_sorted_into_packets_with_the_per_ray_walks_answers(which, request,
                                                                                           monkeypatch):
    """Camera rays in a random order (bad ones among them) make loose packets in that order: the
    batch is sorted by ``engine.query.order.coherent_order`` and walked in packets of sorted
    neighbours, answering each ray exactly as the per-ray walk does and as Embree does
    (tie-aware). Rays that spread in origin and direction alike are not sorted."""
    import engine.query.coherent as coherent
    import engine.query.intersector as intersector

    mesh = request.getfixturevalue(which)
    origins, directions = pinhole_rays(mesh, 96, bad=6)
    shuffle = np.random.default_rng(3).permutation(len(origins))
    origins, directions = origins[shuffle], directions[shuffle]
    scale = mesh.extents.max()
    assert coherent.packing(origins, directions, scale) == coherent.PACK_SORTED
    assert coherent.packing(*pinhole_rays(mesh, 96), scale) == coherent.PACK_INPUT
    assert coherent.packing(*rays_at(mesh, 20000, seed=4), scale) == coherent.PACK_NONE
    packed_rows = []
    monkeypatch.setattr(intersector, "packet_first_hits",
                        lambda *a: packed_rows.append(a[7].copy()) or coherent.packet_first_hits(*a))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BadRayWarning)
        sorted_first = RayMeshIntersector(mesh).intersects_first(origins, directions)
        sorted_any = RayMeshIntersector(mesh).intersects_any(origins, directions)
        assert len(packed_rows) == 2
        rows = packed_rows[0]
        assert np.array_equal(np.sort(rows), np.arange(len(origins)))
        # The packets are tight: far tighter than blocks of the shuffled order.
        assert coherent.coherent_blocks(coherent.block_medians(origins, directions, scale, rows))
        assert coherent.block_medians(origins, directions, scale, rows)[0] < \
            0.1 * coherent.block_medians(origins, directions, scale)[0]
        monkeypatch.setattr(intersector, "packing", lambda *a: coherent.PACK_NONE)
        per_ray = RayMeshIntersector(mesh).intersects_first(origins, directions)
        per_ray_any = RayMeshIntersector(mesh).intersects_any(origins, directions)
        theirs = EmbreeIntersector(mesh)
        good = np.isfinite(directions).all(axis=1) & (np.abs(directions).sum(axis=1) > 0)
        assert_same_first_hits(mesh, sorted_first[good], theirs.intersects_first(origins[good], directions[good]),
                               origins[good], directions[good])
    assert np.array_equal(sorted_first, per_ray) and np.array_equal(sorted_any, per_ray_any)
    assert (sorted_first[~good] == -1).all() and (sorted_first >= 0).sum() > 1000


def test_camera_rays_through_the_packet_walk_equal_trimesh_default_backend(bunny):
    """Rays from one eye take the packet walk with pinhole frusta (``PINHOLE_OR_GENERAL``) and
    answer as Embree does, first and any hit, tie-aware."""
    import engine.query.coherent as coherent

    origins, directions = pinhole_rays(bunny, 160)
    assert coherent.is_coherent(origins, directions, bunny.extents.max())
    ours, theirs = RayMeshIntersector(bunny), EmbreeIntersector(bunny)
    first = ours.intersects_first(origins, directions)
    assert_same_first_hits(bunny, first, theirs.intersects_first(origins, directions), origins, directions)
    assert (first >= 0).sum() > 3000  # the bunny fills about a sixth of the view
    assert np.array_equal(ours.intersects_any(origins, directions), theirs.intersects_any(origins, directions))

def test_camera_rays_are_recognised_by_their_row_length_and_walked_in_tiles(bunny, monkeypatch):
    """A row-by-row image of a width that is no multiple of the tile (101 x 83) is recognised;
    its rays are walked tile by tile (every ray once) with the per-ray walk's answers; shuffled
    rays, parallel rays and too few rows are not taken for an image."""
    import engine.query.coherent as coherent
    import engine.query.intersector as intersector

    side_x, side_y = 101, 83
    origins, directions = pinhole_rays(bunny, side_x)
    # Keep 83 rows of the 101 x 101 image, then spoil one ray with NaN (a bad ray is a miss).
    origins, directions = origins[: side_x * side_y].copy(), directions[: side_x * side_y].copy()
    directions[5 * side_x + 7] = np.nan
    assert coherent.row_length(directions) == side_x
    rows = coherent.tiled_rows(len(directions), side_x)
    assert len(rows) % coherent.PACKET_RAYS == 0
    assert np.array_equal(np.sort(rows[rows >= 0]), np.arange(len(directions)))
    assert rows[:coherent.TILE].tolist() == list(range(coherent.TILE))  # a tile's first row
    assert rows[coherent.TILE] == side_x  # then the next image row
    shuffled = np.random.default_rng(0).permutation(len(directions))
    assert coherent.row_length(directions[shuffled]) == 0
    assert coherent.row_length(np.tile([0.0, 0.0, 1.0], (5000, 1))) == 0
    assert coherent.row_length(directions[: side_x * 4]) == 0  # fewer rows than a tile

    packed_rows = []
    monkeypatch.setattr(intersector, "packet_first_hits",
                        lambda *a: packed_rows.append(a[7]) or coherent.packet_first_hits(*a))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BadRayWarning)
        tiled = RayMeshIntersector(bunny).intersects_first(origins, directions)
        tiled_any = RayMeshIntersector(bunny).intersects_any(origins, directions)
        assert len(packed_rows) == 2 and np.array_equal(packed_rows[0], rows)
        monkeypatch.setattr(intersector, "packing", lambda *a: coherent.PACK_NONE)
        per_ray = RayMeshIntersector(bunny).intersects_first(origins, directions)
        per_ray_any = RayMeshIntersector(bunny).intersects_any(origins, directions)
    assert np.array_equal(tiled, per_ray) and np.array_equal(tiled_any, per_ray_any)
    assert tiled[5 * side_x + 7] == -1 and (tiled >= 0).sum() > 1000


# -- every hit -------------------------------------------------------------------------------
@pytest.mark.parametrize("which,order", [("box", "input"), ("sphere", "morton"), ("bunny", "input"),
                                         ("bunny", "morton")])
def test_every_hit_in_distance_order_equals_trimesh(which, order, request):
    mesh = request.getfixturevalue(which)
    origins, directions = rays_at(mesh, 5000, seed=2)
    ours = RayMeshIntersector(mesh, order=order)
    locations, index_ray, index_tri = ours.intersects_location(origins, directions)  # default: every hit
    assert locations.dtype == np.float64 and locations.shape == (len(index_ray), 3)
    assert index_ray.dtype == index_tri.dtype == np.int64
    assert np.all(np.diff(index_ray) >= 0)  # grouped by ray, in ray order
    # Within a ray, in distance order.
    distance = np.linalg.norm(locations - origins[index_ray], axis=1)
    same_ray = np.diff(index_ray) == 0
    assert np.all(np.diff(distance)[same_ray] > 0)
    # The same hits per ray as trimesh's default backend (which re-casts from each hit).
    their_tri, their_ray, their_loc = EmbreeIntersector(mesh).intersects_id(origins, directions,
                                                                             return_locations=True)
    ours_per_ray = np.bincount(index_ray, minlength=len(origins))
    theirs_per_ray = np.bincount(their_ray, minlength=len(origins))
    assert (ours_per_ray != theirs_per_ray).sum() <= 0.002 * len(origins)
    agree = np.flatnonzero(ours_per_ray == theirs_per_ray)
    mine = np.isin(index_ray, agree)
    theirs = np.isin(their_ray, agree)
    key = np.lexsort((np.linalg.norm(their_loc[theirs] - origins[their_ray[theirs]], axis=1), their_ray[theirs]))
    np.testing.assert_allclose(locations[mine], their_loc[theirs][key], atol=1e-5 * mesh.scale)
    # Locations lie on their triangle's plane and on the ray.
    t = plane_distance(mesh, origins, directions, index_ray, index_tri)
    np.testing.assert_allclose(distance, t, atol=1e-9 * mesh.scale, rtol=1e-9)
    if which in ("box", "sphere"):  # convex and closed: a ray from outside that hits crosses twice
        outside = ~mesh.contains(origins)
        assert set(np.unique(ours_per_ray[outside])) <= {0, 2} and (ours_per_ray == 2).sum() > 1000


def test_max_hits_caps_hits_per_ray(sphere):
    origins, directions = rays_at(sphere, 3000, seed=3)
    ours = RayMeshIntersector(sphere)
    all_tri, all_ray = ours.intersects_id(origins, directions, max_hits=None)
    one_tri, one_ray = ours.intersects_id(origins, directions, max_hits=1)
    first = ours.intersects_first(origins, directions)
    assert np.array_equal(one_ray, np.flatnonzero(first >= 0)) and np.array_equal(one_tri, first[one_ray])
    assert len(all_ray) > len(one_ray)


def test_rays_along_and_through_edges_of_a_box(box):
    """A ray through a shared edge or corner crosses once; rays in a face's plane are trimesh's
    business too: the count per ray equals trimesh's."""
    ours, theirs = RayMeshIntersector(box), EmbreeIntersector(box)
    hx, hy, hz = box.extents / 2
    origins = np.array([[0, 0, -5], [hx, 0, -5], [hx, hy, -5], [0, hy, -5], [-5, -5, -5],
                        [hx, -5, 0], [0.1, 0.2, 5]], np.float64)
    directions = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 1, 1], [0, 1, 0], [0, 0, -1]], float)
    directions[4] = np.array([hx, hy, hz]) - origins[4]  # through the corner and out of the opposite one
    _, index_ray = ours.intersects_id(origins, directions)
    counts = np.bincount(index_ray, minlength=len(origins))
    assert counts[0] == 2 and counts[6] == 2  # straight through two faces
    assert counts[4] in (1, 2)  # the corner ray touches the box at one corner point only ...
    _, their_ray = theirs.intersects_id(origins, directions)
    assert counts[1] == np.bincount(their_ray, minlength=len(origins))[1] == 2  # ... an edge is one crossing


# -- contains --------------------------------------------------------------------------------
def box_truth(box, points):
    return np.all(np.abs(points - box.bounds.mean(axis=0)) < box.extents / 2, axis=1)


def test_contains_on_a_box_with_points_on_face_planes_and_rays_through_edges(box):
    rng = np.random.default_rng(4)
    h = box.extents / 2
    points = rng.uniform(-1.5 * h, 1.5 * h, size=(4000, 3))
    # Points on the planes of faces, inside and outside the faces' extent (not on the surface).
    on_plane = rng.uniform(-1.5 * h, 1.5 * h, size=(600, 3))
    axis = rng.integers(0, 3, 600)
    on_plane[np.arange(600), axis] = h[axis] * rng.choice([-1, 1], 600)
    on_surface = np.all(np.abs(on_plane) <= h, axis=1)
    # Points inside whose first cast direction runs exactly through an edge or a corner.
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    edge_mid = (corners[:, None] + corners[None]) / 2
    targets = np.concatenate([corners, edge_mid.reshape(-1, 3)])
    through = targets - 0.3 * DIRECTIONS[0]
    through = through[np.all(np.abs(through) < h, axis=1)]
    assert len(through) > 0
    pts = np.concatenate([points, on_plane[~on_surface], through])
    got = RayMeshIntersector(box).contains_points(pts)
    assert got.dtype == np.bool_ and got.shape == (len(pts),)
    assert np.array_equal(got, box_truth(box, pts))
    assert got.sum() > 500


def test_contains_on_a_sphere_and_an_annulus_equals_geometry_and_trimesh(sphere):
    rng = np.random.default_rng(5)
    pts = rng.uniform(-2.5, 2.5, size=(20000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = (r < 1.95) | (r > 2.001)  # away from the facets of the icosphere
    got = RayMeshIntersector(sphere).contains_points(pts)
    assert np.array_equal(got[clear], r[clear] < 2)
    assert (got == EmbreeIntersector(sphere).contains_points(pts)).mean() > 0.999
    ring = trimesh.creation.annulus(r_min=1.0, r_max=2.0, height=1.0, sections=64)  # not convex
    assert ring.is_watertight
    radial = np.linalg.norm(pts[:, :2], axis=1)
    inside = (radial > 1.0) & (radial < 2.0) & (np.abs(pts[:, 2]) < 0.5)
    clear = (np.abs(radial - 1.0) > 0.01) & (np.abs(radial - 2.0) > 0.01) & (np.abs(np.abs(pts[:, 2]) - 0.5) > 1e-6)
    got = RayMeshIntersector(ring).contains_points(pts)
    assert np.array_equal(got[clear], inside[clear]) and inside.sum() > 1000


# -- as mesh.ray -----------------------------------------------------------------------------
def test_trimesh_features_use_it_as_mesh_ray(sphere):
    mesh = sphere.copy()
    mesh.ray = RayMeshIntersector(mesh)
    assert mesh.ray.mesh is mesh
    rng = np.random.default_rng(6)
    pts = rng.uniform(-2.5, 2.5, size=(3000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = (r < 1.95) | (r > 2.001)
    assert np.array_equal(mesh.contains(pts)[clear], r[clear] < 2)
    samples = trimesh.sample.volume_mesh(mesh, 2000, seed=1)  # built on mesh.contains
    assert len(samples) > 500 and np.linalg.norm(samples, axis=1).max() < 2.0
    from trimesh.voxel.creation import voxelize_ray  # built on mesh.ray.intersects_location

    ours = voxelize_ray(mesh, pitch=0.25)
    mesh.ray = EmbreeIntersector(mesh)
    theirs = voxelize_ray(mesh, pitch=0.25)
    cells = np.unique(ours.encoding.sparse_indices, axis=0)
    assert np.array_equal(cells, np.unique(theirs.encoding.sparse_indices, axis=0)) and len(cells) > 100


class CountingIntersector(RayMeshIntersector):
    """RayMeshIntersector that counts the rays each of its queries is asked about."""

    def __init__(self, mesh):
        super().__init__(mesh)
        self.asked = {}

    def _count(self, name, n):
        self.asked[name] = self.asked.get(name, 0) + n

    def intersects_id(self, ray_origins, ray_directions, *args, **kwargs):
        self._count("intersects_id", len(ray_origins))
        return super().intersects_id(ray_origins, ray_directions, *args, **kwargs)

    def contains_points(self, points):
        self._count("contains_points", len(points))
        return super().contains_points(points)


def test_trimesh_proximity_thickness_and_signed_distance_use_it(sphere):
    """trimesh.proximity's ray thickness (every hit along rays from surface points) and signed
    distance (inside or outside by ray parity, where a point projects off its nearest triangle)
    ask mesh.ray and agree with trimesh's default backend. They need scipy and rtree (the
    ``proximity`` extra, which ``make test`` installs)."""
    pytest.importorskip("scipy")
    pytest.importorskip("rtree")
    from trimesh.proximity import signed_distance, thickness

    ours = sphere.copy()
    ours.ray = CountingIntersector(ours)
    theirs = sphere.copy()
    theirs.ray = EmbreeIntersector(theirs)
    surface = sphere.sample(300, seed=3)
    expected = thickness(theirs, surface, method="ray")
    got = thickness(ours, surface, method="ray")
    assert ours.ray.asked.get("intersects_id", 0) >= len(surface)
    assert np.allclose(got, expected, rtol=0, atol=1e-9 * sphere.scale) and np.all(np.isfinite(got))
    # Along the face normal, through (nearly) the centre: a diameter of the radius-2 polyhedron,
    # whose faces lie within 1.5% of the sphere.
    assert np.all((got > 3.94) & (got <= 4.0))
    points = np.random.default_rng(8).uniform(-3, 3, size=(400, 3))
    points[:40] = surface[:40] * 0.999  # just inside, where the sign decides most
    expected = signed_distance(theirs, points)
    got = signed_distance(ours, points)
    assert ours.ray.asked.get("contains_points", 0) > 0
    assert np.array_equal(np.sign(got), np.sign(expected)) and np.allclose(got, expected, atol=1e-12)


# -- precision -------------------------------------------------------------------------------
@pytest.mark.parametrize("offset", [1e6, -3e6])
def test_locations_far_from_the_origin_are_float64_accurate(sphere, offset):
    far = sphere.copy()
    shift = np.array([offset, -offset / 2, offset / 3])
    far.apply_translation(shift)
    origins, directions = rays_at(sphere, 5000, seed=7)
    near_loc, near_ray, near_tri = RayMeshIntersector(sphere).intersects_location(origins, directions)
    far_loc, far_ray, far_tri = RayMeshIntersector(far).intersects_location(origins + shift, directions)
    assert np.array_equal(near_ray, far_ray) and len(near_ray) > 3000
    same = near_tri == far_tri
    assert same.mean() > 0.99
    np.testing.assert_allclose(far_loc[same] - shift, near_loc[same], atol=1e-6 * sphere.scale, rtol=0)
    # inside/outside far away: the same answers as near the origin
    pts = np.random.default_rng(8).uniform(-2.5, 2.5, size=(5000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = (r < 1.95) | (r > 2.001)
    assert np.array_equal(RayMeshIntersector(far).contains_points(pts + shift)[clear], r[clear] < 2)


# -- freshness -------------------------------------------------------------------------------
def test_answers_follow_moved_vertices_and_new_faces(sphere):
    mesh = sphere.copy()
    ours = RayMeshIntersector(mesh)
    origins, directions = rays_at(sphere, 5000, seed=9)
    ours.intersects_first(origins, directions)  # builds
    built = ours._structure()
    mesh.apply_translation([0.7, 0.0, 0.0])  # vertices move in place: refit
    mesh.vertices[:, 2] *= 1.3
    first = ours.intersects_first(origins, directions)
    assert ours._structure().faces is built.faces  # same triangles, refitted tree
    assert_same_first_hits(mesh, first, EmbreeIntersector(mesh).intersects_first(origins, directions),
                           origins, directions)
    new = trimesh.creation.icosphere(subdivisions=2, radius=1.5)  # new faces: rebuild
    mesh.vertices, mesh.faces = new.vertices, new.faces
    first = ours.intersects_first(origins, directions)
    assert first.max() < len(new.faces)
    assert_same_first_hits(mesh, first, EmbreeIntersector(mesh).intersects_first(origins, directions),
                           origins, directions)
    pts = np.random.default_rng(10).uniform(-2, 2, size=(3000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = (r < 1.45) | (r > 1.501)
    assert np.array_equal(ours.contains_points(pts)[clear], r[clear] < 1.5)


def test_queries_reuse_their_working_arrays_but_never_return_them(sphere):
    """The scratch an intersector keeps between queries (engine.core.scratch) changes no answer,
    whatever the order and sizes of the batches, never backs a returned array, and a query that
    finds it taken (another thread inside a query) works in fresh arrays."""
    ours = RayMeshIntersector(sphere)
    camera = pinhole_rays(sphere, 80)             # the packet walk
    scattered = rays_at(sphere, 3000, seed=21)    # the per-ray walk
    small = rays_at(sphere, 700, seed=22)
    expected = {name: (RayMeshIntersector(sphere).intersects_first(*rays),
                       RayMeshIntersector(sphere).intersects_id(*rays, multiple_hits=False),
                       RayMeshIntersector(sphere).intersects_id(*rays))
                for name, rays in (("camera", camera), ("scattered", scattered), ("small", small))}
    kept = []
    for name, rays in (("camera", camera), ("scattered", scattered), ("small", small), ("camera", camera),
                       ("small", small), ("scattered", scattered)):
        first = ours.intersects_first(*rays)
        one_hit = ours.intersects_id(*rays, multiple_hits=False)
        every_hit = ours.intersects_id(*rays)
        want_first, want_one, want_every = expected[name]
        assert np.array_equal(first, want_first)
        assert all(np.array_equal(a, b) for a, b in zip(one_hit + every_hit, want_one + want_every))
        kept.append((name, first.copy(), first))
    for name, copied, returned in kept:  # later queries did not write into earlier answers
        assert np.array_equal(copied, returned)
        for buffer in ours._scratch._buffers.values():
            assert not np.shares_memory(returned, buffer)
    assert ours._scratch.nbytes() > 0
    assert ours._scratch_lock.acquire(blocking=False)
    try:
        assert np.array_equal(ours.intersects_first(*camera), expected["camera"][0])
    finally:
        ours._scratch_lock.release()


def test_pickle_and_copy_behave_like_trimesh(sphere):
    ours = RayMeshIntersector(sphere)
    origins, directions = rays_at(sphere, 2000, seed=11)
    expected = ours.intersects_first(origins, directions)
    for other in (pickle.loads(pickle.dumps(ours)), copy.copy(ours), copy.deepcopy(ours)):
        assert isinstance(other, RayMeshIntersector) and other._structure_cache is None
        assert np.array_equal(other.intersects_first(origins, directions), expected)
    assert copy.copy(ours).mesh is sphere


# -- bad rays and bad arrays -----------------------------------------------------------------
def test_bad_rays_are_misses_beside_good_rays(sphere):
    origins, directions = rays_at(sphere, 1000, seed=12)
    bad_o, bad_d = origins.copy(), directions.copy()
    bad_d[3] = np.nan
    bad_d[5] = 0.0
    bad_o[7] = [np.inf, 0, 0]
    bad_d[9] = [1e308, 1e308, 0]  # |d| overflows
    bad = [3, 5, 7, 9]
    good = np.setdiff1d(np.arange(1000), bad)
    ours = RayMeshIntersector(sphere)
    expected = ours.intersects_first(origins, directions)
    with pytest.warns(BadRayWarning, match="4 of 1000 rays"):
        first = ours.intersects_first(bad_o, bad_d)
    with pytest.warns(BadRayWarning, match="4 of 1000 rays"):  # sorted, bad rays go last: same answers
        assert np.array_equal(RayMeshIntersector(sphere, order="morton").intersects_first(bad_o, bad_d), first)
    assert np.all(first[bad] == -1) and np.array_equal(first[good], expected[good])
    assert (expected[good] >= 0).sum() > 300
    with pytest.warns(BadRayWarning):
        assert not ours.intersects_any(bad_o, bad_d)[bad].any()
    with pytest.warns(BadRayWarning):
        _, index_ray = ours.intersects_id(bad_o, bad_d)
    assert not np.isin(index_ray, bad).any()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ours.intersects_first(origins, directions)  # no warning when every ray is fine
    assert not ours.contains_points([[np.nan, 0, 0]])[0]


def test_an_origin_too_far_for_float32_is_a_miss_the_warning_names(sphere):
    # 1e29 mesh sizes out float32 still answers; from 1e30 no hit distance keeps a digit of the
    # mesh, so the ray is a miss, and the warning says why (it once blamed NaN/inf for it).
    ours = RayMeshIntersector(sphere)
    size = float(np.ptp(sphere.vertices, axis=0).max())
    centre = sphere.bounds.mean(axis=0)
    near = centre + [1e28 * size, 0, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ours.intersects_any([near], [[-1.0, 0, 0]])[0]
    far = centre + [1e31 * size, 0, 0]
    with pytest.warns(BadRayWarning, match="1 of 2 rays .* origin 1e\\+30 mesh sizes"):
        assert list(ours.intersects_any([far, near], [[-1.0, 0, 0]] * 2)) == [False, True]


@pytest.mark.parametrize("call,error,words", [
    (lambda r: r.intersects_first(np.zeros((4, 2)), np.ones((4, 2))), QueryInputError, ["ray_origins", "(4, 2)"]),
    (lambda r: r.intersects_id(np.zeros((4, 3)), np.ones((5, 3))), QueryInputError, ["ray_directions", "(5, 3)"]),
    (lambda r: r.intersects_any([["a", "b", "c"]], np.ones((1, 3))), QueryTypeError, ["ray_origins", "dtype"]),
    (lambda r: r.intersects_location(np.zeros((1, 3)), np.ones((1, 3)) * 1j), QueryTypeError, ["ray_directions"]),
    (lambda r: r.intersects_id(np.zeros((1, 3)), np.ones((1, 3)), max_hits=-1), QueryInputError, ["max_hits", "-1"]),
    (lambda r: r.intersects_id(np.zeros((1, 3)), np.ones((1, 3)), max_hits=2.5), QueryTypeError, ["max_hits"]),
    (lambda r: r.contains_points(np.zeros((3, 4))), QueryInputError, ["points", "(3, 4)"]),
    (lambda r: r.contains_points([[object(), 1, 2]]), QueryTypeError, ["points"]),
    (lambda r: RayMeshIntersector("mesh"), QueryTypeError, ["vertices", "faces"]),
    (lambda r: RayMeshIntersector(r.mesh, order="random"), QueryInputError, ["order", "morton"]),
])
def test_malformed_arrays_raise_one_line_naming_the_argument(sphere, call, error, words):
    with pytest.raises(error) as info:
        call(RayMeshIntersector(sphere))
    assert isinstance(info.value, ValueError) and "\n" not in str(info.value)
    if error is QueryTypeError:
        assert isinstance(info.value, TypeError)
    for word in words:
        assert word in str(info.value)


def test_empty_batches_answer_empty(sphere):
    ours = RayMeshIntersector(sphere)
    assert ours.intersects_first(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    loc, ray, tri = ours.intersects_location([], [])
    assert loc.shape == (0, 3) and ray.shape == tri.shape == (0,)
    assert ours.contains_points(np.zeros((0, 3))).shape == (0,)


def test_rays_with_many_hits_take_the_exact_path_and_keep_distance_order():
    """More hits per ray than the one-walk kernel's slot (engine.query.intersector.SLOT): a stack of
    boxes crossed by every ray; the same hits as trimesh, the nearest ones under max_hits."""
    boxes = [trimesh.creation.box(extents=(1, 1, 0.5)).apply_translation([0, 0, z]) for z in range(12)]
    stack = trimesh.util.concatenate(boxes)
    rng = np.random.default_rng(13)
    origins = np.column_stack([rng.uniform(-0.4, 0.4, (300, 2)), np.full(300, -3.0)])
    directions = np.column_stack([rng.uniform(-0.01, 0.01, (300, 2)), np.ones(300)])
    origins[::3, 2] = 20.0  # every third ray from above, some mixed in with few hits
    directions[::3, 2] = -1.0
    directions[1::3] = [1, 0, 0]  # sideways: misses or crosses one box
    ours = RayMeshIntersector(stack)
    locations, index_ray, index_tri = ours.intersects_location(origins, directions, max_hits=None)
    counts = np.bincount(index_ray, minlength=300)
    assert counts.max() == 24
    their_loc, their_ray, _ = EmbreeIntersector(stack).intersects_location(origins, directions)
    assert np.array_equal(counts, np.bincount(their_ray, minlength=300))
    key = np.lexsort((np.linalg.norm(their_loc - origins[their_ray], axis=1), their_ray))
    np.testing.assert_allclose(locations, their_loc[key], atol=1e-6 * stack.scale)
    near, near_ray, _ = ours.intersects_location(origins, directions, max_hits=10)
    assert np.bincount(near_ray, minlength=300).max() == 10
    first10 = np.concatenate([np.flatnonzero(index_ray == r)[:10] for r in range(300)])
    np.testing.assert_array_equal(near, locations[first10])


# -- found by a fuzz against trimesh's backends (session 38) -------------------------------------
@pytest.mark.parametrize("stray", [1e7, -1e7, 1e39, np.nan])
def test_a_vertex_no_face_uses_does_not_move_the_frame(stray):
    """trimesh's bounds count only the vertices faces use; a stray one 1e7 away shrank the
    sphere below float32's resolution in the local frame (one hit, off the surface; the centre
    read as outside), and a NaN or 1e39 one was an error."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    mesh = trimesh.Trimesh(np.vstack([sphere.vertices, [[stray] * 3]]), sphere.faces, process=False)
    ours = RayMeshIntersector(mesh)
    locations, index_ray, index_tri = ours.intersects_location([[0.0, 0.0, -5.0]], [[0.0, 0.0, 1.0]])
    assert len(locations) == 2
    np.testing.assert_allclose(np.abs(locations[:, 2]), 1.0, atol=1e-3)  # the sphere's facets at the poles
    assert ours.contains_points([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]).tolist() == [True, False]


@pytest.mark.parametrize("distance", [3.0, 30.0, 100.0, 1000.0])
def test_a_ray_through_an_edge_crosses_once_from_afar(distance):
    """A ray at the sphere's centre through the middle of each edge crosses the surface twice;
    from 30 or more sizes away the two triangles of the edge reported t a few float32 units
    apart, more than the fixed merge gap: three crossings (2-12% of the edges)."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    middle = mesh.vertices[mesh.edges_unique].mean(axis=1)
    unit = middle / np.linalg.norm(middle, axis=1, keepdims=True)
    index_tri, index_ray = RayMeshIntersector(mesh).intersects_id(middle + distance * unit, -unit)
    assert np.bincount(index_ray, minlength=len(middle)).tolist() == [2] * len(middle)


def test_bad_ray_warnings_name_the_callers_line_each_time():
    """The warning named a line in engine/core/threads.py (a decorator), so Python's default
    filter (once per location) hid it from every later call."""
    ours = RayMeshIntersector(trimesh.creation.icosphere())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        ours.intersects_first([[0.0, 0.0, -5.0]], [[0.0, 0.0, 0.0]])
        ours.intersects_id([[0.0, 0.0, -5.0]], [[0.0, 0.0, 0.0]])
    assert [w.category for w in caught] == [BadRayWarning, BadRayWarning]
    assert {w.filename for w in caught} == {__file__}


@pytest.mark.parametrize("gap_of_diagonal", [0.6, 0.8])
def test_hits_closer_than_trimeshs_step_are_one_crossing(gap_of_diagonal):
    """trimesh steps 1e-6 of ``mesh.scale`` (its box's diagonal) past each hit, so two surfaces
    closer than that along a ray are one crossing. The merge gap was 1e-6 of the largest extent
    instead: on a flat mesh (diagonal sqrt(2) x its largest extent) two squares 0.8e-6 x diagonal
    apart were two crossings for packetrt and one for trimesh."""
    square = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    top = square.faces[np.isclose(square.triangles_center[:, 2], 0.5)]
    diagonal = np.sqrt(2.0)  # the two squares' box: 1 x 1 x ~0
    lift = gap_of_diagonal * 1e-6 * diagonal
    vertices = np.concatenate([square.vertices, square.vertices + [0.0, 0.0, lift]])
    mesh = trimesh.Trimesh(vertices, np.concatenate([top, top + len(square.vertices)]), process=False)
    assert np.isclose(mesh.scale, diagonal)
    # Near the squares: the relative part of the merge (2^-21 of t) stays below the gap.
    origins = np.array([[0.1, 0.2, 0.8], [-0.3, 0.1, 0.8], [0.2, -0.2, 0.2]])
    directions = np.array([[0.0, 0.0, -1.0], [0.01, 0.0, -1.0], [0.0, 0.01, 1.0]])
    ours = RayMeshIntersector(mesh).intersects_id(origins, directions)
    theirs = EmbreeIntersector(mesh).intersects_id(origins, directions)
    assert np.bincount(ours[1], minlength=3).tolist() == np.bincount(theirs[1], minlength=3).tolist() == [1, 1, 1]


@pytest.mark.parametrize("open_side", range(6))
def test_contains_on_an_open_box_follows_trimeshs_free_space_rule(open_side):
    """A box with one side missing: where a point's two casts disagree and one of them meets no
    surface (it leaves through the hole), trimesh calls the point outside. packetrt went on to
    other directions and their vote, and called 25-30% of the points differently."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    outward = np.eye(3)[open_side // 2] * (1.0 if open_side % 2 else -1.0)
    mesh = trimesh.Trimesh(box.vertices, box.faces[~np.isclose(box.face_normals @ outward, 1.0)], process=False)
    points = np.random.default_rng(open_side).uniform(*mesh.bounds, size=(2000, 3))
    ours = RayMeshIntersector(mesh).contains_points(points)
    assert np.array_equal(ours, EmbreeIntersector(mesh).contains_points(points))
    assert 0.3 < ours.mean() < 0.9


@pytest.mark.parametrize("distance", [1.0, 30.0, 100.0])
def test_a_thin_plate_is_two_crossings_from_afar(distance):
    """A plate 1e-5 thick (7e-6 of mesh.scale, seven times trimesh's step) seen from 30 sizes
    away: the relative merge (2^-21 of t), meant for the two triangles of one edge, joined its two
    faces into one crossing, where Embree and exact geometry give two."""
    mesh = trimesh.creation.box(extents=(1.0, 1.0, 1e-5))
    origins = np.array([[0.1, 0.2, distance], [-0.3, 0.25, -distance]])
    directions = np.array([[0.0, 0.0, -1.0], [0.001, 0.0, 1.0]])
    index_tri, index_ray, locations = RayMeshIntersector(mesh).intersects_id(origins, directions,
                                                                             return_locations=True)
    assert np.bincount(index_ray, minlength=2).tolist() == [2, 2]
    np.testing.assert_allclose(np.sort(locations[index_ray == 0, 2]), [-5e-6, 5e-6], atol=1e-9)


@pytest.mark.parametrize("shells", [129, 130])
def test_contains_inside_more_shells_than_a_line_can_sort(shells):
    """Lines through points inside 129+ nested spheres cross more than CAP (256) surfaces:
    each such line gave (0, 0) crossings, so every point was outside whatever its parity."""
    mesh = trimesh.util.concatenate([trimesh.creation.icosphere(1, radius=1.0 + 0.05 * i) for i in range(shells)])
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [1.02, 0.0, 0.0]])
    enclosing = np.array([shells, shells, shells - 1])  # the innermost icosphere's inradius is about 0.98
    assert RayMeshIntersector(mesh).contains_points(points).tolist() == (enclosing % 2 == 1).tolist()


@pytest.mark.parametrize("size", [1e-100, 1e-150])
def test_locations_on_a_vanishingly_small_mesh(size):
    """The float64 plane distance scales as the mesh's size cubed: it underflowed to 0 for a
    mesh 1e-120 across, and the location came back as the ray's origin."""
    mesh = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]) * size, np.array([[0, 1, 2]]), process=False)
    locations, index_ray, index_tri = RayMeshIntersector(mesh).intersects_location(
        np.array([[0.2, 0.2, -1.0]]) * size, np.array([[0.0, 0.0, 1.0]]))
    assert index_tri.tolist() == [0]
    np.testing.assert_allclose(locations / size, [[0.2, 0.2, 0.0]], atol=1e-12)
