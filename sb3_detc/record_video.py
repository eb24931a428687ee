"""Record a video of a trained model with rl-zoo3: ``python -m sb3_detc.record_video --env ID [options]``.

Registers sb3-detc's algorithms with rl-zoo3, checks the input, then runs
``rl_zoo3.record_video`` (options ``-n`` frames, ``-o`` output folder, ``--exp-id``, ...;
default folder ``-f logs``). Multiwalker frames mark every walker's option of the step: a
green disc above a walker that broadcast, a grey ring above a silent one. The video is
written to ``<run folder>/videos/`` unless ``-o`` says otherwise. Environments of other
packages: ``--gym-packages <module>`` imports the module that registers them.
"""

from __future__ import annotations

import runpy
import sys
from collections.abc import Sequence

from sb3_detc.cli import InputError, check_model_arguments, render_modes, run_cli


def _record() -> None:
    """The video command: check ``sys.argv``, then run ``rl_zoo3.record_video`` as a script.

    :raises InputError: on bad input (see :func:`~sb3_detc.cli.check_model_arguments`) or an
        environment without ``rgb_array`` rendering
    """
    argv, known = check_model_arguments(sys.argv[1:])
    if "rgb_array" not in render_modes(known.env):
        raise InputError(f"{known.env} does not render: videos need an environment with render_mode='rgb_array'")
    sys.argv[1:] = argv
    runpy.run_module("rl_zoo3.record_video", run_name="__main__")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the video command line.

    :param argv: rl-zoo3 ``record_video`` arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.record_video", _record, argv)


if __name__ == "__main__":
    main()
