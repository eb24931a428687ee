"""Run a trained model with rl-zoo3: ``python -m sb3_detc.enjoy --algo mappoc --env ID [rl-zoo3 options]``.

Registers sb3-detc's algorithms with rl-zoo3, checks the input, then runs
``rl_zoo3.enjoy``: it loads the latest run of ``--algo`` on ``--env`` from ``-f`` (default
``logs``, where :mod:`sb3_detc.train` saves) or ``--exp-id``, runs it and prints the
episode returns. sb3-detc's environments draw no window (rendering is off-screen), so
rendering is switched off; videos: :mod:`sb3_detc.record_video`. Environments of other
packages: ``--gym-packages <module>`` imports the module that registers them.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import rl_zoo3.enjoy

from sb3_detc.cli import check_model_arguments, render_modes, run_cli


def _enjoy() -> None:
    """The enjoy command: check ``sys.argv``, add ``--no-render`` for an env without a window, run ``rl_zoo3.enjoy``.

    :raises InputError: on bad input (see :func:`~sb3_detc.cli.check_model_arguments`)
    """
    argv, known = check_model_arguments(sys.argv[1:])
    if "--no-render" not in argv and "human" not in render_modes(known.env):
        print(f"{known.env} does not render in a window: running without rendering (videos: sb3_detc.record_video)")
        argv.append("--no-render")
    sys.argv[1:] = argv
    rl_zoo3.enjoy.enjoy()


def main(argv: Sequence[str] | None = None) -> None:
    """Run the enjoy command line.

    :param argv: rl-zoo3 ``enjoy`` arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.enjoy", _enjoy, argv)


if __name__ == "__main__":
    main()
