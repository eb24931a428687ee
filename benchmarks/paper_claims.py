"""The paper's Multiwalker claims against a study's finished seeds: a Markdown table.

    python benchmarks/paper_claims.py benchmarks/studies/multiwalker_paper \\
        --out benchmarks/results/paper_claims.md

One row per claim of Kesper, Trimpe and Baumann (L4DC 2023), with our result (mean over the
finished seeds, 95 % stratified-bootstrap interval, every seed) and a verdict by fixed rules,
listed under the table:

* a seed *carries the package* when its package travel is at least half of the travel with
  communication at every step (the same controllers) (:func:`sb3_detc.evaluation.carries_package`, the
  travel part of the study's success criterion); a claim about learning to carry holds when more
  than half of the seeds carry;
* savings are *learned* when the policy over options ends (last logged ``train/entropy_mu``)
  at least :data:`LEARNED_ENTROPY_GAP` nats below the entropy of options drawn independently of
  the state at the same rate;
* timing beats random timing when the interval of learned minus random options at the learned
  rate (control return, paired episodes) lies above zero, loses when below, else no evidence;
* savings are "about 55 %" when their interval reaches 50 to 60 % (:data:`ABOUT_55`);
* "about half of the runs succeed" holds for 30 to 70 % of the seeds succeeding by the study's
  criterion (``success``);
* a recipe saves more when its savings interval lies above the paper's MAPPOC's;
* with ``--rate-study``, a learned trigger beats the fixed triggers when the interval of its control
  return minus that of the best fixed family at the same savings (the same controller and paired
  episodes, ``learned_minus_best_fixed_control_return``) lies above zero, loses when below, else
  no evidence; ``--frozen`` adds the same row for every results file of
  ``multiwalker_trigger_for_controller.py`` (triggers learned for the study's frozen controllers).

``--splice`` replaces the text between the lines ``<!-- paper_claims.py: start -->`` and
``<!-- paper_claims.py: end -->`` of a Markdown file with the table.

The numbers come from the study folder alone (``evaluation.json`` and ``progress.csv.xz`` of every
finished trial), as ``python -m sb3_detc.study report`` computes them.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
from typing import Any

from sb3_detc.plot import open_progress, progress_file
from sb3_detc.study.report import interval_text, mark_lines, metric_estimates, splice, summarise
from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.study.trial import SUCCESS_NO_FALL, SUCCESS_TRAVEL, carries_package, trial_folder

#: How far (nats) below a state-independent trigger's entropy the policy over options must end to count as learned.
LEARNED_ENTROPY_GAP = 0.05
#: Savings that count as "about 55 %": the interval must reach this range.
ABOUT_55 = (0.5, 0.6)
#: Fraction of succeeding seeds that counts as "about half".
ABOUT_HALF = (0.3, 0.7)
#: The name in the marks between which ``--splice`` puts the table (:func:`~sb3_detc.study.report.splice`).
MARK = "paper_claims.py"


def binary_entropy(p: float) -> float:
    """Entropy (nats) of a two-option distribution.

    :param p: probability of one option
    :return: the entropy in nats
    """
    return -sum(q * math.log(q) for q in (p, 1.0 - p) if q > 0.0)


def final_entropies(folder: Path, label: str) -> dict[int, float]:
    """The last logged ``train/entropy_mu`` of every finished trial of an algorithm.

    :param folder: the study folder
    :param label: the algorithm's label
    :return: seed -> final entropy of the policy over options (seeds that logged none are left out)
    :raises StudyError: if a finished trial has no ``progress.csv.xz`` (or ``progress.csv``)
    """
    spec = load_folder_study(folder)
    entropies = {}
    for trial in spec.trials():
        trial_dir = trial_folder(folder, trial)
        if trial.algorithm.label != label or not (trial_dir / "evaluation.json").is_file():
            continue
        if progress_file(trial_dir) is None:
            raise StudyError(f"{trial_dir}: finished, but its progress.csv is missing")
        with open_progress(trial_dir) as file:
            logged = [row["train/entropy_mu"] for row in csv.DictReader(file) if row.get("train/entropy_mu")]
        if logged:
            entropies[trial.seed] = float(logged[-1])
    return entropies


def estimate(entry: dict[str, Any], metric: str, scale: float = 1.0, digits: int = 1, unit: str = "") -> str:
    """A metric over the seeds as ``mean [low, high] (seeds: ...)``.

    :param entry: an algorithm's entry of :func:`~sb3_detc.study.report.summarise`
    :param metric: the metric's name
    :param scale: factor applied to every value (100 for percentages)
    :param digits: decimals shown
    :param unit: text after the mean
    :return: the mean, its 95 % interval and every seed's value
    """
    mean, (low, high) = entry["mean"][metric], entry["ci95"][metric]
    seeds = ", ".join(f"{scale * entry['seeds'][s][metric]:.{digits}f}" for s in sorted(entry["seeds"], key=int))
    return f"{interval_text(scale * mean, scale * low, scale * high, digits, unit)} (seeds: {seeds})"


def carriers(entry: dict[str, Any]) -> int:
    """The number of seeds that carry the package (:func:`~sb3_detc.evaluation.carries_package`).

    :param entry: an algorithm's entry of :func:`~sb3_detc.study.report.summarise`
    :return: how many of its seeds carry
    """
    return sum(carries_package(m) for m in entry["seeds"].values())


def improvement(summary: dict[str, Any], better: str, than: str) -> str:
    """The probability of improvement in control return of one algorithm over another, with its interval.

    :param summary: the study's :func:`~sb3_detc.study.report.summarise`
    :param better: label of the algorithm claimed better
    :param than: label of the other algorithm
    :return: ``P(better > than) = p [low, high]``
    """
    row = next(c for c in summary["comparisons"] if c["better"] == better and c["than"] == than)
    low, high = row["ci95"]
    return f"P({better} > {than}) = {row['probability']:.2f} [{low:.2f}, {high:.2f}]"


def interval_verdict(low: float, high: float) -> str:
    """The verdict on a difference claimed positive, from its 95 % interval.

    :param low: the interval's lower end
    :param high: the interval's upper end
    :return: ``yes`` above zero, ``no`` below, else ``no evidence``, with where the interval lies
    """
    if low > 0:
        return "yes: the interval lies above zero"
    if high < 0:
        return "no: the interval lies below zero"
    return "no evidence: the interval contains zero"


def rate_row(folder: Path, arm: str) -> tuple[str, str, str]:
    """The claims row of a learned trigger at a rate target against the fixed triggers at its savings.

    :param folder: the rate study's folder (its evaluation compares fixed trigger families)
    :param arm: label of the arm whose trigger is learned
    :return: the claim, our result and the verdict
    :raises StudyError: if the arm has no finished seed or its evaluation compared no fixed family
    """
    summary = summarise(folder)
    entry = summary.get(arm, {})
    if not entry.get("seeds"):
        raise StudyError(f"{folder}: no finished seed of {arm!r}")
    if "learned_minus_best_fixed_control_return" not in entry["mean"]:
        raise StudyError(f"{folder}: the evaluation of {arm!r} compared no fixed trigger family")
    spec = load_folder_study(folder)
    others = [c["than"] for c in summary["comparisons"] if c["better"] == arm]
    low, high = entry["ci95"]["learned_minus_best_fixed_control_return"]
    return (
        f"(beyond the paper) a learned trigger beats the best fixed trigger at the same savings ({arm})",
        f"savings {estimate(entry, 'savings', 100, 1, ' %')}, control return {estimate(entry, 'control_return')}; "
        f"minus the best of {', '.join(spec.fixed_families)} with the same controller ({spec.episodes} paired "
        f"episodes per seed) {estimate(entry, 'learned_minus_best_fixed_control_return')}, minus random options "
        f"at the same rate {estimate(entry, 'learned_minus_random_control_return')}"
        + "".join(
            f"; {other}: control return {estimate(summary[other], 'control_return')}, "
            f"{improvement(summary, arm, other)}"
            for other in others
        ),
        f"{interval_verdict(low, high)} ({len(entry['seeds'])} seeds)",
    )


def frozen_row(path: Path) -> tuple[str, str, str]:
    """The claims row of triggers learned for frozen controllers (``multiwalker_trigger_for_controller.py``'s rows).

    :param path: its rows (one per seed), run with ``--fixed-families``
    :return: the claim, our result and the verdict
    :raises StudyError: if the file cannot be read, has no rows or its rows compared no fixed family
    """
    try:
        rows = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise StudyError(f"{path}: {error}") from error
    if not rows or not all("learned_minus_best_fixed_control_return" in row["metrics"] for row in rows):
        raise StudyError(f"{path}: no rows, or rows that compared no fixed trigger family (--fixed-families)")
    mean, ci = metric_estimates([row["metrics"] for row in rows])
    entry = {"mean": mean, "ci95": ci, "seeds": {str(row["seed"]): row["metrics"] for row in rows}}
    job = json.loads(rows[0]["job"])
    target = job["changes"].get("target_savings")
    families = ", ".join(job["fixed_families"])
    return (
        f"(beyond the paper) a trigger learned for the frozen controllers of {job['algorithm']} beats the best fixed "
        f"trigger at the same savings ({path.stem})",
        f"target {target}: savings {estimate(entry, 'savings', 100, 1, ' %')}, control return "
        f"{estimate(entry, 'control_return')}; minus the best of {families} with the same controller "
        f"{estimate(entry, 'learned_minus_best_fixed_control_return')}, minus random options at the same rate "
        f"{estimate(entry, 'learned_minus_random_control_return')}",
        f"{interval_verdict(*ci['learned_minus_best_fixed_control_return'])} ({len(rows)} seeds)",
    )


def claims(
    folder: Path,
    mappoc: str,
    baseline: str,
    recipe: str | None,
    rate_study: Path | None = None,
    rate_arm: str = "",
    frozen: list[Path] | None = None,
) -> str:
    """The claims table (Markdown) of a study folder.

    :param folder: the study folder
    :param mappoc: label of the paper's MAPPOC in the study
    :param baseline: label of the paper's random-skip baseline
    :param recipe: label of a recipe that claims more savings, or None
    :param rate_study: a study of learned triggers at a rate target, or None (its row: :func:`rate_row`)
    :param rate_arm: label of the rate study's arm whose trigger is learned
    :param frozen: results files of triggers learned for frozen controllers (a row each: :func:`frozen_row`)
    :return: the table and the rules of its verdicts
    :raises StudyError: if a named algorithm has no finished seed, or the trials report no package travel
    """
    rate = rate_row(rate_study, rate_arm) if rate_study is not None else None
    frozen_rows = [frozen_row(path) for path in frozen or []]
    summary = summarise(folder)
    episodes = load_folder_study(folder).episodes
    for label in (mappoc, baseline, recipe):
        if label is not None and not summary.get(label, {}).get("seeds"):
            raise StudyError(f"{folder}: no finished seed of {label!r}")
    paper, skips = summary[mappoc], summary[baseline]
    if "package_travel" not in paper["mean"]:
        raise StudyError(f"{folder}: the trials report no package travel (not a Multiwalker study)")
    n, n_skips = len(paper["seeds"]), len(skips["seeds"])
    rows = []

    carried = carriers(paper)
    rows.append(
        (
            "MAPPOC learns to carry the package",
            f"package travel {estimate(paper, 'package_travel')}; communication at every step with the same "
            f"controllers {estimate(paper, 'periodic_package_travel')}; fails (a fall or a dropped package) "
            f"in {estimate(paper, 'fall_rate', 100, 0, ' %')} of the episodes",
            f"{'yes' if carried > n / 2 else 'no'}: {carried} of {n} seeds carry",
        )
    )

    entropies = final_entropies(folder, mappoc)
    savings = paper["mean"]["savings"]
    low, high = paper["ci95"]["savings"]
    learned = [e < binary_entropy(paper["seeds"][s]["savings"]) - LEARNED_ENTROPY_GAP for s, e in entropies.items()]
    listed = ", ".join(f"{entropies[s]:.3f}" for s in sorted(entropies))
    rows.append(
        (
            "... with about 55 % savings, learned",
            f"savings {estimate(paper, 'savings', 100, 0, ' %')}; entropy of the policy over options at the "
            f"end {listed} (options independent of the state at {100 * savings:.0f} %: "
            f"{binary_entropy(savings):.3f})",
            f"savings {'yes' if low <= ABOUT_55[1] and high >= ABOUT_55[0] else 'no'}, learned in "
            f"{sum(learned)} of {len(learned)} seeds",
        )
    )

    rows.append(
        (
            "learned timing beats random timing at the same rate",
            f"control return, learned minus random options at the learned rate ({episodes} paired episodes "
            f"per seed): {estimate(paper, 'learned_minus_random_control_return')}",
            interval_verdict(*paper["ci95"]["learned_minus_random_control_return"]),
        )
    )

    succeeded = paper["success_count"]
    share = succeeded / n
    rows.append(
        (
            "about half of the runs succeed",
            f"{succeeded} of {n} seeds succeed (at least {100 * SUCCESS_NO_FALL:.0f} % of the episodes without a "
            f"fall, package travel at least {SUCCESS_TRAVEL:g} of communication at every step)",
            f"{'yes' if ABOUT_HALF[0] <= share <= ABOUT_HALF[1] else 'no'}: {100 * share:.0f} %",
        )
    )

    carried_skips = carriers(skips)
    rows.append(
        (
            "PPO with random skips (about 50 %) cannot learn a good policy",
            f"the baseline at {estimate(skips, 'savings', 100, 0, ' %')} skips: package travel "
            f"{estimate(skips, 'package_travel')}, control return {estimate(skips, 'control_return')}, "
            f"fails in {estimate(skips, 'fall_rate', 100, 0, ' %')} of the episodes, {skips['success_count']} "
            f"of {n_skips} seeds succeed; the paper's MAPPOC: control return "
            f"{estimate(paper, 'control_return')}, {improvement(summary, mappoc, baseline)}",
            f"{'no' if carried_skips > n_skips / 2 else 'yes'}: {carried_skips} of {n_skips} baseline seeds carry",
        )
    )

    if recipe is not None:
        first = summary[recipe]
        more = first["ci95"]["savings"][0] > paper["ci95"]["savings"][1]
        rows.append(
            (
                f"(beyond the paper) {recipe} saves more",
                f"savings {estimate(first, 'savings', 100, 0, ' %')}, control return "
                f"{estimate(first, 'control_return')}, package travel {estimate(first, 'package_travel')}, fails "
                f"in {estimate(first, 'fall_rate', 100, 0, ' %')}; learned minus random at the learned rate "
                f"{estimate(first, 'learned_minus_random_control_return')}, never broadcasting "
                f"{estimate(first, 'never_control_return')}; {improvement(summary, recipe, mappoc)}",
                f"savings {'yes' if more else 'no'}; {carriers(first)} of {len(first['seeds'])} seeds carry, "
                f"{first['success_count']} succeed",
            )
        )

    if rate is not None:
        rows.append(rate)
    rows.extend(frozen_rows)

    lines = [
        f"Study `{folder.name}`: {n} seeds of {mappoc}, {n_skips} of {baseline}"
        + (f", {len(summary[recipe]['seeds'])} of {recipe}" if recipe else "")
        + (f"; study `{rate_study.name}`: its arm {rate_arm}" if rate_study is not None else "")
        + (f"; triggers for frozen controllers: {', '.join(f'`{p.name}`' for p in frozen)}" if frozen else "")
        + "; mean [95 % interval] (seeds: each seed's value).",
        "",
        "| paper claim | our result | holds? |",
        "|---|---|---|",
        *(f"| {claim} | {result} | {verdict} |" for claim, result, verdict in rows),
        "",
        "Verdicts:",
        "",
        f"* a seed carries the package when its package travel is at least {SUCCESS_TRAVEL:g} of the travel with "
        "communication at every step (same controllers); an algorithm learns to carry when more than half of its "
        "seeds do;",
        f"* savings are learned when the policy over options ends at least {LEARNED_ENTROPY_GAP} nats below the "
        "entropy of state-independent options at the same rate;",
        f"* savings are about 55 % when their interval reaches {100 * ABOUT_55[0]:.0f} % to {100 * ABOUT_55[1]:.0f} %;",
        "* learned timing beats random timing when the interval of the difference lies above zero;",
        f"* about half is {100 * ABOUT_HALF[0]:.0f} % to {100 * ABOUT_HALF[1]:.0f} % of the seeds;",
        "* a recipe saves more when its savings interval lies above the paper's MAPPOC's;",
        "* a learned trigger beats the fixed triggers when the interval of its control return minus that of the "
        "best fixed family tuned to its savings (the same controller and episodes) lies above zero;",
        "* P(a > b) is the probability of improvement in control return (rliable): that a seed of a has the "
        "higher control return than a seed of b.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Print the claims table of a study folder, and write it to ``--out`` and splice it into ``--splice`` if given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="the study folder")
    parser.add_argument("--mappoc", default="mappoc_paper", help="label of the paper's MAPPOC")
    parser.add_argument("--baseline", default="random_skip_paper", help="label of the paper's random-skip baseline")
    parser.add_argument(
        "--recipe", default="control_first", help="label of a recipe claiming more savings ('' for none)"
    )
    parser.add_argument(
        "--rate-study", type=Path, help="add the row of a learned trigger at a rate target from this study folder"
    )
    parser.add_argument("--rate-arm", default="joint_9375", help="label of the rate study's learned trigger")
    parser.add_argument(
        "--frozen",
        type=Path,
        nargs="+",
        default=[],
        help="add a row per results file of multiwalker_trigger_for_controller.py (with --fixed-families)",
    )
    parser.add_argument("--out", type=Path, help="also write the table to this file")
    parser.add_argument(
        "--splice",
        type=Path,
        help="put the table between the lines {!r} and {!r} of this file".format(*mark_lines(MARK)),
    )
    args = parser.parse_args()
    try:
        table = claims(
            args.folder, args.mappoc, args.baseline, args.recipe or None, args.rate_study, args.rate_arm, args.frozen
        )
        if args.splice:
            splice(args.splice, MARK, table)
    except StudyError as error:
        parser.exit(2, f"error: {error}\n")
    print(table, end="")
    if args.out:
        args.out.write_text(table)


if __name__ == "__main__":
    main()
