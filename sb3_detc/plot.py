"""The paper's training figure from run logs: ``python -m sb3_detc.plot [-f logs] [--env ID] [-o FILE]``.

Two panels over iterations: the episode return (team mean per agent, communication cost
included, ``comm/ep_return``) and the communication savings (``comm/savings``), both
logged by :class:`~sb3_detc.callbacks.CommMetricsCallback` into every run's
``progress.csv`` (written by :mod:`sb3_detc.train`; a study trial keeps it compressed as
``progress.csv.xz``). Every curve is smoothed with a moving average over ``--window``
iterations (the paper: 50); the runs of one algorithm (e.g. several seeds) are drawn as
their mean and a band from their minimum to their maximum. Dashed vertical lines mark the
curriculum phases of the first run that logs them (``curriculum/phase``, or the start and
end of the broadcast entropy decay, ``curriculum/broadcast_ent_coef``).
"""

from __future__ import annotations

import argparse
import csv
import lzma
import math
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the file backend)
import numpy as np  # noqa: E402
from huggingface_sb3 import EnvironmentName  # noqa: E402

from sb3_detc.cli import InputError, run_cli  # noqa: E402
from sb3_detc.renamed import renamed_column  # noqa: E402

__all__ = [
    "LEARNED_MARKERS",
    "LEARNED_POINTS",
    "curriculum_phases",
    "curve_label",
    "estimates_figure",
    "find_runs",
    "main",
    "open_progress",
    "outlier_symlog_threshold",
    "plot_estimates",
    "plot_front",
    "plot_runs",
    "progress_file",
    "read_progress",
    "smooth",
    "symlog_threshold",
]

#: Logged values of the two panels: (column, axis label).
PANELS = (("comm/ep_return", "return"), ("comm/savings", "communication savings"))

#: A run's logged values as the logger writes them while it trains.
PROGRESS_CSV = "progress.csv"
#: The same CSV compressed with xz: a study trial's log, all its attempts merged (:mod:`sb3_detc.study.trial`).
PROGRESS_XZ = "progress.csv.xz"


def progress_file(run: str | Path) -> Path | None:
    """The file of a run's logged values: its ``progress.csv.xz`` (a study trial's), else its ``progress.csv``.

    :param run: the run's log folder (or a study trial's folder)
    :return: the file, None if the folder holds neither
    """
    for name in (PROGRESS_XZ, PROGRESS_CSV):
        path = Path(run) / name
        if path.is_file():
            return path
    return None


def open_progress(run: str | Path) -> TextIO:
    """Open a run's logged values (:func:`progress_file`) as CSV text, decompressed if need be.

    :param run: the run's log folder (or a study trial's folder)
    :return: the open text file (the caller closes it)
    :raises InputError: if the folder holds no progress file
    """
    path = progress_file(run)
    if path is None:
        raise InputError(f"no {PROGRESS_CSV} in {str(run)!r}: train with python -m sb3_detc.train")
    return lzma.open(path, "rt", newline="") if path.name == PROGRESS_XZ else path.open(newline="")


def read_progress(run: str | Path) -> dict[str, np.ndarray]:
    """Columns of a run's logged values (:func:`open_progress`) as float arrays (missing values NaN), by iteration.

    :param run: the run's log folder (or a study trial's folder)
    :return: ``{"iteration": ..., column: ...}``; text columns (e.g. ``curriculum/phase``) as str arrays
    :raises InputError: if the file is missing, empty or has no ``time/iterations`` column
    """
    with open_progress(run) as file:
        rows = list(csv.DictReader(file))
    if not rows or "time/iterations" not in rows[0]:
        raise InputError(f"{progress_file(run)}: no iterations logged yet")
    columns: dict[str, np.ndarray] = {}
    for key in rows[0]:
        values = [row.get(key) or "" for row in rows]
        try:
            columns[renamed_column(key)] = np.array([float(v) if v != "" else math.nan for v in values])
        except ValueError:
            columns[renamed_column(key)] = np.array(values)
    columns["iteration"] = _iterations(columns.pop("time/iterations"), columns.get("time/total_timesteps"))
    return columns


def _iterations(logged: np.ndarray, timesteps: np.ndarray | None) -> np.ndarray:
    """Iterations since the start of training.

    SB3 counts ``time/iterations`` from 1 in every ``learn`` call, so a continued run
    (``sb3_detc.train -i``) restarts it; the step count goes on, and the steps per iteration
    follow from two logged rows.

    :param logged: the logged ``time/iterations``
    :param timesteps: the logged ``time/total_timesteps`` (None: not logged)
    :return: iterations counted from the start of training
    """
    if timesteps is None or len(logged) < 2 or not np.all(np.isfinite(timesteps)) or logged[1] <= logged[0]:
        return logged
    per_iteration = (timesteps[1] - timesteps[0]) / (logged[1] - logged[0])
    return np.rint(timesteps / per_iteration) if per_iteration > 0 else logged


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` entries that skips NaN (NaN where the window has none).

    :param values: the series
    :param window: number of entries averaged (>= 1)
    :return: the smoothed series, same length
    """
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}.")
    valid = np.isfinite(values)
    sums = np.cumsum(np.where(valid, values, 0.0))
    counts = np.cumsum(valid)
    shifted_sums = np.concatenate([np.zeros(window), sums[:-window]])[: len(values)]
    shifted_counts = np.concatenate([np.zeros(window), counts[:-window]])[: len(values)]
    n = counts - shifted_counts
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (sums - shifted_sums) / np.maximum(n, 1), math.nan)


def curriculum_phases(progress: dict[str, np.ndarray]) -> list[tuple[float, str]]:
    """Iterations at which a curriculum phase starts, with the phase's name.

    From ``curriculum/phase`` (:class:`~sb3_detc.callbacks.CurriculumCallback`) where logged,
    else from ``curriculum/stage`` (:class:`~sb3_detc.callbacks.ControlFirstCallback`: "stage 2"
    where the policies over options start to learn), else from ``curriculum/broadcast_ent_coef``
    (:class:`~sb3_detc.callbacks.BroadcastEntropySchedule`): "entropy decay" where it first leaves
    its initial value, "decayed" where it first reaches its last logged value after that.

    :param progress: a run's columns from :func:`read_progress`
    :return: (iteration, name) of every phase start after the first phase
    """
    iterations = progress["iteration"]
    phase = progress.get("curriculum/phase")
    if phase is not None and phase.dtype.kind in "US":
        return [(float(iterations[k]), str(phase[k])) for k in range(1, len(phase)) if phase[k] != phase[k - 1]]
    stage = progress.get("curriculum/stage")
    if stage is not None and stage.dtype.kind == "f" and np.isfinite(stage).any():
        logged = np.flatnonzero(np.isfinite(stage))
        return [
            (float(iterations[k]), f"stage {stage[k]:.0f}")
            for j, k in enumerate(logged[1:], start=1)
            if stage[k] != stage[logged[j - 1]]
        ]
    coef = progress.get("curriculum/broadcast_ent_coef")
    if coef is None or coef.dtype.kind != "f" or not np.isfinite(coef).any():
        return []
    coef = coef[np.isfinite(coef)]
    iterations = iterations[np.isfinite(progress["curriculum/broadcast_ent_coef"])]
    moved = np.flatnonzero(coef != coef[0])
    if len(moved) == 0:
        return []
    marks = [(float(iterations[moved[0]]), "entropy decay")]
    settled = np.flatnonzero((coef == coef[-1]) & (np.arange(len(coef)) > moved[0]))
    if len(settled) and settled[0] > moved[0]:
        marks.append((float(iterations[settled[0]]), "decayed"))
    return marks


def find_runs(folder: str | Path, algo: str, env_id: str) -> list[Path]:
    """Log folders of an algorithm's runs on an environment that have a ``progress.csv``, by run id.

    :param folder: rl-zoo3's log folder (``-f``)
    :param algo: the algorithm name
    :param env_id: the environment id
    :return: the run folders ``<folder>/<algo>/<env>_<id>``
    """
    prefix = f"{EnvironmentName(env_id)}_"
    runs = []
    for path in (Path(folder) / algo).glob(f"{prefix}*"):
        run_id = path.name[len(prefix) :]
        if run_id.isdigit() and progress_file(path) is not None:
            runs.append((int(run_id), path))
    return [path for _, path in sorted(runs)]


def _save(fig: plt.Figure, out: str | Path) -> Path:
    """Lay the figure out, write it as a PNG file (its folder made if needed) and close it.

    :param fig: the figure
    :param out: the PNG file
    :return: the written file
    """
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def curve_label(label: str, lengths: Sequence[int]) -> str:
    """The legend entry of a group of runs: its label, its number of runs and how many end before the longest.

    :param label: the group's label
    :param lengths: the logged iterations of each run
    :return: e.g. ``"mappoc (5 runs, 1 ends earlier)"``
    """
    text = f"{label} ({len(lengths)} run{'s' * (len(lengths) != 1)}"
    shorter = sum(length < max(lengths) for length in lengths)
    if shorter:
        text += f", {shorter} end{'s' * (shorter == 1)} earlier"
    return text + ")"


def plot_runs(
    groups: dict[str, Sequence[str | Path]],
    out: str | Path,
    window: int = 50,
    title: str = "",
    panels: Sequence[tuple[str, str]] = PANELS,
) -> Path:
    """Draw the figure for groups of runs (label -> run folders) into a PNG file.

    Runs of one group may have different lengths (e.g. one still training): the mean and
    the band at an iteration are over the runs that reached it.

    :param groups: one entry per curve: its label and its runs (seeds)
    :param out: the PNG file
    :param window: iterations of the moving average
    :param title: the figure's title
    :param panels: the logged values to draw, one panel each: (column, axis label)
    :return: the written file
    :raises InputError: if a group has no runs or a run lacks the plotted values
    """
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    axes = axes[0]
    phases: list[tuple[float, str]] = []
    drawn: list[list[np.ndarray]] = [[] for _ in panels]
    for label, runs in groups.items():
        if not runs:
            raise InputError(f"no runs with a progress.csv for {label}")
        progress = [read_progress(run) for run in runs]
        phases = phases or curriculum_phases(progress[0])
        longest = max(progress, key=lambda p: len(p["iteration"]))
        length = len(longest["iteration"])
        iterations = longest["iteration"]
        for ax, (column, _) in zip(axes, panels, strict=True):
            curves = []
            for run, p in zip(runs, progress, strict=True):
                if column not in p or p[column].dtype.kind != "f":
                    raise InputError(f"{run}: {column} not logged: add sb3_detc.callbacks.CommMetricsCallback")
                curve = smooth(p[column], window)
                curves.append(np.concatenate([curve, np.full(length - len(curve), math.nan)]))
            curves = np.array(curves)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # iterations where no run has a value
                mean = np.nanmean(curves, axis=0)
                low, high = np.nanmin(curves, axis=0), np.nanmax(curves, axis=0)
            drawn[list(panels).index((column, _))].append(mean)
            (line,) = ax.plot(iterations, mean, label=curve_label(label, [len(p["iteration"]) for p in progress]))
            if len(runs) > 1:
                ax.fill_between(iterations, low, high, color=line.get_color(), alpha=0.25, linewidth=0)
    for ax, (_, name), curves in zip(axes, panels, drawn, strict=True):
        scale = symlog_threshold(np.concatenate(curves))
        if scale is not None:  # early returns can be orders of magnitude below the final ones
            ax.set_yscale("symlog", linthresh=scale)
            name = f"{name} (symlog)"
        for iteration, phase in phases:
            ax.axvline(iteration, color="0.4", linestyle="--", linewidth=1)
            ax.annotate(
                phase,
                (iteration, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(3, -3),
                textcoords="offset points",
                va="top",
                ha="left",
                fontsize="small",
            )
        ax.set_xlabel("iteration")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower right")
    fig.suptitle(f"{title}{': ' if title else ''}moving averages over {window} iterations")
    return _save(fig, out)


def plot_estimates(
    estimates: dict[str, dict[str, tuple[float, float, float, Sequence[float]]]],
    out: str | Path,
    panels: Sequence[tuple[str, str]],
    title: str = "",
) -> Path:
    """Draw :func:`estimates_figure` into a PNG file.

    :param estimates: label -> metric -> (mean, low, high, the seeds' values); a label may lack a metric
    :param out: the PNG file
    :param panels: the metrics to draw, one panel each: (metric, axis label)
    :param title: the figure's title
    :return: the written file
    """
    return _save(estimates_figure(estimates, panels, title), out)


#: Points of a front that are learned triggers, not fixed families: sampled as learned, and made deterministic at
#: the learned rate (the protocol's mode ``thresholded``).
LEARNED_POINTS = ("learned", "thresholded")
#: Markers of the learned triggers of one panel of a front, in the order of its rows (squares are the families').
LEARNED_MARKERS = "o^vDPX*"


def plot_front(rows: Sequence[dict], out: str | Path, title: str = "") -> Path:
    """Control return against savings: learned triggers as points with intervals, fixed families as curves.

    Every learned trigger is a filled marker of its own, named in the legend, and where the
    protocol ran it, the same trigger thresholded at its rate the same marker open. Algorithms
    with the same environment settings (``settings``) share a panel, in which every family's
    points at the algorithms' rates are joined in the order of their savings.

    :param rows: the study's front (:func:`sb3_detc.study.report.front`)
    :param out: the PNG file
    :param title: the figure's title
    :return: the written file
    """
    panels = list(dict.fromkeys(row["settings"] for row in rows))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 5.0), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, settings in zip(axes[0], panels, strict=True):
        group = [row for row in rows if row["settings"] == settings]
        families = list(dict.fromkeys(name for row in group for name in row["points"] if name not in LEARNED_POINTS))
        for k, family in enumerate(families):
            points = sorted(row["points"][family] for row in group if family in row["points"])
            x, y = [p[0] for p in points], [p[1] for p in points]
            errors = np.array([[p[1] - p[2][0], p[2][1] - p[1]] for p in points]).T
            ax.errorbar(
                x,
                y,
                yerr=errors,
                color=colors[(k + 1) % len(colors)],
                marker="s",
                markersize=4,
                capsize=2,
                linewidth=1.2,
                label=family,
            )
        for r, row in enumerate(group):
            marker = LEARNED_MARKERS[r % len(LEARNED_MARKERS)]
            for name in LEARNED_POINTS:
                if name not in row["points"]:
                    continue
                savings, mean, (low, high) = row["points"][name]
                ax.errorbar(
                    [savings],
                    [mean],
                    yerr=[[mean - low], [high - mean]],
                    color=colors[0],
                    marker=marker,
                    markersize=7,
                    markerfacecolor=colors[0] if name == "learned" else "none",
                    capsize=3,
                    linestyle="none",
                )
            ax.plot([], [], marker, color=colors[0], label=row["label"])
        if any("thresholded" in row["points"] for row in group):
            ax.plot([], [], "o", color=colors[0], markerfacecolor="none", label="open: thresholded at its rate")
        ax.set_xlabel("communication savings")
        ax.set_ylabel("control return (mean over seeds, 95 % interval)")
        ax.set_title(settings if settings != "{}" else "entry settings", fontsize="small")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.suptitle("\n".join(filter(None, (title, "learned triggers and fixed families at the same savings"))))
    return _save(fig, out)


def estimates_figure(
    estimates: dict[str, dict[str, tuple[float, float, float, Sequence[float]]]],
    panels: Sequence[tuple[str, str]],
    title: str = "",
) -> plt.Figure:
    """Means over seeds with their intervals and every seed's value: one panel per metric, one row per label.

    :param estimates: label -> metric -> (mean, low, high, the seeds' values); a label may lack a metric
    :param panels: the metrics to draw, one panel each: (metric, axis label); a panel whose
        metric no label has is left out, one named ``...minus...`` gets a line at zero, one
        with outliers a symmetric log axis (:func:`outlier_symlog_threshold`)
    :param title: the figure's title
    :return: the figure (rows top to bottom in the order of ``estimates``)
    """
    labels = list(estimates)
    panels = [(metric, name) for metric, name in panels if any(metric in estimates[label] for label in labels)]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(3.6 * len(panels), 0.6 + 0.5 * len(labels)), squeeze=False, sharey=True
    )
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (metric, name) in zip(axes[0], panels, strict=True):
        drawn = [estimates[label][metric] for label in labels if metric in estimates[label]]
        scale = outlier_symlog_threshold(np.array([v for m, lo, hi, seeds in drawn for v in (m, lo, hi, *seeds)]))
        if scale is not None:  # a failed seed far from the others
            ax.set_xscale("symlog", linthresh=scale)
            name = f"{name} (symlog)"
        else:
            ax.locator_params(axis="x", nbins=5)
        for row, label in enumerate(labels):
            if metric not in estimates[label]:
                continue
            mean, low, high, seeds = estimates[label][metric]
            color = colors[row % len(colors)]
            ax.plot([low, high], [row, row], color=color, linewidth=6, alpha=0.35, solid_capstyle="butt")
            ax.plot(seeds, [row] * len(seeds), "o", color=color, markersize=3.5, markerfacecolor="none")
            ax.plot([mean], [row], "|", color=color, markersize=14, markeredgewidth=2.5)
        if "minus" in metric:
            ax.axvline(0.0, color="0.4", linestyle="--", linewidth=1)
        ax.set_xlabel(name)
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].set_yticks(range(len(labels)), labels)
    axes[0][0].set_ylim(len(labels) - 0.5, -0.5)
    fig.suptitle(f"{title}{': ' if title else ''}mean (bar), 95 % interval (band), seeds (circles)", fontsize="medium")
    return fig


def outlier_symlog_threshold(values: np.ndarray, span: float = 100.0) -> float | None:
    """Linear range of a symmetric log axis for values with outliers, else None.

    Unlike :func:`symlog_threshold` (for curves that grow by orders of magnitude), the axis stays
    linear up to the values' median magnitude, so that values near zero keep a linear scale.

    :param values: the plotted values (NaN allowed)
    :param span: ratio of the largest to the median magnitude above which the axis turns logarithmic
    :return: the median magnitude, or None for a linear axis
    """
    magnitudes = np.abs(values[np.isfinite(values)])
    if len(magnitudes) == 0:
        return None
    typical = float(np.median(magnitudes))
    return typical if typical > 0 and magnitudes.max() > span * typical else None


def symlog_threshold(values: np.ndarray, span: float = 100.0, near_zero: float = 0.01) -> float | None:
    """Linear range of a symmetric log axis for curves spanning more than ``span`` in magnitude, else None.

    The smallest magnitude is taken after leaving out the fraction ``near_zero`` of values nearest
    zero, so that a curve crossing zero (returns rising from negative to positive) does not by
    itself turn the axis logarithmic.

    :param values: the plotted values (NaN allowed)
    :param span: ratio of the largest to the smallest magnitude above which the axis turns logarithmic
    :param near_zero: fraction of the values, those nearest zero, left out of the smallest magnitude
    :return: the smallest magnitude (so counted), or None for a linear axis
    """
    magnitudes = np.abs(values[np.isfinite(values)])
    if len(magnitudes) == 0:
        return None
    smallest = float(np.quantile(magnitudes, near_zero, method="lower"))
    return smallest if smallest > 0 and magnitudes.max() > span * smallest else None


def _main() -> None:
    """The plot command: read ``sys.argv``, find the runs of every algorithm and draw their figure.

    :raises InputError: on ``--window < 1`` or if no algorithm has runs with a ``progress.csv``
    """
    parser = argparse.ArgumentParser(prog="python -m sb3_detc.plot", description=__doc__.splitlines()[0])
    parser.add_argument("-f", "--folder", default="logs", help="rl-zoo3 log folder (default: logs)")
    parser.add_argument("--env", default="sb3_detc/LinearETC-v0", help="environment id")
    parser.add_argument("--algos", nargs="+", default=["mappoc", "ppo_random_skip"], help="algorithms to draw")
    parser.add_argument("--window", type=int, default=50, help="iterations of the moving average (default: 50)")
    parser.add_argument("-o", "--out", default=None, help="PNG file (default: <folder>/<env>.png)")
    args = parser.parse_args(sys.argv[1:])
    if args.window < 1:
        raise InputError(f"--window must be >= 1, got {args.window}")
    groups = {algo: find_runs(args.folder, algo, args.env) for algo in args.algos}
    groups = {algo: runs for algo, runs in groups.items() if runs}
    if not groups:
        raise InputError(f"no runs of {', '.join(args.algos)} on {args.env} with a progress.csv in {args.folder!r}")
    out = args.out or Path(args.folder) / f"{EnvironmentName(args.env)}.png"
    print(f"Saved {plot_runs(groups, out, args.window, title=args.env)}")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the plot command line (bad input: one line on stderr, exit code 2).

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.plot", _main, argv)


if __name__ == "__main__":
    main()
