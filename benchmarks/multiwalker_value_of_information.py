"""What a message is worth on Multiwalker: the final controllers of a study under fixed triggers.

Every finished trial of a study folder (``policy.pt``) runs the study's seeded evaluation
episodes (the same for every controller and trigger) with its deterministic control policy
and, instead of its own options, random skips at several rates, periodic communication
every ``k`` steps and send-on-delta (a walker broadcasts when the package, as it sees it, moved
more than ``delta`` since its last broadcast). Its learned trigger comes from the trial's
``evaluation.json`` (the same episodes, options sampled from its policy over options); a trial
that learned its options also runs with the most likely option of its policy over options
(``mode of mu``: what ``predict(deterministic=True)`` does for a policy without ``sample_options``). For
every algorithm of the study and every trigger: control return (without the communication
cost), package travel, savings and fall rate, mean over seeds with a 95 % bootstrap interval
(:func:`sb3_detc.study.report.interval_estimates`).

Results are written after every (trial, trigger) to ``--out`` (JSON); running the command
again skips what is there, so an interrupted sweep goes on where it stopped. ``--plot`` draws
control return and package travel against savings; ``--splice PAGE`` puts the algorithms
(``--columns``, default all) side by side into a results page, between the lines
``<!-- multiwalker_value_of_information.py: start -->`` and ``... end -->``.

    python benchmarks/multiwalker_value_of_information.py benchmarks/studies/multiwalker_paper \\
        --out benchmarks/results/multiwalker_value_of_information.json --plot \\
        --splice benchmarks/README.md --columns mappoc_paper random_skip_paper control_first
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.report import interval_estimates, interval_text, mark_lines, splice, splice_marks
from sb3_detc.study.spec import StudyError, entry_fixed_trigger, load_folder_study
from sb3_detc.study.trial import read_status, trial_folder
from sb3_detc.triggers import PeriodicTrigger, RandomTrigger, SendOnDelta

#: Skip probabilities of the random triggers.
RATES = (0.0, 0.25, 0.5, 0.75, 0.85, 0.9, 0.95, 1.0)
#: Periods of the periodic triggers (savings 1 - 1/k).
PERIODS = (2, 4, 8, 16, 32)
#: Thresholds of the send-on-delta triggers, in the units of the trigger features (the package relative to the
#: walker: dx and dy divided by the package length, and its angle); their savings depend on the controller.
DELTAS = (0.01, 0.02, 0.04, 0.08)
#: Name of the row of the policy over options' most likely options.
MODE = "mode of mu"
#: The name in the marks between which ``--splice`` puts the side-by-side table.
MARK = "multiwalker_value_of_information.py"


def triggers(rates: list[float], periods: list[int], deltas: list[float], seed: int) -> dict[str, Any]:
    """The fixed triggers of the sweep by name (random ones seeded with ``seed``).

    :param rates: skip probabilities of the random triggers (``random <rate>``)
    :param periods: periods in steps of the periodic triggers (``periodic <k>``)
    :param deltas: thresholds of the send-on-delta triggers (``send-on-delta <delta>``)
    :param seed: seed of every random trigger (the study's ``eval_seed``)
    :return: trigger name -> trigger
    """
    named: dict[str, Any] = {f"random {rate:g}": RandomTrigger(rate, seed=seed) for rate in rates}
    named.update({f"periodic {k}": PeriodicTrigger(k) for k in periods})
    named.update({f"send-on-delta {delta:g}": SendOnDelta(delta) for delta in deltas})
    return named


def row(control_returns: Any, package_travel: Any, failed: Any, savings: float) -> dict[str, float]:
    """Means of one controller's episodes under one trigger (package travel None or NaN where not reported).

    :param control_returns: every episode's team-mean return without the communication cost (episodes,)
    :param package_travel: every episode's package travel (episodes,), None or NaN where not reported
    :param failed: whether each episode ended by a fall or a dropped package (episodes,)
    :param savings: communication savings over all the episodes
    :return: ``control_return``, ``package_travel``, ``fall_rate`` and ``savings``
    """
    travel = [math.nan if x is None else x for x in package_travel]
    return {
        "control_return": float(np.mean(control_returns)),
        "package_travel": float(np.mean(travel)),
        "fall_rate": float(np.mean(failed)),
        "savings": float(savings),
    }


def sweep(
    folder: Path,
    out: Path,
    rates: list[float],
    periods: list[int],
    deltas: list[float],
    algorithms: list[str] | None = None,
) -> dict[str, Any]:
    """Evaluate every finished trial under every trigger not in ``out`` yet; return all results.

    :param folder: the study folder
    :param out: the JSON file of results (read first, written after every evaluation)
    :param rates: skip probabilities of the random triggers
    :param periods: periods of the periodic triggers
    :param deltas: thresholds of the send-on-delta triggers
    :param algorithms: the labels of the algorithms whose trials to evaluate (None: all)
    :return: trial name -> trigger name -> metrics
    """
    spec = load_folder_study(folder)
    results = read_results(out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def write() -> None:  # at once: an interruption leaves the results of the evaluations before
        replace_atomically(out, lambda scratch: scratch.write_text(json.dumps(results, indent=1) + "\n"))

    for trial in spec.trials():
        if algorithms is not None and trial.algorithm.label not in algorithms:
            continue
        trial_dir = trial_folder(folder, trial)
        if read_status(trial_dir)["status"] != "done" or not (trial_dir / "policy.pt").is_file():
            continue
        done = results.setdefault(trial.name, {})
        evaluation = json.loads((trial_dir / "evaluation.json").read_text())
        learned = evaluation["modes"]["learned"]
        done["learned"] = row(
            learned["control_return"], learned["package_travel"], learned["failed"], learned["savings"]
        )
        named = triggers(rates, periods, deltas, spec.eval_seed)
        if entry_fixed_trigger(trial.algorithm.entry) is None:
            named[MODE] = None  # no fixed trigger: the policy's own options, their mode (below)
        todo = {name: t for name, t in named.items() if name not in done}
        if not todo:
            continue
        policy = MlpHybridPolicy.load(str(trial_dir / "policy.pt"), device="cpu")
        env = gym.make(spec.env, **(trial.algorithm.entry.get("env_kwargs") or {}))
        seeds = [spec.eval_seed + k for k in range(spec.episodes)]
        for name, trigger in todo.items():
            began = time.monotonic()
            episodes = evaluate_episodes(
                policy, env, seeds, deterministic=True, sample_options=name != MODE, fixed_trigger=trigger
            )
            done[name] = row(episodes.control_returns, episodes.package_travel, episodes.failed, episodes.savings)
            write()
            print(
                f"{trial.name} {name}: control return {done[name]['control_return']:.1f}, package travel "
                f"{done[name]['package_travel']:.2f}, savings {done[name]['savings']:.3f} "
                f"({time.monotonic() - began:.0f} s)",
                flush=True,
            )
        env.close()
    write()
    return results


def read_results(out: Path) -> dict[str, Any]:
    """The results of an earlier sweep (none if ``out`` does not exist).

    :param out: the JSON file of results
    :return: trial name -> trigger name -> metrics
    :raises StudyError: if the file is not such a JSON object
    """
    if not out.is_file():
        return {}
    try:
        results = json.loads(out.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise StudyError(f"{out}: not the JSON of an earlier sweep ({error}); give another --out") from None
    if not isinstance(results, dict):
        raise StudyError(f"{out}: not the JSON of an earlier sweep (not an object); give another --out")
    return results


def summary(folder: Path, results: dict[str, Any]) -> dict[str, dict[str, dict[str, list[float]]]]:
    """Algorithm -> trigger -> metric -> [mean, low, high] over the seeds that have it.

    :param folder: the study folder
    :param results: trial name -> trigger name -> metrics (:func:`sweep`)
    :return: label -> trigger -> metric -> [mean, low, high] (95 % bootstrap interval), and under
        ``seeds`` the number of seeds as ``[n]``; algorithms without results are left out
    """
    spec = load_folder_study(folder)
    table: dict[str, dict[str, dict[str, list[float]]]] = {}
    metrics = ("control_return", "package_travel", "savings", "fall_rate")
    for algorithm in spec.algorithms:
        names = [t.name for t in spec.trials() if t.algorithm is algorithm and t.name in results]
        if not names:
            continue
        table[algorithm.label] = {}
        for trigger in dict.fromkeys(t for n in names for t in results[n]):  # every seed's, in order
            values = np.array([[results[n][trigger][m] for m in metrics] for n in names if trigger in results[n]])
            means, intervals = interval_estimates({"x": values})
            table[algorithm.label][trigger] = {
                m: [float(means["x"][k]), float(intervals["x"][0, k]), float(intervals["x"][1, k])]
                for k, m in enumerate(metrics)
            } | {"seeds": [float(len(values))]}
    return table


def estimate(values: dict[str, list[float]], metric: str, digits: int) -> str:
    """One metric as ``mean [low, high]``.

    :param values: one algorithm's results under one trigger (a row of :func:`summary`)
    :param metric: the metric
    :param digits: digits after the decimal point
    :return: the text, e.g. ``507.6 [402.2, 613.0]``
    """
    return interval_text(*values[metric], digits)


def markdown(table: dict[str, dict[str, dict[str, list[float]]]]) -> str:
    """One Markdown table per algorithm: trigger, seeds, savings, control return, package travel, fall rate.

    :param table: the summary (:func:`summary`)
    :return: the tables, rows sorted by savings
    """
    lines = []
    for label, rows in table.items():
        lines += [
            f"### {label}",
            "",
            "| trigger | seeds | savings | control return | package travel | fall rate |",
            "|---|---:|---|---|---|---|",
        ]
        for trigger, values in sorted(rows.items(), key=lambda item: item[1]["savings"][0]):
            lines.append(
                f"| {trigger} | {int(values['seeds'][0])} | {estimate(values, 'savings', 3)} "
                f"| {estimate(values, 'control_return', 1)} | {estimate(values, 'package_travel', 2)} "
                f"| {estimate(values, 'fall_rate', 2)} |"
            )
        lines.append("")
    return "\n".join(lines)


#: Savings from which the lower panels of the figure show the results (where timing matters).
ZOOM = 0.75
#: Savings of one trigger that differ more than this between algorithms are shown in every cell.
SAVINGS_DIFFER = 0.005
#: Names on the results page of the fixed triggers that never and always skip.
PAGE_NAMES = {"random 0": "every step", "random 1": "never"}


def _seeds(n: int) -> str:
    """``"1 seed"``, ``"2 seeds"``, ...

    :param n: the number of seeds
    """
    return f"{n} seed{'s' * (n != 1)}"


def page_table(table: dict[str, dict[str, dict[str, list[float]]]], labels: list[str], episodes: int) -> str:
    """The algorithms side by side: one row per trigger, sorted by savings, for the results page.

    A cell holds the control return, mean [95 % interval] over the algorithm's seeds, and in
    parentheses package travel ("n/a" where the env reports none) and fall rate (then the
    algorithm's savings if a trigger's savings differ between the columns by more than
    :data:`SAVINGS_DIFFER`, as send-on-delta's do, and the number of seeds where fewer than the
    algorithm's own have the trigger). The fixed triggers' savings are the mean over the columns;
    ``random 0`` and ``random 1`` are named as in :data:`PAGE_NAMES`. Each algorithm's own options
    ("learned", "mode of mu") have a row of their own, with its savings.

    :param table: the summary (:func:`summary`)
    :param labels: the algorithms to show, in this order
    :param episodes: the number of evaluation episodes (for the text above the table)
    :return: Markdown
    :raises StudyError: if there is no algorithm to show, one is named twice or has no results
    """
    if not labels:
        raise StudyError("no results to put on the page")
    if len(set(labels)) < len(labels):
        raise StudyError(f"an algorithm named twice among {', '.join(labels)}")
    missing = [label for label in labels if label not in table]
    if missing:
        raise StudyError(f"no results of {', '.join(missing)}")
    seeds = {label: max(int(v["seeds"][0]) for v in table[label].values()) for label in labels}
    own = ("learned", MODE)

    def savings(trigger: str) -> list[float]:
        return [table[label][trigger]["savings"][0] for label in labels if trigger in table[label]]

    def cell(label: str, trigger: str) -> str:
        values = table[label].get(trigger)
        if values is None:
            return ""
        travel = values["package_travel"][0]
        extra = ""
        if trigger not in own and np.ptp(savings(trigger)) > SAVINGS_DIFFER:
            extra += f", savings {values['savings'][0]:.3f}"
        if values["seeds"][0] < seeds[label]:
            extra += f", {_seeds(int(values['seeds'][0]))}"
        return (
            f"{estimate(values, 'control_return', 1)} "
            f"({'n/a' if math.isnan(travel) else f'{travel:.2f}'}, {values['fall_rate'][0]:.2f}{extra})"
        )

    shared = dict.fromkeys(t for label in labels for t in table[label] if t not in own)
    rows = [(float(np.mean(savings(t))), PAGE_NAMES.get(t, t), [cell(label, t) for label in labels]) for t in shared]
    rows += [
        (
            table[label][t]["savings"][0],
            f"{t} ({label})",
            [cell(label, t) if other == label else "" for other in labels],
        )
        for label in labels
        for t in own
        if t in table[label]
    ]
    lines = [
        f"Control return, mean [95 % interval] over seeds (package travel, fall rate), on the same {episodes} "
        "episodes; savings of a fixed trigger: mean over the columns.",
        "",
        "| trigger | savings | " + " | ".join(f"`{label}` ({_seeds(seeds[label])})" for label in labels) + " |",
        "|---|---:|" + "---|" * len(labels),
    ]
    lines += [f"| {name} | {savings:.3f} | " + " | ".join(cells) + " |" for savings, name, cells in sorted(rows)]
    return "\n".join(lines) + "\n"


def plot(table: dict[str, dict[str, dict[str, list[float]]]], path: Path) -> None:
    """Control return and package travel against savings, over all savings and from :data:`ZOOM` on.

    Random skips and send-on-delta are lines, periodic messages, learned options and their mode markers.

    :param table: the summary (:func:`summary`)
    :param path: the PNG to write
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    metrics = (("control_return", "control return"), ("package_travel", "package travel"))
    zoomed: list[list[float]] = [[], []]  # per metric: the interval ends of every point from ZOOM on
    for (label, rows), color in zip(table.items(), plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False):
        kinds = {
            "random": sorted((v for k, v in rows.items() if k.startswith("random")), key=lambda v: v["savings"][0]),
            "periodic": [v for k, v in rows.items() if k.startswith("periodic")],
            "send-on-delta": sorted(
                (v for k, v in rows.items() if k.startswith("send-on-delta")), key=lambda v: v["savings"][0]
            ),
            "learned": [rows["learned"]] if "learned" in rows else [],
            MODE: [rows[MODE]] if MODE in rows else [],
        }
        for kind, style in (
            ("random", "-o"),
            ("periodic", "s"),
            ("send-on-delta", ":^"),
            ("learned", "*"),
            (MODE, "X"),
        ):
            values = kinds[kind]
            if not values:
                continue
            x = np.array([v["savings"][0] for v in values])
            for column, (metric, _) in enumerate(metrics):
                y = np.array([v[metric] for v in values])
                zoomed[column] += [*y[x >= ZOOM, 1], *y[x >= ZOOM, 2]]
                for ax in axes[:, column]:
                    ax.errorbar(
                        x,
                        y[:, 0],
                        yerr=[y[:, 0] - y[:, 1], y[:, 2] - y[:, 0]],
                        fmt=style,
                        color=color,
                        markersize=10 if kind in ("learned", MODE) else 5,
                        capsize=2,
                        label=f"{label}: {kind}",
                    )
    for column, (_, name) in enumerate(metrics):
        for ax in axes[:, column]:
            ax.set_xlabel("communication savings")
            ax.set_ylabel(name)
        shown = [end for end in zoomed[column] if np.isfinite(end)]  # NaN: a metric the env does not report
        if shown:
            low, high = min(shown), max(shown)
            margin = 0.05 * (high - low) or 1.0
            axes[1, column].set_ylim(low - margin, high + margin)
        axes[1, column].set_xlim(ZOOM - 0.01, 1.01)
        axes[1, column].set_title(f"savings from {ZOOM:g} on", fontsize=9)
    axes[0, 1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the data, not over it
    fig.suptitle("Multiwalker: final controllers under fixed triggers (mean over seeds, 95 % CI)")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    """Sweep the triggers, print the tables, draw the figure and splice the page if asked."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a study folder with finished trials")
    parser.add_argument("--out", type=Path, required=True, help="JSON file of the results (resumed if present)")
    for flag, default, what in (
        ("--rates", RATES, "skip probabilities"),
        ("--deltas", DELTAS, "send-on-delta thresholds"),
    ):
        parser.add_argument(
            flag, type=float, nargs="*", default=list(default), help=f"{what} (none given: evaluate no new ones)"
        )
    parser.add_argument("--periods", type=int, nargs="+", default=list(PERIODS), help="periods in steps")
    parser.add_argument(
        "--algorithms", nargs="+", help="labels of the algorithms whose trials to evaluate (default: all)"
    )
    parser.add_argument("--plot", action="store_true", help="draw <out>.png")
    parser.add_argument(
        "--splice",
        type=Path,
        help="put the algorithms side by side between the lines {!r} and {!r} of this file".format(*mark_lines(MARK)),
    )
    parser.add_argument(
        "--columns", nargs="+", help="with --splice: the algorithms side by side (default: all with results)"
    )
    args = parser.parse_args()
    try:  # the triggers check their own settings
        triggers(args.rates, args.periods, args.deltas, seed=0)
    except ValueError as error:
        parser.error(str(error))
    if args.columns and not args.splice:
        parser.error("--columns needs --splice")
    try:  # what can be checked before the sweep
        spec = load_folder_study(args.folder)
        named = set(args.columns or []) | set(args.algorithms or [])
        unknown = sorted(named - {algorithm.label for algorithm in spec.algorithms})
        if unknown:
            raise StudyError(f"{args.folder}: no algorithm {', '.join(unknown)} in the study")
        if args.splice:
            splice_marks(args.splice, MARK)
        read_results(args.out)
    except StudyError as error:
        parser.exit(2, f"error: {error}\n")
    th.set_num_threads(1)
    results = sweep(args.folder, args.out, args.rates, args.periods, args.deltas, args.algorithms)
    table = summary(args.folder, results)
    print(markdown(table))
    if args.plot and table:
        plot(table, args.out.with_suffix(".png"))
        print(f"Figure: {args.out.with_suffix('.png')}")
    if args.splice:
        try:
            splice(args.splice, MARK, page_table(table, args.columns or list(table), spec.episodes))
        except StudyError as error:
            parser.exit(2, f"error: {error}\n")
        print(f"Spliced into {args.splice}")


if __name__ == "__main__":
    main()
