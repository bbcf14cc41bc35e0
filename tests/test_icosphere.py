"""The default scene's spheres (``scenes.whitted.icosphere``): a closed, outward-facing icosphere
on the sphere, the vertices of trimesh's icosphere, and no trimesh import to render the scene."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from scenes.whitted import icosphere


@pytest.mark.parametrize("subdivisions", [0, 1, 2, 3])
def test_icosphere_is_a_closed_outward_sphere(subdivisions):
    vertices, faces = icosphere(subdivisions, 1.7)
    assert vertices.shape == (10 * 4 ** subdivisions + 2, 3)
    assert faces.shape == (20 * 4 ** subdivisions, 3) and faces.dtype == np.int64
    np.testing.assert_allclose(np.linalg.norm(vertices, axis=1), 1.7, rtol=1e-12)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (np.einsum("ij,ij->i", normals, corners.mean(axis=1)) > 0).all()  # every face faces out


@pytest.mark.parametrize("subdivisions", [1, 3])
def test_icosphere_has_trimesh_s_vertices(subdivisions):
    """The same points as trimesh's icosphere (which the default scene used until session 25), in
    another order: the default scene's image did not change (compared byte for byte then)."""
    ours, _ = icosphere(subdivisions, 1.0)
    theirs = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0).vertices

    def rows(a):
        return a[np.lexsort(np.round(a, 9).T[::-1])]
    np.testing.assert_allclose(rows(ours), rows(theirs), atol=1e-12)


def test_the_default_scene_loads_without_trimesh():
    code = ("import sys; from scenes.catalog import load_named; load_named('whitted'); "
            "assert 'trimesh' not in sys.modules, 'trimesh imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])
