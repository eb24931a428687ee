"""The report of a study folder: statistics over seeds (rliable), tables, curves and ``summary.json``.

It reads only the trials' files (``evaluation.json``, ``status.json``, ``progress.csv.xz``), so
anyone with a copy of the folder can make it. Per algorithm label, every metric of
:func:`~sb3_detc.evaluation.evaluate_policy_modes` is summarised over the finished seeds by
its mean and a 95 % stratified-bootstrap percentile interval of the mean (rliable's
``get_interval_estimates``, 10,000 resamples, fixed random state); the interquartile mean
and the probability that one algorithm's control return beats another's (rliable's
``probability_of_improvement``, with a 2,000-resample interval) compare the algorithms.
The probability of improvement compares control returns as they are: algorithms that
communicate at different rates differ in what they pay for it too (see the returns).
The learned (and thresholded) minus the best fixed family's control return also gets an interval
over seeds and episodes (:func:`crossed_interval`): the seeds run the same episodes.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from rliable import library as rly
from rliable import metrics as rly_metrics
from scipy import stats

from sb3_detc.files import replace_atomically
from sb3_detc.plot import LEARNED_POINTS, open_progress, plot_estimates, plot_front, plot_runs, progress_file
from sb3_detc.study.spec import AlgorithmSpec, StudyError, StudySpec, Trial, load_folder_study
from sb3_detc.study.trial import read_status, trial_folder
from sb3_detc.triggers import TRIGGER_FAMILIES

__all__ = [
    "BOOTSTRAP_REPS",
    "CURVE_PANELS",
    "ESTIMATE_PANELS",
    "METRICS",
    "PAIRED",
    "crossed_interval",
    "front",
    "front_markdown",
    "interval_estimates",
    "interval_text",
    "mark_lines",
    "paired_differences",
    "read_trials",
    "report_study",
    "splice",
    "splice_marks",
    "summarise",
]

#: Resamples of the bootstrap intervals.
BOOTSTRAP_REPS = 10_000

#: Resamples of the intervals of the probability of improvement (a rank test per resample: slower).
IMPROVEMENT_REPS = 2_000

#: Metrics of the report, in table order (those a trial lacks, e.g. package travel on the linear system, are left out).
METRICS = (
    "timesteps",
    "return",
    "control_return",
    "savings",
    "random_same_rate_return",
    "random_same_rate_control_return",
    "random_same_rate_savings",
    "learned_minus_random_control_return",
    "periodic_return",
    "periodic_control_return",
    "never_return",
    "never_control_return",
    "mode_control_return",
    "mode_savings",
    "thresholded_control_return",
    "thresholded_savings",
    "option_state_information",
    *(f"fixed_{family}_{metric}" for family in TRIGGER_FAMILIES for metric in ("control_return", "savings")),
    "best_fixed_control_return",
    "learned_minus_best_fixed_control_return",
    "thresholded_minus_best_fixed_control_return",
    "package_travel",
    "mode_package_travel",
    "thresholded_package_travel",
    "random_same_rate_package_travel",
    "periodic_package_travel",
    "fall_rate",
    "success",
)

#: Differences of a front's row, learned and thresholded minus the best fixed family: (key, metric, table header).
DIFFERENCES = (
    ("difference", "learned_minus_best_fixed_control_return", "learned minus best fixed"),
    ("thresholded_difference", "thresholded_minus_best_fixed_control_return", "thresholded minus best fixed"),
)

#: Paired differences whose interval over seeds *and* episodes the report gives too: (metric, mode). Every
#: seed runs the same episodes, so what they favour moves every seed alike and stays outside an interval
#: over the seeds alone (:func:`crossed_interval`).
PAIRED = (
    ("learned_minus_best_fixed_control_return", "learned"),
    ("thresholded_minus_best_fixed_control_return", "thresholded"),
)

#: Panels of ``curves.png``: training control return (without the communication cost, so that
#: algorithms trained with and without it compare like with like) and savings.
CURVE_PANELS = (
    ("comm/ep_control_return", "control return (no communication cost)"),
    ("comm/savings", "communication savings"),
)


#: Panels of ``estimates.png``: the final policies' metrics (those the trials report), means
#: over seeds with their intervals and every seed.
ESTIMATE_PANELS = (
    ("control_return", "control return"),
    ("savings", "savings"),
    ("learned_minus_random_control_return", "learned - random, same rate"),
    ("package_travel", "package travel"),
    ("fall_rate", "fall rate"),
)


def interval_estimates(values: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Means over seeds and their 95 % bootstrap intervals, for every label.

    :param values: label -> array (seeds, metrics)
    :return: label -> means (metrics,), label -> intervals (2, metrics) (low, high)
    """
    return _bootstrap(values, lambda scores: np.mean(scores, axis=0))


def metric_estimates(seeds: list[dict[str, Any]]) -> tuple[dict[str, float], dict[str, list[float]]]:
    """Means over seeds of every metric of :data:`METRICS` that all seeds have, with their 95 % bootstrap intervals.

    One bootstrap over the metrics in :data:`METRICS`' order, so that a study's summary and any
    other table of the same seeds' metrics give the same intervals.

    :param seeds: every seed's metrics (at least one)
    :return: metric -> mean, metric -> [low, high]
    """
    names = [m for m in METRICS if all(m in metrics for metrics in seeds)]
    means, intervals = interval_estimates({"x": np.array([[float(metrics[m]) for m in names] for metrics in seeds])})
    mean = {name: float(means["x"][k]) for k, name in enumerate(names)}
    ci = {name: [float(intervals["x"][0, k]), float(intervals["x"][1, k])] for k, name in enumerate(names)}
    return mean, ci


def crossed_interval(values: np.ndarray) -> tuple[float, float]:
    """95 % interval of the mean of paired differences of seeds on the same episodes, seeds and episodes both random.

    The seeds run the same episodes: a crossed design whose mean has the variance
    ``s2_seed / S + s2_episode / E + s2_rest / (S E)``, each component from the mean squares of the
    two-way analysis of variance (at least 0), and the interval is Student's t with Satterthwaite's
    degrees of freedom. One seed: the interval over its episodes alone. (Resampling seeds and
    episodes at once would count the rest three times.)

    :param values: (seeds, episodes), at least 2 episodes
    :return: low, high
    :raises ValueError: for fewer than 2 episodes
    """
    values = np.asarray(values, dtype=np.float64)
    n_seeds, n_episodes = values.shape
    if n_episodes < 2:
        raise ValueError(f"an interval over episodes needs at least 2 of them, got {n_episodes}.")
    mean = float(values.mean())
    if n_seeds == 1:
        half = stats.t.ppf(0.975, n_episodes - 1) * values.std(ddof=1) / math.sqrt(n_episodes)
        return mean - float(half), mean + float(half)
    by_seed, by_episode = values.mean(axis=1), values.mean(axis=0)
    rest = values - by_seed[:, None] - by_episode[None, :] + mean
    freedom = np.array([n_seeds - 1, n_episodes - 1, (n_seeds - 1) * (n_episodes - 1)], dtype=np.float64)
    squares = (
        np.array(
            [n_episodes * np.sum((by_seed - mean) ** 2), n_seeds * np.sum((by_episode - mean) ** 2), np.sum(rest**2)]
        )
        / freedom
    )
    cells = n_seeds * n_episodes
    # the components' shares of the variance of the mean, as multiples of the mean squares (a clamped one: none)
    weights = np.array([squares[0] > squares[2], squares[1] > squares[2], 0.0])
    weights[2] = 1.0 - weights[0] - weights[1]
    variance = float(weights @ squares) / cells
    if variance <= 0:
        return mean, mean
    dof = variance**2 / float(np.sum((weights * squares / cells) ** 2 / freedom))
    half = stats.t.ppf(0.975, dof) * math.sqrt(variance)
    return mean - float(half), mean + float(half)


def paired_differences(evaluations: list[dict[str, Any]], family: str | None = None) -> dict[str, np.ndarray]:
    """Per seed and episode, the learned (and thresholded) control return minus that of a fixed family.

    :param evaluations: every seed's ``evaluation.json``, the same episodes
    :param family: the family compared (None: each seed's best, ``best_fixed``)
    :return: mode of :data:`PAIRED` (``"learned"``, ``"thresholded"``) -> (seeds, episodes), for the modes that
        every seed ran beside the family on the same episodes (at least 2)
    """
    if not evaluations or len({(e["seed"], e["episodes"]) for e in evaluations}) > 1 or evaluations[0]["episodes"] < 2:
        return {}  # not the same episodes, or too few for an interval over them
    compared = [f"fixed_{family or e.get('best_fixed')}" for e in evaluations]
    out = {}
    for _, mode in PAIRED:
        if not all(mode in e["modes"] and name in e["modes"] for e, name in zip(evaluations, compared, strict=True)):
            continue
        pairs = [
            (e["modes"][mode]["control_return"], e["modes"][name]["control_return"])
            for e, name in zip(evaluations, compared, strict=True)
        ]
        if all(len(a) == len(b) == e["episodes"] for (a, b), e in zip(pairs, evaluations, strict=True)):
            out[mode] = np.array([np.subtract(a, b) for a, b in pairs])
    return out


def _bootstrap(
    values: dict[str, Any], statistic: Any, reps: int = BOOTSTRAP_REPS
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Stratified-bootstrap (rliable) point estimates and 95 % percentile intervals, the same on every call.

    rliable draws its resamples from NumPy's global generator: it is seeded for the call and
    restored afterwards.

    :param values: label -> array (seeds, metrics), or a tuple of such arrays (resampled alike) that
        ``statistic`` takes together
    :param statistic: one label's (resampled) array, or the arrays of its tuple as arguments -> estimates (k,)
    :param reps: bootstrap resamples
    :return: label -> point estimates (k,), label -> intervals (2, k) (low, high)
    """
    state = np.random.get_state()
    np.random.seed(0)
    try:
        with warnings.catch_warnings():
            # arch warns that a RandomState will once have to be passed differently; rliable passes it.
            warnings.simplefilter("ignore", FutureWarning)
            return rly.get_interval_estimates(values, statistic, reps=reps, random_state=np.random.RandomState(0))
    finally:
        np.random.set_state(state)


def read_trials(directory: str | Path) -> tuple[Any, dict[str, dict[int, dict[str, Any]]], dict[str, dict[int, str]]]:
    """The evaluations of a study folder's finished trials and the states of the others.

    :param directory: the study folder
    :return: the study, label -> seed -> ``evaluation.json`` of every finished trial, and
        label -> seed -> state (e.g. ``running, 2048 steps`` or ``failed (...)``) of the others
    """
    directory = Path(directory)
    spec = load_folder_study(directory)
    evaluations: dict[str, dict[int, dict[str, Any]]] = {a.label: {} for a in spec.algorithms}
    states: dict[str, dict[int, str]] = {a.label: {} for a in spec.algorithms}
    for trial in spec.trials():
        folder = trial_folder(directory, trial)
        status = read_status(folder)
        state = status["status"]
        if state == "done" and (folder / "evaluation.json").is_file():
            evaluations[trial.algorithm.label][trial.seed] = json.loads((folder / "evaluation.json").read_text())
        elif state == "failed":
            states[trial.algorithm.label][trial.seed] = f"failed ({status.get('error', 'see error.txt')})"
        else:
            states[trial.algorithm.label][trial.seed] = f"{state}, {status.get('timesteps', 0)} steps"
    return spec, evaluations, states


def summarise(directory: str | Path) -> dict[str, Any]:
    """The statistics of a study folder (what ``summary.json`` holds).

    :param directory: the study folder
    :return: label -> ``seeds`` (seed -> metrics and ``timesteps``), ``mean`` and ``ci95`` (metric -> value,
        metric -> [low, high]), ``episodes_ci95`` (metric of :data:`PAIRED` -> [low, high] over seeds and
        episodes, :func:`crossed_interval`), ``iqm_control_return``, ``success_count`` (seeds succeeding;
        None where the env reports no success), ``unfinished`` (seed -> state);
        and under ``"comparisons"`` the probability of improvement of control return for
        every ordered pair of labels with finished seeds
    """
    directory = Path(directory)
    spec, evaluations, states = read_trials(directory)
    summary: dict[str, Any] = {}
    scores: dict[str, np.ndarray] = {}
    for algorithm in spec.algorithms:
        label = algorithm.label
        seeds = {seed: {"timesteps": e["timesteps"], **e["metrics"]} for seed, e in evaluations[label].items()}
        entry: dict[str, Any] = {"seeds": seeds, "mean": {}, "ci95": {}, "unfinished": states[label]}
        summary[label] = entry
        if not seeds:
            continue
        ordered = [seeds[s] for s in sorted(seeds)]
        entry["mean"], entry["ci95"] = metric_estimates(ordered)
        paired = paired_differences([evaluations[label][s] for s in sorted(seeds)])
        if paired:
            entry["episodes_ci95"] = {
                metric: list(crossed_interval(paired[mode])) for metric, mode in PAIRED if mode in paired
            }
        control = np.array([float(metrics["control_return"]) for metrics in ordered])
        entry["iqm_control_return"] = float(rly_metrics.aggregate_iqm(control[:, None]))
        success = "success" in entry["mean"]
        entry["success_count"] = int(sum(float(metrics["success"]) for metrics in ordered)) if success else None
        scores[label] = control[:, None]
    comparisons = []
    labels = list(scores)
    for k, x in enumerate(labels):
        for y in labels[k + 1 :]:
            # P(Y > X) = 1 - P(X > Y) (ties count half): one bootstrap per pair of labels.
            point, interval = _bootstrap(
                {"pair": (scores[x], scores[y])},
                lambda a, b: np.array([rly_metrics.probability_of_improvement(a, b)]),
                reps=IMPROVEMENT_REPS,
            )
            p, (low, high) = float(point["pair"][0]), (float(v) for v in interval["pair"][:, 0])
            comparisons.append({"better": x, "than": y, "probability": p, "ci95": [low, high]})
            comparisons.append({"better": y, "than": x, "probability": 1.0 - p, "ci95": [1.0 - high, 1.0 - low]})
    summary["comparisons"] = comparisons
    return summary


def _number(value: float, digits: int = 2) -> str:
    """A number for the report's tables.

    :param value: the number (None or NaN: not available)
    :param digits: decimals shown below 1000 in size (from 1000 on: no decimals, thousands separated by commas)
    :return: the text, ``n/a`` for None or NaN
    """
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    return f"{value:.{digits}f}"


def _markdown(directory: Path, spec: Any, summary: dict[str, Any]) -> str:
    """The Markdown report of a study: per algorithm its unfinished seeds, metric table and seed table; comparisons.

    :param directory: the study folder (its name is the title's)
    :param spec: the study (:class:`~sb3_detc.study.spec.StudySpec`)
    :param summary: the study's statistics (:func:`summarise`)
    :return: the report
    """
    lines = [f"# Study {directory.name}: {spec.env}", ""]
    lines += [
        f"Evaluation: {spec.episodes} episodes per mode, the same seeded episodes for every trial "
        f"(seeds {spec.eval_seed} to {spec.eval_seed + spec.episodes - 1}). Mean over seeds and 95 % "
        f"stratified-bootstrap interval (rliable, {BOOTSTRAP_REPS} resamples).",
        "",
    ]
    for algorithm in spec.algorithms:
        label = algorithm.label
        entry = summary[label]
        seeds = entry["seeds"]
        lines += [f"## {label} ({algorithm.algo}): {len(seeds)} of {len(algorithm.seeds)} seeds finished", ""]
        for seed, state in sorted(entry["unfinished"].items()):
            lines.append(f"- seed {seed}: {state}")
        if entry["unfinished"]:
            lines.append("")
        if not seeds:
            continue
        lines += ["| metric | mean | 95 % CI |", "|---|---|---|"]
        for name, mean in entry["mean"].items():
            low, high = entry["ci95"][name]
            digits = 3 if "savings" in name or name in ("fall_rate", "success") else 2
            lines.append(f"| {name} | {_number(mean, digits)} | [{_number(low, digits)}, {_number(high, digits)}] |")
        lines.append("")
        difference = entry["mean"].get("learned_minus_random_control_return")
        if difference is not None:
            low, high = entry["ci95"]["learned_minus_random_control_return"]
            lines.append(
                f"Learned minus random options at the learned rate (control return, paired episodes): "
                f"{_number(difference)} [{_number(low)}, {_number(high)}]."
            )
        over = (
            "over seeds and episodes (the seeds share the episodes)" if len(seeds) > 1 else "over episodes (one seed)"
        )
        for metric, (low, high) in entry.get("episodes_ci95", {}).items():
            lines.append(f"{metric}: 95 % interval {over}: [{_number(low)}, {_number(high)}].")
        if algorithm.selection is not None:
            lines += selection_lines(directory, spec, algorithm, sorted(seeds))
        if entry.get("success_count") is not None:
            lines.append(f"Seeds succeeding: {entry['success_count']} of {len(seeds)}.")
        lines.append(f"Interquartile mean of the control return: {_number(entry['iqm_control_return'])}.")
        lines.append("")
        columns = [
            m
            for m in (
                "control_return",
                "savings",
                "random_same_rate_control_return",
                "periodic_control_return",
                "package_travel",
                "fall_rate",
                "success",
            )
            if m in entry["mean"]
        ]
        lines += ["| seed | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
        for seed in sorted(seeds):
            cells = [
                _number(float(seeds[seed][m]), 3 if m in ("savings", "fall_rate", "success") else 2) for m in columns
            ]
            lines.append(f"| {seed} | " + " | ".join(cells) + " |")
        lines.append("")
    if summary["comparisons"]:
        lines += [
            "## Probability of improvement (control return)",
            "",
            "| algorithm | over | P(X > Y) | 95 % CI |",
            "|---|---|---|---|",
        ]
        for row in summary["comparisons"]:
            low, high = row["ci95"]
            lines.append(f"| {row['better']} | {row['than']} | {row['probability']:.2f} | [{low:.2f}, {high:.2f}] |")
        lines.append("")
    return "\n".join(lines)


def selection_lines(directory: Path, spec: StudySpec, algorithm: AlgorithmSpec, seeds: list[int]) -> list[str]:
    """What the report says of an algorithm's ``selection``: the validations and, per seed, the kept policy.

    :param directory: the study folder
    :param spec: the study
    :param algorithm: an algorithm with a ``selection``
    :param seeds: its finished seeds
    :return: the lines (a sentence, then one line per seed)
    """
    selection = algorithm.selection
    validation = spec.validation_seeds(selection.episodes, selection.seed)
    first, last = validation[0], validation[-1]
    lines = [
        f"The final policy of every seed is the one that did best on {selection.episodes} validation episodes "
        f"(seeds {first} to {last}) at the target savings (at most {selection.tolerance} below it), validated "
        f"every {selection.every:,} steps:"
    ]
    for seed in seeds:
        record = trial_folder(directory, Trial(algorithm, seed)) / "selection.json"
        if not record.is_file():
            lines.append(f"- seed {seed}: no record of the validations")
            continue
        saved = json.loads(record.read_text())
        kept, count = saved["kept"], len(saved["evaluations"])
        if kept is None:
            lines.append(f"- seed {seed}: none of {count} validations at the target, the last policy kept")
        else:
            lines.append(
                f"- seed {seed}: kept at {kept['timesteps']:,} steps of {count} validations (validation control "
                f"return {_number(kept['control_return'])} at savings {_number(kept['savings'], 3)})"
            )
    return [*lines, ""]


def _logged_iterations(run: Path) -> int:
    """Rows of a run's logged values (one per logged iteration, :func:`~sb3_detc.plot.open_progress`).

    :param run: the trial folder, holding a ``progress.csv.xz``
    :return: the number of non-empty lines after the header
    """
    with open_progress(run) as file:
        return max(0, sum(1 for line in file if line.strip()) - 1)


def front(spec: Any, summary: dict[str, Any]) -> list[dict[str, Any]]:
    """Control return against savings: every learned trigger and every fixed family at its rate (mean and interval).

    From the evaluations that compared fixed families (``evaluation: fixed_families`` of the study):
    per algorithm, the learned trigger's point and each family's point at the learned rate, the same
    episodes, means over seeds with their 95 % intervals. Algorithms that train with the same
    environment settings share their families' curves.

    :param spec: the study (:class:`~sb3_detc.study.spec.StudySpec`)
    :param summary: the study's statistics (:func:`summarise`)
    :return: one row per algorithm with finished seeds that compared families, as :func:`front_row`
        gives it, in the order of the study
    """
    rows = []
    for algorithm in spec.algorithms:
        entry = summary[algorithm.label]
        if "best_fixed_control_return" not in entry["mean"]:
            continue
        settings = json.dumps(algorithm.entry.get("env_kwargs") or {}, sort_keys=True)
        mean, ci, episodes_ci = entry["mean"], entry["ci95"], entry.get("episodes_ci95")
        rows.append(front_row(algorithm.label, settings, mean, ci, spec.fixed_families, episodes_ci))
    return rows


def front_row(
    label: str,
    settings: str,
    mean: dict[str, float],
    ci: dict[str, Any],
    families: list[str],
    episodes_ci: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One learned trigger's row of a front, from the protocol's metrics averaged over seeds.

    :param label: what learned the trigger (an algorithm of a study, a results file)
    :param settings: its environment settings, as text (rows with the same settings share a panel)
    :param mean: the metrics' means over seeds (the protocol's names: ``savings``, ``control_return``,
        ``fixed_<family>_savings`` ...)
    :param ci: the same metrics' 95 % intervals, (low, high) each
    :param families: the fixed families the evaluation compared
    :param episodes_ci: intervals over seeds and episodes of the differences (:data:`PAIRED`'s metrics), if known
    :return: ``label``, ``settings``, ``points`` (``"learned"``, ``"thresholded"`` where every seed ran
        that mode, and every family -> ``(savings, control return, (low, high))``), and ``difference``
        (learned minus the best family: mean and interval) and, with the thresholded point,
        ``thresholded_difference`` (the same for it); with ``episodes_ci``, ``difference_episodes`` and
        ``thresholded_difference_episodes`` (the intervals over seeds and episodes)
    """
    points = {"learned": (mean["savings"], mean["control_return"], tuple(ci["control_return"]))}
    if "thresholded_control_return" in mean:
        name = "thresholded_control_return"
        points["thresholded"] = (mean["thresholded_savings"], mean[name], tuple(ci[name]))
    for family in families:
        name = f"fixed_{family}_control_return"
        if name in mean and f"fixed_{family}_savings" in mean:
            points[family] = (mean[f"fixed_{family}_savings"], mean[name], tuple(ci[name]))
    row = {"label": label, "settings": settings, "points": points}
    for key, difference, _ in DIFFERENCES:
        if difference in mean:
            row[key] = (mean[difference], tuple(ci[difference]))
            if episodes_ci and difference in episodes_ci:
                row[f"{key}_episodes"] = tuple(episodes_ci[difference])
    return row


def front_markdown(rows: list[dict[str, Any]]) -> str:
    """The front as a Markdown table: control return (95 % interval) and savings, learned triggers and every family.

    :param rows: :func:`front`'s rows
    :return: the table, with the learned (and thresholded) minus the best family's control return per algorithm
        (and its interval over seeds and episodes where the rows have it)
    """
    names = list(dict.fromkeys(name for row in rows for name in [*LEARNED_POINTS, *row["points"]]))
    names = [name for name in names if any(name in row["points"] for row in rows)]
    differences = [
        column
        for key, _, header in DIFFERENCES
        for column in [(key, header), (f"{key}_episodes", f"{header}, over seeds and episodes")]
        if any(column[0] in row for row in rows)
    ]
    header = ["algorithm", *names, *(header for _, header in differences)]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for row in rows:
        cells = [row["label"]]
        for name in names:
            point = row["points"].get(name)
            cells.append("-" if point is None else f"{interval_text(point[1], *point[2])} at {point[0]:.3f}")
        for key, _ in differences:
            if key not in row:
                cells.append("-")
            elif key.endswith("_episodes"):
                cells.append(f"[{row[key][0]:.2f}, {row[key][1]:.2f}]")
            else:
                cells.append(interval_text(row[key][0], *row[key][1]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def report_study(directory: str | Path, plot: bool = True) -> str:
    """Write ``summary.json`` (and the figures) into a study folder and return the Markdown report.

    :param directory: the study folder
    :param plot: draw the training curves of every algorithm (mean and min-max band over
        seeds, curriculum phases dashed) to ``curves.png``, and the final policies' metrics
        (mean, 95 % interval and every seed) to ``estimates.png``
    :return: the report
    :raises StudyError: if the folder is not a study folder
    """
    directory = Path(directory)
    spec = load_folder_study(directory)
    summary = summarise(directory)
    (directory / "summary.json").write_text(json.dumps(summary, separators=(",", ":"), default=str) + "\n")
    text = _markdown(directory, spec, summary)
    rows = front(spec, summary)
    if rows:
        text += (
            "\n## Front: control return against savings\n\nMean control return over seeds [95 % interval] at the "
            "mean savings, the learned trigger and every fixed family matched to its rate on the same episodes.\n\n"
            + front_markdown(rows)
            + "\n"
        )
        if plot:
            text += f"\nFront: {plot_front(rows, directory / 'front.png', title=spec.env)}\n"
    if plot:
        groups, single = {}, []
        for algorithm in spec.algorithms:
            runs = [trial_folder(directory, t) for t in spec.trials() if t.algorithm is algorithm]
            runs = [run for run in runs if progress_file(run) is not None]
            if runs and all(_logged_iterations(run) < 2 for run in runs):
                single.append(algorithm.label)  # no curve to draw
            elif runs:
                groups[algorithm.label] = runs
        if groups:
            figure = plot_runs(groups, directory / "curves.png", title=spec.env, panels=CURVE_PANELS)
            text += f"\nCurves: {figure}\n"
        estimates = {
            label: {
                metric: (
                    entry["mean"][metric],
                    *entry["ci95"][metric],
                    [float(seed_metrics[metric]) for seed_metrics in entry["seeds"].values()],
                )
                for metric, _ in ESTIMATE_PANELS
                if metric in entry["mean"]
            }
            for label, entry in summary.items()
            if label != "comparisons" and entry["seeds"]
        }
        if estimates:
            figure = plot_estimates(estimates, directory / "estimates.png", ESTIMATE_PANELS, title=spec.env)
            text += f"\nFinal policies: {figure}\n"
        if single:
            text += f"\nNot drawn (trained one iteration): {', '.join(single)}.\n"
    return text


def interval_text(mean: float, low: float, high: float, digits: int = 2, unit: str = "") -> str:
    """A mean and its 95 % interval as ``mean [low, high]``.

    :param mean: the mean
    :param low: the interval's lower end
    :param high: the interval's upper end
    :param digits: decimals shown
    :param unit: text after the mean (e.g. ``" %"``)
    :return: the text
    """
    return f"{mean:.{digits}f}{unit} [{low:.{digits}f}, {high:.{digits}f}]"


def mark_lines(name: str) -> tuple[str, str]:
    """The two lines of a Markdown page between which :func:`splice` puts generated text.

    :param name: the name in the marks (the generating command, say)
    :return: the start mark and the end mark
    """
    return f"<!-- {name}: start -->", f"<!-- {name}: end -->"


def splice_marks(path: str | Path, name: str) -> tuple[list[str], int, int]:
    """A Markdown page's lines and where its marks ``<!-- name: start -->`` and ``<!-- name: end -->`` are.

    Check a page with it before long work whose result goes there (:func:`splice`).

    :param path: the Markdown file
    :param name: the name in the two marks
    :return: the page's lines (with their line ends), the index of the start mark and of the end mark
    :raises StudyError: if the file cannot be read as text, or lacks the two lines, in this order, once each
    """
    path = Path(path)
    start, end = mark_lines(name)
    try:
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    except (OSError, UnicodeDecodeError) as error:
        raise StudyError(f"{path}: cannot be read as a text page ({error})") from error
    marks = [i for i, line in enumerate(lines) if line.strip() in (start, end)]
    if [lines[i].strip() for i in marks] != [start, end]:
        raise StudyError(f"{path}: needs the lines {start!r} and {end!r}, in this order, once each")
    return lines, marks[0], marks[1]


def splice(path: str | Path, name: str, text: str) -> None:
    """Put generated text into a Markdown page between the lines ``<!-- name: start -->`` and ``<!-- name: end -->``.

    Splicing the same text again leaves the page as it is, so a results page can be regenerated
    from its study folders whenever seeds finish. The page is replaced at once (through a
    ``.tmp`` file next to it): an interruption leaves it whole.

    :param path: the Markdown file
    :param name: the name in the two marks (the generating command, say)
    :param text: what goes between them
    :raises StudyError: as :func:`splice_marks` (the page is left as it is)
    """
    lines, first, last = splice_marks(path, name)
    page = "".join([*lines[: first + 1], "\n", text, "\n", *lines[last:]])
    replace_atomically(Path(path), lambda scratch: scratch.write_text(page, encoding="utf-8"))
