"""A variant study against its base study, seed by seed on the same evaluation episodes.

Both folders must have been evaluated on the same seeded episodes (the same ``evaluation``
settings); every algorithm label of both is compared on the seeds finished in both. Per seed
the control return and savings of both, and the difference of the control return (variant
minus base) averaged over the paired episodes; over seeds its mean with a 95 % stratified
bootstrap interval (rliable, as ``python -m sb3_detc.study report``).

    python benchmarks/study_variant.py benchmarks/studies/linear benchmarks/studies/linear_normalised \\
        --out benchmarks/results/linear_normalised_against_linear.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sb3_detc.study.report import interval_estimates, read_trials
from sb3_detc.study.spec import StudyError


def finished_evaluations(folder: Path) -> tuple[dict, dict[str, dict[int, dict]]]:
    """The study's environment and evaluation settings, and label -> seed -> evaluation of its finished trials.

    :param folder: the study folder
    :return: ``env``, ``episodes`` and ``seed`` (of the first evaluation episode), and label -> seed ->
        ``evaluation.json`` of every finished trial
    """
    spec, evaluations, _ = read_trials(folder)
    return {"env": spec.env, "episodes": spec.episodes, "seed": spec.eval_seed}, evaluations


def compare(base: Path, variant: Path) -> str:
    """Markdown tables of the variant against the base, one per algorithm label of both.

    :param base: the base study folder
    :param variant: the variant study folder
    :return: the Markdown, with a title and one section per label with seeds finished in both
    :raises StudyError: if the studies differ in environment or evaluation episodes
    """
    base_settings, base_runs = finished_evaluations(base)
    variant_settings, variant_runs = finished_evaluations(variant)
    if base_settings != variant_settings:
        raise StudyError(
            f"the studies differ in environment or evaluation episodes: {base_settings} against {variant_settings}"
        )
    lines = [
        f"# {variant.name} against {base.name}",
        "",
        f"{base_settings['env']}, {base_settings['episodes']} evaluation episodes per trial (seeds "
        f"{base_settings['seed']} onwards, the same in both studies); control return per agent and episode; "
        "difference: variant minus base, mean over the paired episodes.",
    ]
    for label in (label for label in base_runs if label in variant_runs):
        seeds = sorted(set(base_runs[label]) & set(variant_runs[label]))
        if not seeds:
            continue
        lines += [
            "",
            f"## {label}",
            "",
            f"| seed | {base.name} control return | savings | {variant.name} control return | savings | difference |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        differences = []
        for seed in seeds:
            old, new = base_runs[label][seed], variant_runs[label][seed]
            paired = np.subtract(new["modes"]["learned"]["control_return"], old["modes"]["learned"]["control_return"])
            differences.append(float(np.mean(paired)))
            lines.append(
                f"| {seed} | {old['metrics']['control_return']:.2f} | {old['metrics']['savings']:.3f} "
                f"| {new['metrics']['control_return']:.2f} | {new['metrics']['savings']:.3f} | {differences[-1]:.2f} |"
            )
        mean, interval = interval_estimates({label: np.array(differences)[:, None]})
        better = sum(d > 0 for d in differences)
        lines += [
            "",
            f"Difference over {len(seeds)} seeds: {mean[label][0]:.2f} [{interval[label][0, 0]:.2f}, "
            f"{interval[label][1, 0]:.2f}]; the variant is better on {better} of {len(seeds)} seeds.",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Print the comparison, and write it to ``--out`` if given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", type=Path, help="the base study folder")
    parser.add_argument("variant", type=Path, help="the variant study folder")
    parser.add_argument("--out", type=Path, default=None, help="also write the tables to this Markdown file")
    args = parser.parse_args()
    try:
        text = compare(args.base, args.variant)
    except StudyError as error:  # not study folders, or studies that cannot be compared
        parser.exit(2, f"error: {error}\n")
    print(text, end="")
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
