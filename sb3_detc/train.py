"""Train with rl-zoo3: ``python -m sb3_detc.train --algo mappoc --env sb3_detc/LinearETC-v0 [rl-zoo3 options]``.

Registers sb3-detc's algorithms with rl-zoo3 (:func:`sb3_detc.zoo.register`), checks the
input, then runs ``rl_zoo3.train``: every rl-zoo3 training option works (``-n``,
``--seed``, ``-conf``, ``--eval-freq``, ``--save-freq``, ``-i``, ``--optimize``,
``--tensorboard-log``, ``--progress``, ``--gym-packages``, ...). Defaults: ``--algo mappoc``,
``--env sb3_detc/LinearETC-v0`` and the package's hyperparameter file of the algorithm. Runs
are saved to ``logs/<algo>/<env>_<run id>/`` with the logger's values in ``progress.csv``.
Bad input ends the command with one line on stderr and exit code 2; an error while training
ends it with its traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import rl_zoo3.train

from sb3_detc.cli import check_train_arguments, run_cli
from sb3_detc.zoo import ExperimentManager


def _train() -> None:
    """The training command: check ``sys.argv``, complete it with the defaults and run ``rl_zoo3.train``.

    rl-zoo3 builds its runs with :class:`~sb3_detc.zoo.ExperimentManager` meanwhile.

    :raises InputError: on bad input (see :func:`~sb3_detc.cli.check_train_arguments`)
    """
    sys.argv[1:] = check_train_arguments(sys.argv[1:])
    stock = rl_zoo3.train.ExperimentManager
    rl_zoo3.train.ExperimentManager = ExperimentManager  # rl-zoo3's train() builds it from its module
    try:
        rl_zoo3.train.train()
    finally:
        rl_zoo3.train.ExperimentManager = stock


def main(argv: Sequence[str] | None = None) -> None:
    """Run the training command line.

    :param argv: rl-zoo3 training arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.train", _train, argv)


if __name__ == "__main__":
    main()
