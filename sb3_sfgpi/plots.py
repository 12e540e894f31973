"""The figures of ``sb3-sfgpi plot``.

* :func:`plot_returns` -- GPI return over OLS iterations, mean ± std over seeds, one line per algorithm
  (paper Fig. 4 and Fig. 7), from run directories, with horizontal reference lines (:class:`Reference`: the
  learners trained a priori for each test weight, an exact optimum);
* :func:`plot_step_metrics` -- a per-step quantity over an evaluation episode (e.g. the vehicles' or the
  pedestrians' waiting time) for GPI at several weights (paper Figs. 8-10), from a comparison file;
* :func:`plot_versus` -- GPI against the learners trained from scratch for one fixed weight, per objective
  (paper Figs. 11-15), from a comparison file;
* :func:`plot_tradeoff` -- the per-objective episode metrics of every method in one scatter plot.

A comparison file is what ``sb3-sfgpi compare`` writes (see :mod:`sb3_sfgpi.cli.compare`): one row per evaluated
method with its weights, returns, episode metrics and per-step traces (sum over agents, mean and std over
episodes).
"""

from __future__ import annotations

import itertools
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.common.weights import format_weights
from sb3_sfgpi.run_directory import RunDirectory

#: Axis labels of the summary metrics (one meaning of "w·return" everywhere: discounted, as the training curve).
METRIC_LABELS = {
    "mean_return": "w·(discounted return), mean",
    "mean_return_undiscounted": "w·(undiscounted return), mean",
    "expected_utility": "expected utility (discounted)",
    "n_policies": "|Π|",
    "ccs_size": "CCS size",
}
LABELS = {"ma-sfols": "MA-SFOLS + GPI", "random": "Random + GPI", "fixed": "fixed-weight learners"}
REFERENCE_COLORS = ("black", "tab:gray", "tab:brown")  # reference lines, apart from the algorithms' colours
BASELINE_STYLES = ("--", "-.", ":")  # the comparison's baselines (fixed-time, actuated, max-pressure): one each
TITLE_WIDTH = 60  # characters per line of a title: a 6-inch figure holds about this many


@dataclass(frozen=True)
class Reference:
    """
    A horizontal line of :func:`plot_returns`: a value the curves are measured against.

    :param label: its legend entry
    :param mean: its value
    :param std: its spread over seeds (a band; 0 for none)
    """

    label: str
    mean: float
    std: float = 0.0


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, output: Path) -> Path:
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(output, dpi=120)
    _pyplot().close(fig)
    return output


def align_runs(runs: list[dict[int, float]], complete: Sequence[bool] | None = None) -> np.ndarray:
    """
    One row per run over the union of their iterations. A run whose set is complete (OLS ended) keeps its last
    value after its last iteration; one that stopped for another reason (interrupted, a smaller ``--iterations``)
    is NaN there: it is not drawn as if it went on.

    :param runs: per run, iteration -> value
    :param complete: per run, whether its set is complete (default: all are)
    :return: shape ``(n_runs, n_iterations)``
    """
    iterations = sorted(set().union(*runs))
    complete = [True] * len(runs) if complete is None else list(complete)
    rows = []
    for run, carry in zip(runs, complete, strict=True):
        last, row = np.nan, []
        for i in iterations:
            last = run.get(i, last if carry else np.nan)
            row.append(last)
        rows.append(row)
    return np.array(rows)


def ols_ended(run_dir: RunDirectory) -> bool:
    """Whether a run's OLS ended (its last checkpoint has no next weights): its policy set is complete."""
    return run_dir.has_checkpoint() and run_dir.read_checkpoint()["next_weights"] is None


def _seeds_label(values: np.ndarray, iterations: list[int]) -> str:
    """``"3 seeds"``, or ``"3 seeds, 2 from iteration 7"`` where some runs stop before the others."""
    counts = (~np.isnan(values)).sum(axis=0)
    n = int(counts.max())
    label = f"{n} seed{'s' * (n > 1)}"
    if (counts < n).any():
        first = int(np.argmax(counts < n))
        label += f", {int(counts[first:].min())} from iteration {iterations[first]}"
    return label


def plot_returns(
    runs: Sequence[tuple[str, RunDirectory]],
    output: Path,
    metric: str = "mean_return",
    title: str | None = None,
    references: Sequence[Reference] = (),
) -> Path:
    """
    GPI's ``metric`` over iterations (each run's summary rows), mean ± std over the runs of an algorithm.

    :param runs: (algorithm, run directory) pairs
    :param output: the PNG file
    :param metric: a column of the summary (:data:`~sb3_sfgpi.run_directory.SUMMARY_FIELDS`)
    :param title: the title (default: a description of the curve)
    :param references: horizontal lines (dashed, with a band of ± their std) in the metric's units
    """
    curves: dict[str, list[dict[int, float]]] = {}
    ended: dict[str, list[bool]] = {}
    for algorithm, run_dir in runs:
        rows = run_dir.read_summary()
        curves.setdefault(algorithm, []).append(
            {int(row["iteration"]): float(row[metric]) for row in rows if row[metric] != ""}
        )
        ended.setdefault(algorithm, []).append(ols_ended(run_dir))
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for algorithm, values_by_run in sorted(curves.items()):
        values = align_runs(values_by_run, ended[algorithm])
        iterations = sorted(set().union(*values_by_run))
        mean, std = np.nanmean(values, axis=0), np.nanstd(values, axis=0)  # over the runs that got that far
        label = f"{LABELS.get(algorithm, algorithm)} ({_seeds_label(values, iterations)})"
        ax.plot(iterations, mean, marker="o", label=label)
        ax.fill_between(iterations, mean - std, mean + std, alpha=0.2)
    for reference, color in zip(references, itertools.cycle(REFERENCE_COLORS)):
        low, high = reference.mean - reference.std, reference.mean + reference.std
        line = ax.axhline(reference.mean, color=color, linestyle="--", linewidth=1.2, label=reference.label)
        if reference.std > 0:
            ax.axhspan(low, high, color=line.get_color(), alpha=0.1)
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(_pyplot().MaxNLocator(integer=True))
    ax.set_ylabel(METRIC_LABELS.get(metric, metric.replace("_", " ")))
    ax.set_title(textwrap.fill(title or "GPI over the policy set, mean over test weights and agents", TITLE_WIDTH))
    ax.grid(alpha=0.3)
    ax.legend()
    return _save(fig, output)


# --- comparison files -------------------------------------------------------------------------------------
def _weights_tag(w: Sequence[float]) -> str:
    return "-".join(f"{x:g}" for x in np.round(w, 3))


def _step_metrics(compare: dict[str, Any]) -> list[tuple[int, str, str, str]]:
    """(objective index, objective name, step-metric key, its label) for every objective with a step metric."""
    names = compare.get("objectives") or [f"objective {i}" for i in range(len(compare["step_metrics"]))]
    return [(i, names[i], key, label) for i, (key, label) in enumerate(compare["step_metrics"])]


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the last ``window`` values (fewer at the start); ``window <= 1`` returns ``values``."""
    values = np.asarray(values, dtype=np.float64)
    if window <= 1 or len(values) == 0:
        return values
    cumulative = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - window, 0)
    return (cumulative[ends] - cumulative[starts]) / (ends - starts)


def _trace(row: dict[str, Any], key: str, smooth: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    traces = row["traces"]
    if key not in traces:
        raise ValueError(f"the comparison has no per-step {key!r} for {row['label']}")
    x = np.asarray(traces.get("time") or np.arange(1, len(traces[key]["mean"]) + 1), dtype=np.float64)
    mean, std = traces[key]["mean"], traces[key]["std"]
    return x, moving_average(mean, smooth), moving_average(std, smooth)


def _smoothed(label: str, smooth: int, x: np.ndarray) -> str:
    if smooth <= 1 or len(x) < 2:
        return label
    return f"{label}, mean over {smooth * (x[1] - x[0]):g} s"


def plot_step_metrics(
    compare: dict[str, Any], output_dir: Path, zoom_threshold: float = 0.5, smooth: int = 10
) -> list[Path]:
    """
    For each objective: its per-step metric over the episode for GPI at every weight of the comparison (paper
    Figs. 8 and 9), and a zoom showing only the policies that favour it, ``w_i >= zoom_threshold`` (paper Fig. 10).
    Curves are coloured by ``w_i``; legends give the whole weight vector.

    :param compare: a comparison (``sb3-sfgpi compare``)
    :param output_dir: where ``steps_<objective>.png`` and ``steps_<objective>_zoom.png`` go
    :param zoom_threshold: the zoom shows the curves of weights with ``w_i >= zoom_threshold``
    :param smooth: trailing moving average over this many steps (the raw curves follow the signal cycles)
    :return: the files written
    """
    rows = sorted((r for r in compare["rows"] if r["method"] == "gpi"), key=lambda r: tuple(r["weights"]))
    if not rows:
        raise ValueError("the comparison has no GPI rows")
    plt = _pyplot()
    cmap = plt.get_cmap("viridis")
    written = []
    for i, name, key, label in _step_metrics(compare):
        ordered = sorted(rows, key=lambda r: r["weights"][i])
        for zoom in (False, True):
            fig, ax = plt.subplots(figsize=(7, 4.2))
            for row in (r for r in ordered if not zoom or r["weights"][i] >= zoom_threshold):
                x, mean, _ = _trace(row, key, smooth)
                ax.plot(x, mean, color=cmap(row["weights"][i]), label=f"w = {format_weights(row['weights'])}", lw=1.5)
            ax.set_xlabel("simulated time [s]")
            ax.set_ylabel(_smoothed(label, smooth, x))
            title = f"{label.split(' [')[0]} for policies generated by GPI"
            ax.set_title(title + (f"\n(only weights with {name} ≥ {zoom_threshold:g})" if zoom else ""))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8, ncol=2)
            written.append(_save(fig, output_dir / f"steps_{name}{'_zoom' if zoom else ''}.png"))
    return written


def plot_versus(compare: dict[str, Any], output_dir: Path, smooth: int = 10) -> list[Path]:
    """
    For each weight with a fixed-weight learner: GPI and that learner (and the baselines, dashed, dash-dotted, dotted),
    one panel per objective, per-step metric over the episode, mean ± std over episodes (paper Figs. 11-15).

    :param compare: a comparison (``sb3-sfgpi compare``)
    :param output_dir: where ``versus_w<w>.png`` go
    :param smooth: trailing moving average over this many steps
    :return: the files written
    """
    gpi = {tuple(np.round(r["weights"], 6)): r for r in compare["rows"] if r["method"] == "gpi"}
    fixed = [r for r in compare["rows"] if r["method"] == "fixed"]
    baselines = [r for r in compare["rows"] if r["method"] == "baseline"]
    if not fixed:
        raise ValueError("the comparison has no fixed-weight learners (sb3-sfgpi compare --fixed RUN)")
    plt = _pyplot()
    metrics = _step_metrics(compare)
    written = []
    done: set[tuple[float, ...]] = set()
    for row in fixed:
        w = tuple(np.round(row["weights"], 6))
        if w in done:
            continue
        done.add(w)
        learners = [r for r in fixed if tuple(np.round(r["weights"], 6)) == w]
        fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4), squeeze=False)
        for ax, (_, name, key, label) in zip(axes[0], metrics, strict=True):
            curves = [(gpi[w], "MA-SFOLS + GPI", "-")] if w in gpi else []
            curves += [(r, r["label"], "-") for r in learners]
            curves += [(r, r["label"], style) for r, style in zip(baselines, itertools.cycle(BASELINE_STYLES))]
            for curve, text, style in curves:
                x, mean, std = _trace(curve, key, smooth)
                (line,) = ax.plot(x, mean, linestyle=style, label=text, lw=1.5 if style == "-" else 1.2)
                if style == "-":
                    ax.fill_between(x, mean - std, mean + std, alpha=0.15, color=line.get_color())
            ax.set_xlabel("simulated time [s]")
            ax.set_ylabel(_smoothed(label, smooth, x))
            ax.set_title(f"w = {format_weights(w)} ({name})")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        written.append(_save(fig, output_dir / f"versus_w{_weights_tag(w)}.png"))
    return written


def plot_tradeoff(compare: dict[str, Any], output: Path) -> Path:
    """
    The first two episode metrics of every method against each other: GPI at every weight (a line in the
    order of ``w``, points coloured by the first objective's weight), the fixed-weight learners and the baselines.

    :param compare: a comparison (``sb3-sfgpi compare``)
    :param output: the PNG file
    """
    metrics = compare["episode_metrics"]
    if len(metrics) < 2:
        raise ValueError("the trade-off plot needs two episode metrics")
    (kx, lx), (ky, ly) = metrics[0], metrics[1]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5))

    def point(row: dict[str, Any]) -> tuple[float, float, float, float]:
        mx, my = row["episode_metrics"][kx], row["episode_metrics"][ky]
        return mx["mean"], my["mean"], mx["std"], my["std"]

    gpi = sorted((r for r in compare["rows"] if r["method"] == "gpi"), key=lambda r: tuple(r["weights"]))
    if gpi:
        pts = np.array([point(r) for r in gpi])
        ax.errorbar(pts[:, 0], pts[:, 1], xerr=pts[:, 2], yerr=pts[:, 3], fmt="-", color="0.6", capsize=2, zorder=1)
        first = np.array([r["weights"][0] for r in gpi])
        dots = ax.scatter(pts[:, 0], pts[:, 1], c=first, vmin=0, vmax=1, label="MA-SFOLS + GPI", zorder=2)
        name = (compare.get("objectives") or ["objective 0"])[0]
        fig.colorbar(dots, ax=ax, label=f"GPI's weight w0 of {name}")
    markers = iter("s^vD<>p*h")
    for row in compare["rows"]:
        if row["method"] == "gpi":
            continue
        x, y, sx, sy = point(row)
        ax.errorbar([x], [y], xerr=[sx], yerr=[sy], fmt=next(markers, "x"), label=row["label"], capsize=2)
    ax.set_xlabel(lx)
    ax.set_ylabel(ly)
    runs = compare.get("merged", 1)
    ax.set_title(f"per-objective outcome (mean ± std over the episodes{f' of {runs} runs' if runs > 1 else ''})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, output)
