"""rl-baselines3-zoo integration: algorithm names, hyperparameter files and the experiment manager.

:func:`register` adds sb3-detc's algorithms to rl-zoo3 (``rl_zoo3.utils.ALGOS``) together with
Optuna samplers for ``--optimize``; the command lines (:func:`sb3_detc.cli.run_cli`) and
:class:`ExperimentManager` call it, importing this module does not:

* ``mappoc``: :class:`~sb3_detc.MAPPOC`, hyperparameters in ``hyperparams/mappoc.yml``;
* ``ppo_random_skip``: the paper's random-skip baseline, also :class:`~sb3_detc.MAPPOC`
  but trained with :class:`~sb3_detc.callbacks.RandomSkipCallback`
  (``hyperparams/ppo_random_skip.yml``); its runs are logged under its own name.

Every run writes the SB3 logger's values to ``progress.csv`` in its log folder
(:class:`ExperimentManager`), which :mod:`sb3_detc.plot` reads. The command lines check their
input in :mod:`sb3_detc.cli` before they hand over to rl-zoo3.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import optuna
import rl_zoo3.exp_manager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import ALGOS
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat
from stable_baselines3.common.vec_env import SubprocVecEnv, VecEnv

from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.critics import CRITICS

__all__ = [
    "ALGORITHMS",
    "HYPERPARAMS_DIR",
    "CSVLogCallback",
    "ExperimentManager",
    "convert_mappoc_params",
    "register",
    "uses_rollout_workers",
    "sample_mappoc_params",
]

#: rl-zoo3 algorithm names of sb3-detc and their classes.
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mappoc": MAPPOC, "ppo_random_skip": MAPPOC}

#: Folder of the hyperparameter files shipped with the package, one per algorithm name.
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"

#: Import path of the rollout-worker env wrapper (an entry naming it as ``env_wrapper`` runs in worker processes).
ROLLOUT_WORKER = "sb3_detc.mappoc.workers.RolloutWorker"

#: Network sizes the Optuna sampler chooses from (the paper's is ``paper``).
NET_ARCHS = {"small": [64, 64], "medium": [128, 128], "paper": [96, 96, 96]}


# ----------------------------------------------------------------------------- registration
def sample_mappoc_params(
    trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict[str, Any]
) -> dict[str, Any]:
    """Optuna sampler of MAPPOC hyperparameters (rl-zoo3's sampler signature).

    :param trial: the Optuna trial
    :param n_actions: size of a Box action space (unused: the joint action space is a Dict)
    :param n_envs: number of training environments (the minibatch is at most one rollout)
    :param additional_args: rl-zoo3's extra arguments (unused)
    :return: keyword arguments of :class:`~sb3_detc.MAPPOC`
    """
    params = {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "n_steps": trial.suggest_categorical("n_steps", [128, 256, 512, 1024, 2048]),
        "batch_size": trial.suggest_categorical("batch_size", [32, 64, 128, 256]),
        "n_epochs": trial.suggest_categorical("n_epochs", [5, 10, 20]),
        "gamma": trial.suggest_categorical("gamma", [0.95, 0.98, 0.99, 0.995]),
        "gae_lambda": trial.suggest_categorical("gae_lambda", [0.9, 0.95, 0.98]),
        "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3]),
        "clip_range_broadcast": trial.suggest_categorical("clip_range_broadcast", [0.1, 0.2, 0.3]),
        "broadcast_ent_coef": trial.suggest_float("broadcast_ent_coef", 1e-4, 1.0, log=True),
        "max_grad_norm": trial.suggest_categorical("max_grad_norm", [0.5, 1.0, 5.0]),
        "reward_scale": trial.suggest_float("reward_scale", 1e-3, 1.0, log=True),
        "team_reward": trial.suggest_categorical("team_reward", [False, True]),
        "normalize_broadcast_advantage": trial.suggest_categorical("normalize_broadcast_advantage", [False, True]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        # the random-skip baseline replaces mu's options: no critic that needs the probabilities they were drawn with
        "critic": trial.suggest_categorical(
            "critic", [name for name, critic in CRITICS.items() if not critic.needs_draw_probabilities]
        ),
    }
    params["batch_size"] = min(params["batch_size"], params["n_steps"] * n_envs)
    return convert_mappoc_params(params)


def convert_mappoc_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Turn sampled MAPPOC parameters into keyword arguments (rl-zoo3's converter signature).

    :param sampled_params: the parameters of a trial, as :func:`sample_mappoc_params` names them
    :return: keyword arguments of :class:`~sb3_detc.MAPPOC` (``net_arch`` and ``critic`` go into ``policy_kwargs``)
    """
    params = dict(sampled_params)
    policy_kwargs = {"net_arch": NET_ARCHS[params.pop("net_arch")], "learn_log_std": True}
    if "critic" in params:
        policy_kwargs["critic"] = params.pop("critic")
    return {**params, "policy_kwargs": policy_kwargs}


def register() -> None:
    """Add sb3-detc's algorithms and their Optuna samplers to rl-zoo3 (idempotent)."""
    ALGOS.update(ALGORITHMS)
    for name in ALGORITHMS:
        HYPERPARAMS_SAMPLER[name] = sample_mappoc_params
        HYPERPARAMS_CONVERTER[name] = convert_mappoc_params


# ----------------------------------------------------------------------------- run logs
class CSVLogCallback(BaseCallback):
    """Write everything the SB3 logger dumps to ``<folder>/progress.csv`` while training.

    rl-zoo3 logs to stdout and TensorBoard only; :mod:`sb3_detc.plot` reads this file.

    :param folder: the run's log folder
    :param verbose: verbosity level
    """

    def __init__(self, folder: str | os.PathLike, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.path = Path(folder) / "progress.csv"
        self._output: CSVOutputFormat | None = None

    def _on_training_start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._output = CSVOutputFormat(str(self.path))
        self.logger.output_formats.append(self._output)

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        if self._output is not None:
            self.logger.output_formats.remove(self._output)
            self._output.close()
            self._output = None


def uses_rollout_workers(entry: dict[str, Any]) -> bool:
    """Whether a hyperparameter entry names :data:`ROLLOUT_WORKER` among its ``env_wrapper``.

    :param entry: the entry (``env_wrapper``: one name, a ``{name: arguments}`` mapping or a list of those)
    :return: True if its envs are rollout workers
    """
    wrappers = entry.get("env_wrapper") or []
    wrappers = wrappers if isinstance(wrappers, list) else [wrappers]
    return ROLLOUT_WORKER in [w if isinstance(w, str) else next(iter(w)) for w in wrappers]


class ExperimentManager(rl_zoo3.exp_manager.ExperimentManager):
    """rl-zoo3's experiment manager that writes ``progress.csv`` and continues step counts.

    Every run's log folder gets the logger's ``progress.csv``. rl-zoo3 restarts the step count
    of a model loaded to continue training (``-i``) at zero, which would restart the
    curriculum, the schedules and the checkpoint numbering; here ``-n`` steps are added to
    where the saved model stopped. Registers sb3-detc's algorithms (:func:`register`).

    :param args: rl-zoo3's arguments, then its experiment manager's (see ``rl_zoo3.exp_manager``)
    :param kwargs: as rl-zoo3's experiment manager takes them
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        register()
        super().__init__(*args, **kwargs)
        #: the vector env class of the evaluation envs (``--vec-env``), once training envs got another
        self.eval_vec_env_class: type[VecEnv] | None = None

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        """rl-zoo3's preprocessing; an entry with rollout-worker envs (:data:`ROLLOUT_WORKER`) gets worker processes.

        Rollout workers pay off only in their own processes (``SubprocVecEnv``), so an entry
        that names them as ``env_wrapper`` trains in them whatever ``--vec-env`` says; its
        evaluation envs, which step one at a time with the learner's policy, stay as
        ``--vec-env`` says (default: in the learner's process, without a message per step).

        :param hyperparams: the entry, as read from the file and the command line
        :return: what rl-zoo3's preprocessing returns
        """
        if uses_rollout_workers(hyperparams):
            self.eval_vec_env_class = self.vec_env_class
            self.vec_env_class = SubprocVecEnv
        return super()._preprocess_hyperparams(hyperparams)

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        """rl-zoo3's envs; evaluation envs of the class in :attr:`eval_vec_env_class` where it is set.

        :param n_envs: number of envs
        :param eval_env: whether the envs are for evaluation
        :param no_log: whether to write no monitor files
        :return: the vector env
        """
        training = self.vec_env_class
        if eval_env and self.eval_vec_env_class is not None:
            self.vec_env_class = self.eval_vec_env_class
        try:
            return super().create_envs(n_envs, eval_env, no_log)
        finally:
            self.vec_env_class = training

    def create_callbacks(self) -> None:
        """rl-zoo3's callbacks (progress bar, checkpoints, evaluation) and a :class:`CSVLogCallback`."""
        super().create_callbacks()
        self.callbacks.append(CSVLogCallback(self.save_path))

    def learn(self, model: BaseAlgorithm) -> None:
        """Train ``model`` as rl-zoo3 does; a model loaded to continue (``-i``) counts on from its step count.

        rl-zoo3 trains with ``model.learn(n_timesteps, ...)``, which restarts the step count at
        zero; a loaded model learns with ``reset_num_timesteps=False`` instead
        (:class:`_ContinuedModel`). Training envs of rollout workers and evaluation envs of
        ``--vec-env`` differ in class by design: SB3's evaluation callback's warning about it is
        left out.

        :param model: the model to train
        """
        with warnings.catch_warnings():
            if self.eval_vec_env_class is not None:
                warnings.filterwarnings("ignore", "Training and eval env are not of the same type", UserWarning)
            super().learn(_ContinuedModel(model) if self.continue_training else model)  # type: ignore[arg-type]


class _ContinuedModel:
    """A model as rl-zoo3's ``learn`` sees it: ``learn`` continues the model's step count.

    Every call of ``learn`` gets ``reset_num_timesteps=False``; every other attribute is the
    model's. The model and its class stay as they are, so what a callback saves of the model
    and other models of the class are not affected.

    :param model: the model loaded to continue training
    """

    def __init__(self, model: BaseAlgorithm) -> None:
        self.model = model

    def learn(self, *args: Any, **kwargs: Any) -> BaseAlgorithm:
        """The model's ``learn`` with ``reset_num_timesteps=False``.

        :param args: positional arguments of the model's ``learn``
        :param kwargs: keyword arguments of the model's ``learn`` (without ``reset_num_timesteps``)
        :return: the trained model
        """
        return self.model.learn(*args, reset_num_timesteps=False, **kwargs)

    def __getattr__(self, name: str) -> Any:
        """The model's attribute ``name`` (rl-zoo3 reads e.g. ``env`` to close it after training).

        :param name: the attribute
        :return: the model's attribute
        """
        return getattr(self.model, name)
