"""How far overlapping rollouts sample from the policy that each update starts at: a Markdown table.

    python benchmarks/overlap_staleness.py benchmarks/studies/multiwalker_paper \\
        --out benchmarks/results/overlap_staleness.md

With ``overlap_rollouts`` the workers sample the next rollout while the learner updates on the
last one, so every update starts one update ahead of the policy that sampled its data. MAPPOC then
logs, per rollout, ``rollout/sampler_kl_pi`` and ``rollout/sampler_kl_mu``: the estimated KL
divergence between the sampling policy and the update's start, for the control policy and the
policy over options. Next to them, the table puts ``train/kl_pi`` and ``train/kl_mu``: the KL from
the update's start, averaged over the update's gradient steps (the scale of one update's move),
for every trial of the study, with or without overlap.

Per trial (finished or running, from its segments' ``progress.csv``): the median over the logged
iterations and, in brackets, the 90th percentile.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.study.trial import merged_progress, trial_folder

#: The logged columns of the table, in its order.
COLUMNS = ("rollout/sampler_kl_pi", "train/kl_pi", "rollout/sampler_kl_mu", "train/kl_mu")


def _cell(values: np.ndarray) -> str:
    """One cell of the table: ``median [90th percentile]`` of a logged column.

    :param values: the column's logged values (iterations,), without missing ones
    :return: the cell, ``-`` if nothing was logged (values below 1e-6 in size shown as 0)
    """
    if values.size == 0:
        return "-"
    median, high = (0.0 if abs(x) < 1e-6 else x for x in np.percentile(values, [50, 90]))  # float noise of a zero KL
    return f"{median:.2g} [{high:.2g}]"


def staleness_table(folder: Path) -> str:
    """The Markdown table of every trial of a study that has logged ``train/kl_pi``.

    :param folder: the study folder (with its ``study.yml``)
    :return: the table, one row per trial, with a caption line
    :raises StudyError: if the folder holds no ``study.yml`` or no trial logged ``train/kl_pi``
    """
    if not (folder / "study.yml").is_file():
        raise StudyError(f"{folder}: not a study folder (no study.yml)")
    spec = load_folder_study(folder)
    lines = []
    order = [algorithm.label for algorithm in spec.algorithms]
    for trial in sorted(spec.trials(), key=lambda t: (order.index(t.algorithm.label), t.seed)):
        trial_dir = trial_folder(folder, trial)
        progress = merged_progress(trial_dir)
        if "train/kl_pi" not in progress:
            continue
        cells = [_cell(progress[c].dropna().to_numpy() if c in progress else np.array([])) for c in COLUMNS]
        finished = (trial_dir / "evaluation.json").is_file()
        iterations = f"{progress['train/kl_pi'].notna().sum()}{'' if finished else ' (running)'}"
        lines.append(f"| {trial.algorithm.label} | {trial.seed} | {iterations} | " + " | ".join(cells) + " |")
    if not lines:
        raise StudyError(f"{folder}: no trial has logged train/kl_pi yet")
    header = [
        f"Study `{folder.name}`: median [90th percentile] over the logged iterations.",
        "",
        "| algorithm | seed | iterations | " + " | ".join(COLUMNS) + " |",
        "|---|---|---|" + "---|" * len(COLUMNS),
    ]
    return "\n".join(header + lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    """Print the table, and write it to ``--out`` if given.

    :param argv: the command line's arguments (None: ``sys.argv``)
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="the study folder")
    parser.add_argument("--out", type=Path, help="also write the table to this file")
    args = parser.parse_args(argv)
    try:
        table = staleness_table(args.folder)
    except StudyError as error:
        parser.exit(2, f"error: {error}\n")
    print(table, end="")
    if args.out is not None:
        args.out.write_text(table)


if __name__ == "__main__":
    main()
