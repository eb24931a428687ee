"""Multi-seed studies: ``python -m sb3_detc.study run STUDY.yml --dir DIR`` and ``python -m sb3_detc.study report DIR``.

``run`` trains and evaluates every (algorithm, seed) trial of a study file (``--algorithms``
to run some algorithms' trials only) as a Ray Tune trial (Ray started on this machine, or
``--address`` of a running cluster); running it again skips finished trials and resumes
interrupted ones. ``evaluate DIR`` evaluates the
finished trials again with the current protocol (``--algorithms`` to choose some), rewriting
their ``evaluation.json``. ``report`` prints the tables
and writes ``curves.png``, ``estimates.png`` and ``summary.json`` to the study folder. Study files shipped
with the package can be named without their path (``multiwalker_paper.yml``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from sb3_detc.cli import run_cli
from sb3_detc.study.spec import load_study

#: The study files shipped with the package.
STUDIES_DIR = Path(__file__).resolve().parent.parent / "studies"


def _study_path(name: str) -> Path:
    """The study file of a ``run`` argument: a bare file name not found here is looked up in :data:`STUDIES_DIR`.

    :param name: the study file, or the name of one shipped with the package (``multiwalker_paper.yml``)
    :return: the shipped study file if ``name`` is a bare name of one and no such file exists here, else ``name``
    """
    path = Path(name)
    if not path.is_file() and (STUDIES_DIR / path.name).is_file() and path.parent == Path():
        return STUDIES_DIR / path.name
    return path


def _main() -> None:
    """Run the ``run``, ``evaluate`` or ``report`` command given in ``sys.argv``.

    :raises SystemExit: with code 1 if ``run`` leaves a trial not done (failed, or unfinished after a stop), or
        an evaluation of ``evaluate`` fails
    :raises StudyError: if the folder given to ``evaluate`` or ``report`` is not a study folder (or, for
        ``evaluate``, another run uses it), or an algorithm given to ``run`` or ``evaluate`` is not the study's
    """
    parser = argparse.ArgumentParser(prog="python -m sb3_detc.study", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="run (or continue) the trials of a study")
    run.add_argument("study", help=f"study file (or the name of one in {STUDIES_DIR})")
    run.add_argument("--dir", required=True, type=Path, help="study folder (made if needed)")
    run.add_argument("--address", default=None, help="address of a running Ray cluster, e.g. auto (default: local)")
    run.add_argument(
        "--cpus",
        type=int,
        default=None,
        help="cores Ray hands out on this machine (default: all); more than it has runs more trials at once",
    )
    run.add_argument(
        "--algorithms", nargs="+", default=None, help="labels of the algorithms whose trials to run (default: all)"
    )
    evaluate = commands.add_parser(
        "evaluate", help="evaluate the finished trials of a study folder again with the current protocol"
    )
    evaluate.add_argument("dir", type=Path, help="study folder")
    evaluate.add_argument("--algorithms", nargs="+", default=None, help="labels of the algorithms (default: all)")
    evaluate.add_argument(
        "--cpus", type=int, default=1, help="trials evaluated at once, one core each (default: 1, one after another)"
    )
    report = commands.add_parser("report", help="tables, curves.png, estimates.png and summary.json of a study folder")
    report.add_argument("dir", type=Path, help="study folder")
    report.add_argument("--no-plot", action="store_true", help="do not draw curves.png and estimates.png")
    args = parser.parse_args(sys.argv[1:])
    if args.command == "run":
        from sb3_detc.study.runner import run_study

        study = load_study(_study_path(args.study))
        statuses = run_study(study, args.dir, address=args.address, cpus=args.cpus, labels=args.algorithms)
        if any(status != "done" for status in statuses.values()):
            raise SystemExit(1)
        others = "; the other algorithms' trials: the same command without --algorithms" if args.algorithms else ""
        print(f"[study] done: python -m sb3_detc.study report {args.dir}{others}")
    elif args.command == "evaluate":
        from sb3_detc.study.runner import evaluate_study

        evaluations = evaluate_study(args.dir, args.algorithms, cpus=args.cpus)
        failed = [name for name, evaluation in evaluations.items() if evaluation is None]
        if failed:
            print(f"[study] {len(failed)} evaluation(s) failed: {', '.join(failed)}")
            raise SystemExit(1)
        print(f"[study] evaluated: python -m sb3_detc.study report {args.dir}")
    else:
        from sb3_detc.study.report import report_study

        print(report_study(args.dir, plot=not args.no_plot))


def main(argv: Sequence[str] | None = None) -> None:
    """Run the study command line.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.study", _main, argv)


if __name__ == "__main__":
    main()
