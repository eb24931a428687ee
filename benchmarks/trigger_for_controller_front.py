"""The front of triggers learned for frozen controllers: control return against savings, over seeds.

Every results file of ``multiwalker_trigger_for_controller.py`` run with ``--fixed-families`` (one
row per seed) is one learned trigger: its point is the mean over seeds of the learned savings
and control return with its 95 % bootstrap interval, and every compared family's point the mean
at the savings it was tuned to on the same episodes (as ``study report`` draws a study's front,
:func:`sb3_detc.study.report.front_row`). Files with the same environment settings share a
panel, in which the families' points are joined in the order of their savings. Prints the front
as a Markdown table and writes the figure.

    python benchmarks/trigger_for_controller_front.py benchmarks/results/multiwalker_trigger_rate_875.json \\
        benchmarks/results/multiwalker_trigger_rate_9375.json --out benchmarks/results/multiwalker_trigger_front.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from sb3_detc.plot import plot_front
from sb3_detc.study.report import front_markdown, front_row, metric_estimates
from sb3_detc.triggers import TRIGGER_FAMILIES


def file_row(label: str, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One results file's row of the front: the metrics every seed has, averaged, with their intervals (as a study's).

    :param label: the file's name in the front
    :param rows: its rows (one per seed), each with ``metrics`` and ``env_kwargs``
    :return: :func:`~sb3_detc.study.report.front_row` of the file
    :raises ValueError: for no rows, rows of other environment settings, or rows that compared no family
    """
    if not rows:
        raise ValueError(f"{label} has no rows.")
    settings = {json.dumps(row["env_kwargs"], sort_keys=True) for row in rows}
    if len(settings) > 1:
        raise ValueError(f"the rows of {label} were evaluated with different environment settings: {sorted(settings)}")
    mean, ci = metric_estimates([row["metrics"] for row in rows])
    families = [f for f in TRIGGER_FAMILIES if f"fixed_{f}_control_return" in mean]
    if not families:
        raise ValueError(f"the rows of {label} compared no fixed family (--fixed-families).")
    return front_row(f"{label} ({len(rows)} seeds)", settings.pop(), mean, ci, families)


def main() -> None:
    """Read the files, print the front's table and draw it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", type=Path, nargs="+", help="rows of multiwalker_trigger_for_controller.py")
    parser.add_argument("--labels", nargs="+", help="a name per file (default: the file's stem)")
    parser.add_argument("--out", type=Path, required=True, help="the figure (PNG)")
    parser.add_argument("--title", default="Triggers learned for frozen controllers", help="the figure's title")
    args = parser.parse_args()
    labels = args.labels or [path.stem for path in args.files]
    if len(labels) != len(args.files):
        parser.error(f"--labels names {len(labels)} files, {len(args.files)} given")
    try:
        rows = [file_row(label, json.loads(path.read_text())) for label, path in zip(labels, args.files, strict=True)]
    except (OSError, ValueError) as error:
        parser.error(str(error))
    print(front_markdown(rows))
    print(f"\nfigure: {plot_front(rows, args.out, args.title)}")


if __name__ == "__main__":
    main()
