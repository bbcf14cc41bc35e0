"""Audit a render: check every ray batch the Whitted loop casts against the oracle.

``audit(scene, config)`` renders once with an observer that sends each batch (primary,
shadow, reflection, refraction; every depth) to Embree and classifies every live ray with
``validation.compare``. The report is the ``packetrt audit --json`` document.
"""
from __future__ import annotations

import numpy as np

from engine.bvh import build_bvh
from engine.registry import get_traversal
from engine.types import RAY_KINDS, empty_hits
from engine.whitted import WhittedRenderer

from .compare import compare_hits, compare_occlusion
from .oracle import EmbreeOracle

MISMATCHES_KEPT = 100


def _ray_record(rays, i):
    return {"org": rays.org[i].tolist(), "dir": rays.dir[i].tolist(), "tmin": float(rays.tmin[i]),
            "tmax": float(rays.tmax[i]), "pixel": int(rays.pixel[i])}


def _hit_record(hits, i):
    return {"prim": int(hits.prim[i]), "t": float(hits.t[i]), "u": float(hits.u[i]), "v": float(hits.v[i])}


class AuditObserver:
    """Collects per-kind counts and the first mismatches while a render runs."""

    def __init__(self, scene, bvh, oracle):
        self.tris = scene.triangles
        self.bvh = bvh
        self.oracle = oracle
        self.reference = get_traversal("single")
        self.by_kind = {k: {"checked": 0, "agree": 0, "ties": 0, "mismatches": 0} for k in RAY_KINDS}
        self.max_abs_t_err = 0.0
        self.mismatches: list = []
        self.mismatch_pixels: list = []

    def __call__(self, kind, query, rays, packets, answer):
        if query == "intersect":
            theirs = self.oracle.intersect(rays)
            result = compare_hits(rays, answer, theirs, self.tris)
            ours_rec, theirs_rec = (lambda i: _hit_record(answer, i)), (lambda i: _hit_record(theirs, i))
        else:
            theirs = self.oracle.occluded(rays)
            closest_ours = empty_hits(rays.org.shape[0])
            self.reference.intersect(self.bvh, self.tris, rays, packets, None, closest_ours, None)
            closest_theirs = self.oracle.intersect(rays)
            result = compare_occlusion(rays, answer, theirs, self.tris, closest_ours, closest_theirs)
            ours_rec = lambda i: {"occluded": bool(answer[i]), **_hit_record(closest_ours, i)}
            theirs_rec = lambda i: {"occluded": bool(theirs[i]), **_hit_record(closest_theirs, i)}
        row = self.by_kind[kind]
        row["checked"] += int(np.count_nonzero(rays.tmin <= rays.tmax))
        row["agree"] += int(result.agree.sum())
        row["ties"] += int(result.tie.sum())
        row["mismatches"] += int(result.mismatch.sum())
        self.max_abs_t_err = max(self.max_abs_t_err, result.max_abs_t_err)
        bad = np.flatnonzero(result.mismatch)
        self.mismatch_pixels.extend(rays.pixel[bad].tolist())
        for i in bad[: max(0, MISMATCHES_KEPT - len(self.mismatches))]:
            self.mismatches.append({"kind": kind, "query": query, "ray": _ray_record(rays, i),
                                    "ours": ours_rec(i), "oracle": theirs_rec(i)})

    def report(self) -> dict:
        checked = sum(r["checked"] for r in self.by_kind.values())
        good = sum(r["agree"] + r["ties"] for r in self.by_kind.values())
        return {"oracle": self.oracle.describe(), "rays_checked": checked,
                "by_kind": self.by_kind, "agreement": good / checked if checked else 1.0,
                "max_abs_t_err": self.max_abs_t_err,
                "mismatch_count": sum(r["mismatches"] for r in self.by_kind.values()),
                "mismatches": self.mismatches}


def audit(scene, config, oracle: str = "embree") -> tuple[dict, object, list]:
    """(report, RenderResult, mismatching pixels) for one render of ``scene`` with ``config``.

    ``oracle``: "embree" (default); "open3d" and "both" are wired by the Open3D oracle work.
    """
    if oracle != "embree":
        from engine.errors import ConfigError

        raise ConfigError(f"--oracle {oracle!r} is not available yet; allowed: embree")
    renderer = WhittedRenderer(scene, config)
    oracle = EmbreeOracle(scene.triangles)
    observer = AuditObserver(scene, renderer.bvh, oracle)
    renderer.observer = observer
    result = renderer.render()
    report = observer.report()
    report["scene"] = scene.name
    report["triangles"] = scene.n_triangles
    report["config"] = config.to_dict()
    return report, result, observer.mismatch_pixels
