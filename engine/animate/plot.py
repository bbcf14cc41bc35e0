"""Frame time along an animation path, stacked by phase (scene, accel, trace, shade)."""
from __future__ import annotations

from engine.core.atomic import replacing

PHASES = ("scene", "accel", "trace", "shade")
COLOURS = {"scene": "#8c8c8c", "accel": "#d62728", "trace": "#1f77b4", "shade": "#ff7f0e"}


def plot_path(records: list, path, title: str) -> None:
    """Draw the frame records' phase seconds (ms) against scene time as stacked areas, frames
    where the BVH was rebuilt marked on the axis; PNG to ``path`` (temporary file + rename)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = sorted(records, key=lambda r: r["index"])
    times = [r["time"] for r in records]
    stacks = [[1000 * r["seconds"][p] for r in records] for p in PHASES]
    fig, ax = plt.subplots(figsize=(9, 4))
    if len(records) > 1:
        ax.stackplot(times, *stacks, labels=PHASES, colors=[COLOURS[p] for p in PHASES], alpha=0.85)
    else:
        bottom = 0.0
        for phase, stack in zip(PHASES, stacks):
            ax.bar(times, stack, bottom=bottom, label=phase, color=COLOURS[phase], width=0.1)
            bottom += stack[0]
    rebuilt = [r["time"] for r in records[1:] if r["accel"]["policy"] == "rebuild"]
    if rebuilt and len(rebuilt) < len(records) - 1:
        ax.plot(rebuilt, [0] * len(rebuilt), "|", color="black", markersize=12, label="rebuild")
    ax.set_xlabel("scene time (s)")
    ax.set_ylabel("frame time (ms)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_ylim(bottom=0)
    with replacing(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
