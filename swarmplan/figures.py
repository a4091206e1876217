"""Figures of a run, from its result dictionary: the paths (the paper's Fig. 3/8), the
coverage / engaged curves (Fig. 4/5, 9/10) and the target funnel (the per-target account of
``sim_gateway.target_account``), written as PNG with matplotlib (no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402


def save(fig, path: Path, dpi: int = 120) -> Path:
    """Lay out, write and close ``fig``; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_paths(result: dict, path: Path) -> Path:
    """UAV tracks, starts, engaged targets and threat circles over the mission area."""
    width, height = result["area_km"]
    fig, ax = plt.subplots(figsize=(7, 7))
    for threat in result["threats"]:
        ax.add_patch(
            Circle(
                (threat["x_km"], threat["y_km"]),
                threat["radius_km"],
                fill=False,
                color="black",
                lw=1.5,
            )
        )
    colours = plt.get_cmap("tab20")
    for i, uav in enumerate(result["uavs"]):
        track = uav["track_km"]
        if not track:
            continue
        xs, ys = zip(*track, strict=True)
        ax.plot(xs, ys, lw=0.9, color=colours(i % 20), label=f"UAV {uav['id']}")
        ax.plot(*uav["start_km"], "o", color="tab:blue", ms=5)
    targets = {t["id"]: t for t in result["targets"]}
    ax.plot([t["x_km"] for t in targets.values()], [t["y_km"] for t in targets.values()], "^",
            color="black", ms=5, label="target (prior position)")  # fmt: skip
    for e in result["engagements"]:
        uav = result["uavs"][e["uav"]]
        x, y = uav["track_km"][min(e["step"], len(uav["track_km"]) - 1)]
        ax.plot(x, y, "h", color="red", ms=10)
        ax.annotate(
            str(e["target_id"]),
            (x, y),
            textcoords="offset points",
            xytext=(5, 5),
            fontsize=8,
            color="red",
        )
    ax.set_xlim(0, width)
    ax.set_ylim(0, height)
    ax.set_aspect("equal")
    ax.set_xlabel("x (km, east)")
    ax.set_ylabel("y (km, north)")
    ax.set_title(
        f"{result['scenario']} / {result['algorithm']} / seed {result['seed']}: coverage "
        f"{100 * result['coverage']:.1f}%, engaged {result['engaged_count']}"
    )
    if len(result["uavs"]) <= 10:
        ax.legend(loc="upper right", fontsize=7)
    return save(fig, path)


def plot_curves(result: dict, path: Path) -> Path:
    """Coverage and targets engaged over the decision steps."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.plot([100 * c for c in result["coverage_curve"]], color="tab:blue")
    top.set_ylabel("coverage J_E (%)")
    top.grid(alpha=0.3)
    bottom.step(
        range(len(result["engaged_curve"])), result["engaged_curve"], where="post", color="tab:red"
    )
    bottom.set_ylabel("targets engaged")
    bottom.set_xlabel("decision step")
    bottom.grid(alpha=0.3)
    fig.suptitle(f"{result['scenario']} / {result['algorithm']} / seed {result['seed']}")
    return save(fig, path)


#: The funnel's stages (``sim_gateway.target_account.STAGES``) as the figure names them.
FUNNEL_LABELS = {
    "targets": "targets",
    "in_footprint": "in a\nfootprint",
    "seen": "seen\n(>= 3 steps)",
    "pursued": "pursued",
    "confirmed": "confirmed",
    "engaged": "engaged",
}
KIND_COLOURS = {
    "known_position": "tab:blue",
    "known_speed": "tab:orange",
    "known_velocity": "tab:green",
    "unknown_position": "tab:gray",
}


def draw_funnel(ax, by_kind: dict[str, dict], title: str) -> None:
    """Stacked bars, one per stage of the target funnel, split by target kind; ``by_kind`` maps
    a kind to its counts (``account["by_kind"]``, or their means over runs). Stages without a
    count (no planner facts) are left out."""
    stages = [s for s in FUNNEL_LABELS if all(c.get(s) is not None for c in by_kind.values())]
    bottom = [0.0] * len(stages)
    for kind, counts in by_kind.items():
        heights = [float(counts[s]) for s in stages]
        ax.bar(range(len(stages)), heights, bottom=bottom, color=KIND_COLOURS.get(kind),
               label=kind.replace("_", " "), width=0.7)  # fmt: skip
        bottom = [b + h for b, h in zip(bottom, heights, strict=True)]
    for x, total in enumerate(bottom):
        ax.annotate(f"{total:.3g}", (x, total), ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(stages)), [FUNNEL_LABELS[s] for s in stages], fontsize=8)
    ax.set_ylabel("targets")
    ax.set_ylim(0, max(bottom + [1.0]) * 1.15)
    ax.set_title(title, fontsize=9)
    ax.grid(axis="y", alpha=0.3)


def plot_target_funnel(result: dict, path: Path) -> Path:
    """The run's target funnel by kind: targets, in a footprint, seen, pursued, confirmed,
    engaged (``result["target_account"]``)."""
    account = result["target_account"]
    totals = account["totals"]
    conversion = "n/a" if totals["conversion"] is None else f"{totals['conversion']:.2f}"
    fig, ax = plt.subplots(figsize=(7, 4.2))
    draw_funnel(
        ax,
        account["by_kind"],
        f"{result['scenario']} / {result['algorithm']} / seed {result['seed']}: "
        f"seen {totals['seen']}, engaged {totals['engaged']}, conversion {conversion}",
    )
    ax.legend(loc="upper right", fontsize=7)
    return save(fig, path)


def write_figures(result: dict, out_dir: Path) -> list[Path]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [
        plot_paths(result, out_dir / "paths.png"),
        plot_curves(result, out_dir / "coverage.png"),
    ]
    if result.get("target_account"):
        written.append(plot_target_funnel(result, out_dir / "targets.png"))
    return written
