"""What every yardstick of the benchmark (Embree, Open3D) shares: replaying the recorded batches
once per batch set and keeping the timings and answers until the batches change."""
from __future__ import annotations


def replay_once(yardstick, renderer, recorder, repeat: int, timed_replays) -> tuple:
    """(``repeat`` dicts {kind: seconds}, last answers) of ``yardstick`` (which has ``tracer(renderer)``
    and the attributes ``digest``, ``runs``, ``answers``) on exactly the recorded batches, timed by
    ``timed_replays(batches, tracer, repeat)``. A batch set seen before is not traced again. One
    untimed query comes first: thread pools, first touches and lazily built scenes stay out of it."""
    digest = recorder.digest(renderer.tris)
    if digest != yardstick.digest:
        tracer = yardstick.tracer(renderer)
        if recorder.batches:
            kind, query, rays, packets = recorder.batches[0]
            tracer.trace(kind, query, rays, packets)
        yardstick.digest, yardstick.runs, yardstick.answers = None, None, None  # one batch set alive at a time
        yardstick.runs, yardstick.answers = timed_replays(recorder.batches, tracer, repeat)
        yardstick.digest = digest
    return yardstick.runs, yardstick.answers
