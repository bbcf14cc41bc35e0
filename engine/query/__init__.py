"""Mesh queries with trimesh's semantics: the machinery under ``engine.RayMeshIntersector``.

- ``frame``: the mesh re-expressed about its own centre and scale (float32 for the kernels,
  float64 kept for answers); each ray is moved into that frame as it is walked, bad rays marked.
- ``order``: optional ray order, sorted in numba by direction octant and a Morton code of the origin.
- ``wide``: the 8-wide BVH collapsed from the binary one (children's boxes side by side).
- ``leaf_blocks``: the leaves' triangles in blocks of four, each corner component of the four
  side by side, as the four-triangle test loads them, and the four triangle indices.
- ``walk``: the one inlined per-ray walk over it (closest, any, or every hit).
- ``hits``: parallel kernels over sorted rays: first hit, any hit, all hits (count, then fill).
- ``locations``: float64 hit points from the triangle's plane (or barycentrics).
- ``contains``: inside/outside by counting crossings along rays, no hit lists materialised.
- ``intersector``: ``RayMeshIntersector``, trimesh's ``mesh.ray`` interface over the above.
- ``errors``: the user-mistake exceptions (ValueError / TypeError subclasses).

Imports ``engine.core`` only (rank 1 in tests/test_layers.py).
"""
