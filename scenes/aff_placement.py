"""Placing an ``.aff`` scene's moving geometry in bulk, once per frame.

BART Robots has 1,410 blocks under animated transforms and BART Museum 1,024 animated
triangles; placed one by one (a matrix product, an inverse and a renormalisation each) they took
85 ms and 29 ms a frame. Here every moving row is gathered once, up front, into flat arrays
with the transform node it hangs from, and a frame is one parallel numba pass over them (each
row by its node's matrix and inverse transpose); ``tpa`` triangles with the same key times are
blended together first. Rows come out in scene order: the moving blocks in the walk's order, then the
``tpa`` triangles.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .aff import _face_normals


def _inverse(a: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(a)


@njit(cache=True, parallel=True)
def _place_rows(corners, normals, node, a, b, inverse, with_normals, out_corners, out_normals):
    """Row r's three corners (f64[R,3,3]) by its node's matrix: a[n] @ c + b[n]; its normals by
    the inverse transpose, unit length (zero stays zero) when ``with_normals``."""
    for r in prange(corners.shape[0]):
        n = node[r]
        for c in range(3):
            for i in range(3):
                out_corners[r, c, i] = (a[n, i, 0] * corners[r, c, 0] + a[n, i, 1] * corners[r, c, 1]
                                        + a[n, i, 2] * corners[r, c, 2] + b[n, i])
            if with_normals:
                length2 = 0.0
                for k in range(3):
                    v = (normals[r, c, 0] * inverse[n, 0, k] + normals[r, c, 1] * inverse[n, 1, k]
                         + normals[r, c, 2] * inverse[n, 2, k])
                    out_normals[r, c, k] = v
                    length2 += v * v
                length = np.sqrt(length2)
                for k in range(3):
                    out_normals[r, c, k] = out_normals[r, c, k] / length if length > 0 else 0.0


#: The corner order of a triangle placed by a mirroring transform (determinant < 0): corners 1
#: and 2 swapped, so that its front face -- the winding's, which decides entering and leaving a
#: glass surface -- still faces where the file's did (a mirrored glass sphere refracted as if
#: turned inside out). Normals and texture coordinates follow their corners.
MIRRORED = [0, 2, 1]


class MovingRows:
    """The rows of a scene that move: blocks under animated transforms and ``tpa`` triangles.

    loader: a walked ``scenes.aff.Loader``; moving: bool per loader instance (placed per frame);
    has_normals, has_uvs: whether the scene's triangle arrays carry normals / uvs at all.
    ``blocks``: (instance index, first row, end row) of each moving block in ``place``'s output.
    """

    def __init__(self, loader, moving: list, has_normals: bool, has_uvs: bool):
        self.has_normals, self.has_uvs = has_normals, has_uvs
        chosen = [(k, node, g, m) for k, ((node, g, m), move) in enumerate(zip(loader.instances, moving)) if move]
        self.blocks, start = [], 0
        for k, _, g, _ in chosen:
            self.blocks.append((k, start, start + len(g.corners)))
            start += len(g.corners)
        self.n_block_rows = start
        # tpa triangles, grouped by their key times (blended together), in file order.
        tpa = loader.animated_tris
        groups: dict = {}
        for i, (_, triangle, _) in enumerate(tpa):
            groups.setdefault(triangle.times.tobytes(), []).append(i)
        self.tpa_groups = [(tpa[rows[0]][1].times, np.array(rows),
                            np.stack([tpa[i][1].corners for i in rows]), np.stack([tpa[i][1].normals for i in rows]))
                           for rows in groups.values()]
        self.n_rows = self.n_block_rows + len(tpa)
        # What ``place`` reads and writes, made once, for every moving row: the blocks' rows,
        # then the tpa rows (their corners and normals blended into the tail per frame), and the
        # placed rows. A frame that allocated its 2 x 4.5 MB of output afresh (BART Robots,
        # 62,490 moving rows) spent 5.1 of the pass's 6 ms faulting those pages in.
        n_tpa = len(tpa)
        self._corners_in = np.concatenate([g.corners for _, _, g, _ in chosen] + [np.zeros((n_tpa, 3, 3))])
        self._normals_in = np.concatenate([g.normals if g.normals is not None else np.zeros_like(g.corners)
                                           for _, _, g, _ in chosen] + [np.zeros((n_tpa, 3, 3))])
        self.all_node = np.concatenate([np.full(len(g.corners), node, np.int64) for _, node, g, _ in chosen]
                                       + [np.array([node for node, _, _ in tpa], np.int64)])
        # Rows whose block has no normals get their geometric normal (tpa triangles have theirs).
        self.all_given = np.concatenate([np.full(len(g.corners), g.normals is not None) for _, _, g, _ in chosen]
                                        + [np.ones(n_tpa, bool)])
        self.every_normal_given = bool(self.all_given.all())
        self.all_material = np.concatenate([np.full(len(g.corners), m, np.int32) for _, _, g, m in chosen]
                                           + [np.array([m for _, _, m in tpa], np.int32)])
        self.all_uvs = np.concatenate([g.uvs if g.uvs is not None else np.zeros((len(g.corners), 3, 2))
                                       for _, _, g, _ in chosen] + [np.zeros((n_tpa, 3, 2))]) if has_uvs else None
        self.used_nodes = np.unique(self.all_node)
        self._placed = np.empty_like(self._corners_in)
        self._placed_normals = np.empty_like(self._corners_in)

    def _tpa_at(self, time: float):
        """(corners f64[P,3,3], normals f64[P,3,3]) of the tpa triangles at ``time``, unplaced:
        each blended linearly between its bracketing keys (held at the end keys)."""
        p = self.n_rows - self.n_block_rows
        corners, normals = np.empty((p, 3, 3)), np.empty((p, 3, 3))
        for times, rows, c, n in self.tpa_groups:
            if time <= times[0] or len(times) == 1:
                corners[rows], normals[rows] = c[:, 0], n[:, 0]
            elif time >= times[-1]:
                corners[rows], normals[rows] = c[:, -1], n[:, -1]
            else:
                k = int(np.searchsorted(times, time, side="right")) - 1
                w = (time - times[k]) / (times[k + 1] - times[k])
                corners[rows] = (1 - w) * c[:, k] + w * c[:, k + 1]
                normals[rows] = (1 - w) * n[:, k] + w * n[:, k + 1]
        return corners, normals

    def place(self, world: list, time: float):
        """(corners f64[R,3,3], normals f64[R,3,3] | None, uvs f64[R,3,2] | None, material
        i32[R]) of every moving row at ``time``; ``world``: the loader's f64[4,4] per transform
        node at that time. Rows without normals of their own get their geometric normal.
        The arrays are this object's own, rewritten by the next call: copy what you keep."""
        matrices = np.stack(world)
        a, b = matrices[:, :3, :3], matrices[:, :3, 3]
        inverse = np.zeros_like(a)
        if self.has_normals and self.used_nodes.size:
            try:
                inverse[self.used_nodes] = np.linalg.inv(a[self.used_nodes])
            except np.linalg.LinAlgError:     # a degenerate scale somewhere: one by one
                inverse[self.used_nodes] = [_inverse(a[n]) for n in self.used_nodes]
        tail = self.n_block_rows
        self._corners_in[tail:], self._normals_in[tail:] = self._tpa_at(time)
        # corner @ A^T + b and normal @ A^-1, row by row with the row's own node.
        placed, normals = self._placed, self._placed_normals
        _place_rows(self._corners_in, self._normals_in, self.all_node, np.ascontiguousarray(a),
                    np.ascontiguousarray(b), inverse, self.has_normals, placed, normals)
        uvs = self.all_uvs
        flipped = (np.linalg.det(a) < 0)[self.all_node]  # rows placed by a mirroring transform
        if flipped.any():
            placed[flipped] = placed[flipped][:, MIRRORED]
            if self.has_normals:
                normals[flipped] = normals[flipped][:, MIRRORED]
            if uvs is not None:
                uvs = uvs.copy()
                uvs[flipped] = uvs[flipped][:, MIRRORED]
        if not self.has_normals:
            normals = None
        elif not self.every_normal_given:
            normals[~self.all_given] = _face_normals(placed[~self.all_given])
        return placed, normals, uvs, self.all_material


@njit(cache=True, parallel=True)
def write_triangle_rows(rows, corners, normals, uvs, material, origin, limit, v0, e1, e2, ng, v1, v2,
                        out_material, out_normals, out_uvs):
    """Rows ``rows`` (i64[R]) of a scene's triangle arrays from placed rows, as
    ``engine.core.scene.make_triangles`` computes them, operation for operation (corners rounded
    to float32 after ``origin`` is taken off, edges in float32, the normal's cross product and
    length in float64): corners f64[R,3,3], normals f64[R,3,3] (or 0 rows: none), uvs f64[R,3,2]
    (or 0 rows), material i32[R]. Returns False, writing nothing more, when a corner is not
    finite or beyond ``limit``: the caller then goes through make_triangles, which says why."""
    n = rows.shape[0]
    for r in range(n):
        for c in range(3):
            for a in range(3):
                x = corners[r, c, a] - origin[a]
                if not np.isfinite(x) or abs(x) > limit:
                    return False
    for r in prange(n):
        row = rows[r]
        for a in range(3):
            p0 = np.float32(corners[r, 0, a] - origin[a])
            p1 = np.float32(corners[r, 1, a] - origin[a])
            p2 = np.float32(corners[r, 2, a] - origin[a])
            v0[row, a], v1[row, a], v2[row, a] = p0, p1, p2
            e1[row, a] = p1 - p0
            e2[row, a] = p2 - p0
        a0, a1, a2 = np.float64(e1[row, 0]), np.float64(e1[row, 1]), np.float64(e1[row, 2])
        b0, b1, b2 = np.float64(e2[row, 0]), np.float64(e2[row, 1]), np.float64(e2[row, 2])
        c0 = a1 * b2 - a2 * b1
        c1 = a2 * b0 - a0 * b2
        c2 = a0 * b1 - a1 * b0
        length = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if length > 0:
            ng[row, 0], ng[row, 1], ng[row, 2] = np.float32(c0 / length), np.float32(c1 / length), np.float32(c2 / length)
        else:
            ng[row, 0], ng[row, 1], ng[row, 2] = np.float32(0.0), np.float32(0.0), np.float32(0.0)
        out_material[row] = material[r]
        if normals.shape[0]:
            for c in range(3):
                for a in range(3):
                    x = np.float32(normals[r, c, a])
                    out_normals[row, c, a] = x if np.isfinite(x) else np.float32(0.0)
        if uvs.shape[0]:
            for c in range(3):
                for a in range(2):
                    out_uvs[row, c, a] = np.float32(uvs[r, c, a])
    return True
