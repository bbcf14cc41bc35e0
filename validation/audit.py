"""Audit a render: check every ray batch the Whitted loop casts against one or two oracles.

``audit(scene, config, oracle)`` renders once with an observer that sends each batch (primary,
shadow, reflection, refraction; every depth) to the oracle and classifies every live ray with
``validation.compare``. The report is the ``packetrt audit --json`` document.

oracle = "embree"  Embree through embreex, robust mode (``validation.oracle``); the default.
oracle = "open3d"  Open3D's RaycastingScene (``validation.open3d_oracle``).
oracle = "both"    both: our answers are checked against each, and the two oracles against each
                   other. The report keeps the one-oracle fields, combined per ray (a ray is a
                   mismatch when it mismatches either oracle, a tie when it ties with either and
                   mismatches neither), and adds ``oracles`` (one full one-oracle report per
                   oracle) and ``oracle_disagreements``: per kind, the rays where the oracles
                   disagree beyond a floating-point tie, with the first examples. Those do not
                   fail the audit; they say where the ground truth itself is unsure.
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import ConfigError
from engine.render.plugins import make_traversal
from engine.render.tracer import Tracer
from engine.core.types import RAY_KINDS, Hits, Packets, RayBatch
from engine.gpu.choose import new_renderer

from .compare import compare_hits, compare_occlusion

MISMATCHES_KEPT = 100
ORACLE_CHOICES = ("embree", "open3d", "both")


def _ray_record(rays, i):
    return {"org": rays.org[i].tolist(), "dir": rays.dir[i].tolist(), "tmin": float(rays.tmin[i]),
            "tmax": float(rays.tmax[i]), "pixel": int(rays.pixel[i])}


def _hit_record(hits, i):
    return {"prim": int(hits.prim[i]), "t": float(hits.t[i]), "u": float(hits.u[i]), "v": float(hits.v[i])}


def make_oracle(name: str, tris):
    """The oracle called ``name`` ("embree" or "open3d") over ``tris``."""
    if name == "embree":
        from .oracle import EmbreeOracle

        return EmbreeOracle(tris)
    if name == "open3d":
        from .open3d_oracle import Open3DOracle

        return Open3DOracle(tris)
    raise ConfigError(f"unknown oracle {name!r}; allowed: {', '.join(ORACLE_CHOICES)}")


class _Answers:
    """One side's answers for one batch: closest hits, and for an occlusion query the occlusion
    flags. ``record(i)`` is what a report shows for ray i."""

    def __init__(self, query, closest, occluded=None):
        self.query, self.closest, self.occluded = query, closest, occluded

    def record(self, i):
        if self.query == "intersect":
            return _hit_record(self.closest, i)
        return {"occluded": bool(self.occluded[i]), **_hit_record(self.closest, i)}


def _classify(rays, tris, a: _Answers, b: _Answers, oracle=None):
    """Side a's answers against side b's; ``oracle``: b's oracle, asked what lies behind a hit
    of b's that a tie rule would excuse (``validation.compare``)."""
    if a.query == "intersect":
        return compare_hits(rays, a.closest, b.closest, tris, again=None if oracle is None else oracle.intersect)
    return compare_occlusion(rays, a.occluded, b.occluded, tris, a.closest, b.closest,
                             again=None if oracle is None else oracle.occluded)


class _Tally:
    """Per-kind counts, the worst t error on agreeing hits, the first examples and the pixels of
    every disagreeing ray, for one pair of sides."""

    def __init__(self, bad_word="mismatches"):
        self.bad_word = bad_word
        self.by_kind = {k: {"checked": 0, "agree": 0, "ties": 0, bad_word: 0} for k in RAY_KINDS}
        self.max_abs_t_err = 0.0
        self.examples: list = []
        self.pixels: list = []
        self.tie_pixels: set = set()   # pixels of rays whose answers tie (both valid, they differ)

    def add(self, kind, rays, result, example):
        """Count ``result`` (a Comparison) for a batch; ``example(i)`` is the record of ray i."""
        row = self.by_kind[kind]
        row["checked"] += int(np.count_nonzero(rays.tmin <= rays.tmax))
        row["agree"] += int(result.agree.sum())
        row["ties"] += int(result.tie.sum())
        row[self.bad_word] += int(result.mismatch.sum())
        self.max_abs_t_err = max(self.max_abs_t_err, result.max_abs_t_err)
        bad = np.flatnonzero(result.mismatch)
        self.pixels.extend(rays.pixel[bad].tolist())
        self.tie_pixels.update(rays.pixel[np.flatnonzero(result.tie)].tolist())
        for i in bad[: max(0, MISMATCHES_KEPT - len(self.examples))]:
            self.examples.append(example(i))

    @property
    def count(self) -> int:
        return sum(r[self.bad_word] for r in self.by_kind.values())

    @property
    def checked(self) -> int:
        return sum(r["checked"] for r in self.by_kind.values())

    def agreement(self) -> float:
        checked = self.checked
        return (checked - self.count) / checked if checked else 1.0


class AuditObserver:
    """Collects per-kind counts and the first mismatches while a render runs.

    ``oracle``: one oracle (``intersect(rays) -> Hits``, ``occluded(rays) -> bool[R]``,
    ``describe()``) or a list of them; with two, the oracles are also compared with each other.
    """

    def __init__(self, scene, bvh, oracle):
        self.tris = scene.triangles
        self.bvh = bvh
        self.oracles = list(oracle) if isinstance(oracle, (list, tuple)) else [oracle]
        self.oracle = self.oracles[0]
        # The reference ``single`` traversal gives the closest hits behind our occlusion answers.
        self.reference = Tracer(bvh, self.tris, None, dict.fromkeys(RAY_KINDS, make_traversal("single")),
                                dict.fromkeys(RAY_KINDS))
        self.tallies = [_Tally() for _ in self.oracles]
        self.combined = _Tally()
        self.between = _Tally("disagreements") if len(self.oracles) == 2 else None

    # Kept for callers of the one-oracle observer.
    @property
    def by_kind(self):
        return self.combined.by_kind

    @property
    def mismatches(self):
        return self.combined.examples

    @property
    def mismatch_pixels(self):
        return self.combined.pixels

    @property
    def tie_pixels(self) -> set:
        """Pixels (y * width + x) with a ray whose answer ties the oracle's."""
        return self.combined.tie_pixels

    def __call__(self, kind, query, rays, packets, answer):
        if query == "intersect":
            ours = _Answers(query, answer)
            theirs = [_Answers(query, o.intersect(rays)) for o in self.oracles]
        else:
            closest_ours = self.reference.trace(kind, "intersect", rays, packets)
            ours = _Answers(query, closest_ours, answer)
            theirs = [_Answers(query, o.intersect(rays), o.occluded(rays)) for o in self.oracles]
        results = [_classify(rays, self.tris, ours, t, o) for t, o in zip(theirs, self.oracles)]
        for oracle, tally, side, result in zip(self.oracles, self.tallies, theirs, results):
            tally.add(kind, rays, result, lambda i, side=side: {
                "kind": kind, "query": query, "ray": _ray_record(rays, i),
                "ours": ours.record(i), "oracle": side.record(i)})
        self.combined.add(kind, rays, _combine(results), lambda i: self._combined_example(
            kind, query, rays, i, ours, theirs, results))
        if self.between is not None:
            a, b = (o.name for o in self.oracles)
            self.between.add(kind, rays, _classify(rays, self.tris, theirs[0], theirs[1], self.oracles[1]), lambda i: {
                "kind": kind, "query": query, "ray": _ray_record(rays, i),
                a: theirs[0].record(i), b: theirs[1].record(i), "ours": ours.record(i)})

    def _combined_example(self, kind, query, rays, i, ours, theirs, results):
        if len(self.oracles) == 1:
            return {"kind": kind, "query": query, "ray": _ray_record(rays, i), "ours": ours.record(i),
                    "oracle": theirs[0].record(i)}
        return {"kind": kind, "query": query, "ray": _ray_record(rays, i), "ours": ours.record(i),
                "oracle": {o.name: t.record(i) for o, t in zip(self.oracles, theirs)},
                "mismatch_against": [o.name for o, r in zip(self.oracles, results) if r.mismatch[i]]}

    @staticmethod
    def _one_report(tally, description) -> dict:
        return {"oracle": description, "rays_checked": tally.checked, "by_kind": tally.by_kind,
                "agreement": tally.agreement(), "max_abs_t_err": tally.max_abs_t_err,
                "mismatch_count": tally.count, "mismatches": tally.examples}

    def report(self) -> dict:
        descriptions = [o.describe() for o in self.oracles]
        if len(self.oracles) == 1:
            return self._one_report(self.combined, descriptions[0])
        names = [d["name"] for d in descriptions]
        report = self._one_report(self.combined, {
            "name": "+".join(names),
            "version": "; ".join(f"{d['name']} {d['version']}" for d in descriptions),
            "robust": all(d.get("robust", False) for d in descriptions)})
        report["max_abs_t_err"] = max(t.max_abs_t_err for t in self.tallies)
        report["oracles"] = {d["name"]: self._one_report(t, d) for d, t in zip(descriptions, self.tallies)}
        if self.between is not None:
            report["oracle_disagreements"] = {
                "between": names, "rays_checked": self.between.checked, "by_kind": self.between.by_kind,
                "count": self.between.count, "max_abs_t_err": self.between.max_abs_t_err,
                "examples": self.between.examples}
        return report


def _combine(results):
    """One Comparison from several for the same rays: mismatch if any mismatches, else tie if any
    ties, else agree."""
    if len(results) == 1:
        return results[0]
    mismatch = np.logical_or.reduce([r.mismatch for r in results])
    tie = np.logical_or.reduce([r.tie for r in results]) & ~mismatch
    agree = np.logical_and.reduce([r.agree for r in results]) & ~mismatch & ~tie
    return type(results[0])(agree, tie, mismatch, max(r.max_abs_t_err for r in results))


def audit(scene, config, oracle: str = "embree") -> tuple[dict, object, list]:
    """(report, RenderResult, mismatching pixels) for one render of ``scene`` with ``config``.

    ``oracle``: "embree" (default), "open3d" or "both" (see the module doc).
    """
    if oracle not in ORACLE_CHOICES:
        raise ConfigError(f"unknown oracle {oracle!r}; allowed: {', '.join(ORACLE_CHOICES)}")
    names = ["embree", "open3d"] if oracle == "both" else [oracle]
    # Build the oracles first: a missing Open3D is reported before any rendering.
    oracles = [make_oracle(name, scene.triangles) for name in names]
    renderer = new_renderer(scene, config)  # the GPU frame for device = "cuda": same rays, same checks
    observer = AuditObserver(scene, renderer.bvh, oracles)
    renderer.observer = observer
    result = renderer.render()
    report = observer.report()
    report["scene"] = scene.name
    report["triangles"] = scene.n_triangles
    report["config"] = config.to_dict()
    return report, result, observer.mismatch_pixels


class PixelBand:
    """Observer that passes on only the rays whose ancestral pixel lies in [lo, hi) (one band
    of a tiled audit), each batch narrowed to them as one packet."""

    def __init__(self, observer, lo: int, hi: int):
        self.observer, self.lo, self.hi = observer, lo, hi

    def __call__(self, kind, query, rays, packets, answer):
        keep = np.flatnonzero((rays.pixel >= self.lo) & (rays.pixel < self.hi))
        if keep.size == 0:
            return
        narrowed = RayBatch(*(np.ascontiguousarray(a[keep]) for a in rays[:7]), rays.kind)
        one = Packets(np.array([0, keep.size], np.int32), 2, 1, 1)
        if query == "intersect":
            answer = Hits(*(np.ascontiguousarray(a[keep]) for a in answer))
        else:
            answer = np.ascontiguousarray(np.asarray(answer)[keep])
        self.observer(kind, query, narrowed, one, answer)


def audit_band(scene, config, lo: int, hi: int, oracle: str = "embree") -> tuple[dict, object, list]:
    """``audit`` of the rays of pixels [lo, hi) only (the whole frame is rendered; only this
    band's rays are checked): one task of a tiled audit (``merge_reports`` joins them)."""
    if oracle not in ("embree", "open3d"):
        raise ConfigError(f"a tiled audit checks against one oracle (embree or open3d), got {oracle!r}")
    oracles = [make_oracle(oracle, scene.triangles)]
    renderer = new_renderer(scene, config)
    observer = AuditObserver(scene, renderer.bvh, oracles)
    renderer.observer = PixelBand(observer, lo, hi)
    result = renderer.render()
    report = observer.report()
    report.update(scene=scene.name, triangles=scene.n_triangles, config=config.to_dict(), band=[lo, hi])
    return report, result, observer.mismatch_pixels


def merge_reports(reports: list) -> dict:
    """One audit report from the reports of disjoint pixel bands (``audit_band``): counts
    summed per kind, the worst t error, the first examples, the agreement over everything."""
    merged = {key: value for key, value in reports[0].items() if key != "band"}
    by_kind = {kind: dict.fromkeys(reports[0]["by_kind"][kind], 0) for kind in reports[0]["by_kind"]}
    for report in reports:
        for kind, row in report["by_kind"].items():
            for key, value in row.items():
                by_kind[kind][key] += value
    checked = sum(r["rays_checked"] for r in reports)
    mismatches = sum(r["mismatch_count"] for r in reports)
    merged.update(by_kind=by_kind, rays_checked=checked, mismatch_count=mismatches,
                  agreement=(checked - mismatches) / checked if checked else 1.0,
                  max_abs_t_err=max(r["max_abs_t_err"] for r in reports),
                  mismatches=[m for r in reports for m in r["mismatches"]][:MISMATCHES_KEPT],
                  bands=[r["band"] for r in reports])
    return merged
