"""Evaluation of communication and control: returns with and without the communication cost, savings, per episode."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.mappoc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.mappoc.sampling import FixedTrigger


@dataclass
class CommunicationReport:
    """Averages over evaluation episodes.

    :param mean_return: team-mean return per episode, communication cost included
    :param mean_control_return: team-mean return per episode without the communication cost
    :param std_control_return: standard deviation over episodes of the control return
    :param broadcast_rate: broadcasts per agent-step
    :param savings: communication savings ``Gamma = 1 - broadcasts / agent-steps``
    :param agent_savings: savings of every agent (N,)
    :param episodes: number of episodes
    """

    mean_return: float
    mean_control_return: float
    std_control_return: float
    broadcast_rate: float
    savings: float
    agent_savings: np.ndarray
    episodes: int


@dataclass
class Episodes:
    """Per-episode results of a policy, one entry per episode (arrays of length ``episodes``).

    :param returns: team-mean return, communication cost included
    :param control_returns: team-mean return without the communication cost
    :param lengths: steps
    :param broadcasts: broadcasts of every agent (episodes, N)
    :param terminated: whether the episode terminated (rather than being truncated)
    :param failed: whether it ended by a failure (``info["failed"]``, Multiwalker: a fall or a
        dropped package; False where the env does not report it)
    :param package_travel: final minus initial ``info["package_x"]`` (NaN where the env does not report it)
    """

    returns: np.ndarray
    control_returns: np.ndarray
    lengths: np.ndarray
    broadcasts: np.ndarray
    terminated: np.ndarray
    failed: np.ndarray
    package_travel: np.ndarray

    @property
    def savings(self) -> float:
        """Communication savings over all episodes, ``1 - broadcasts / agent-steps``."""
        return float(1.0 - self.broadcasts.sum() / (self.lengths.sum() * self.broadcasts.shape[1]))


#: Most envs that :func:`evaluate_episodes` runs side by side.
MAX_SIDE_BY_SIDE = 64


@dataclass
class _Running:
    """An episode in progress in one of the envs."""

    index: int  # position of its seed
    obs: dict[str, np.ndarray]
    start_x: float
    broadcasts: np.ndarray  # (N,) broadcasts so far of every agent
    total: float = 0.0
    control_total: float = 0.0
    steps: int = 0


def evaluate_episodes(
    policy: MlpHybridPolicy,
    env: gym.Env | str,
    seeds: Sequence[int | None],
    deterministic: bool = True,
    sample_options: bool | None = None,
    fixed_trigger: FixedTrigger | None = None,
) -> Episodes:
    """Run a policy for whole episodes, one per seed, and record each.

    Where every episode has its seed and ``env`` can be made again (``env.spec``, as for an
    env from ``gym.make`` or an id, with wrappers that Gymnasium can make again), the episodes
    run side by side in ``env`` and copies made with ``gym.make(env.spec)`` (at most
    :data:`MAX_SIDE_BY_SIDE` at once), with one policy call per step for all of them;
    otherwise one after another in ``env``. Episode
    ``k`` is reset with ``seeds[k]`` either way, and the results are in the order of ``seeds``.
    The copies have the settings of ``env.spec``: what was changed in ``env`` after it was
    made (e.g. its broadcast cost set by hand) does not carry over. Where every episode has its
    seed, the policy's draws (options sampled from ``mu``, controls unless ``deterministic``)
    are seeded with the first (PyTorch's CPU generator, left as it was afterwards; a policy on
    a GPU draws from the GPU's): the same policy, env and seeds give the same episodes.

    :param policy: the policy (of a trained model, ``model.policy``, or loaded on its own)
    :param env: a joint env (not vectorised) or its registered id
    :param seeds: the seed of every episode's reset (None: continue the env's generator)
    :param deterministic: mean of ``pi`` instead of samples, and the most likely options unless
        ``sample_options`` says otherwise
    :param sample_options: options sampled from ``mu`` (True) or its most likely ones (False)
        whatever ``deterministic`` says (None: as the policy's ``sample_options`` says when
        ``deterministic``, else sampled)
    :param fixed_trigger: options to use instead of ``mu``'s (e.g. a
        :class:`~sb3_detc.triggers.RandomTrigger`), with the policy's control policy
    :return: the episodes' results
    """
    if isinstance(env, str):
        with gym.make(env) as made:
            return evaluate_episodes(policy, made, seeds, deterministic, sample_options, fixed_trigger)
    if not isinstance(env.unwrapped, JointEnv):
        raise ValueError(f"evaluation needs a joint sb3_detc env, got {env}.")
    if len(seeds) < 1:
        raise ValueError("evaluation needs at least one episode.")
    if sample_options is None:
        sample_options = policy.sample_options or not deterministic
    policy.set_training_mode(False)
    low, high = env.action_space["control"].low, env.action_space["control"].high
    n_agents = env.action_space["broadcast"].shape[0]
    seeded = all(seed is not None for seed in seeds)
    copies = []
    if seeded and env.spec is not None:
        try:
            copies = [gym.make(env.spec) for _ in range(min(len(seeds), MAX_SIDE_BY_SIDE) - 1)]
        except (ValueError, gym.error.Error):  # a wrapper that cannot be made again (the first copy fails)
            copies = []  # one episode after another
    envs = [env, *copies]
    pending = iter(enumerate(seeds))
    running: dict[int, _Running] = {}  # env position -> its episode
    records: list[dict | None] = [None] * len(seeds)

    def start(slot: int) -> None:
        index, seed = next(pending, (None, None))
        if index is not None:
            obs, info = envs[slot].reset(seed=seed)
            running[slot] = _Running(index, obs, info.get("package_x", math.nan), np.zeros(n_agents, np.int64))

    try:
        with th.random.fork_rng(devices=[], enabled=seeded):
            if seeded:
                th.default_generator.manual_seed(int(seeds[0]))  # type: ignore[arg-type]
            for slot in range(len(envs)):
                start(slot)
            while running:
                slots = list(running)
                batch = {key: np.stack([running[slot].obs[key] for slot in slots]) for key in running[slots[0]].obs}
                with th.no_grad():
                    forced = None
                    if fixed_trigger is not None:
                        forced = th.as_tensor(fixed_trigger(batch), device=policy.device)
                    sampled, controls = policy.sample_actions(
                        obs_as_tensor(batch, policy.device),
                        broadcast=forced,
                        deterministic=deterministic,
                        sample_options=sample_options,
                    )
                sampled, controls = sampled.cpu().numpy(), np.clip(controls.cpu().numpy(), low, high)
                for row, slot in enumerate(slots):
                    episode = running[slot]
                    obs, reward, terminated, truncated, info = envs[slot].step(
                        {"broadcast": sampled[row], "control": controls[row]}
                    )
                    episode.obs = obs
                    episode.total += reward
                    episode.control_total += float(np.mean(info["control_rewards"]))
                    episode.broadcasts += sampled[row]
                    episode.steps += 1
                    if terminated or truncated:
                        records[episode.index] = {
                            "returns": episode.total,
                            "control_returns": episode.control_total,
                            "lengths": episode.steps,
                            "broadcasts": episode.broadcasts,
                            "terminated": bool(terminated),
                            "failed": bool(info.get("failed", False)),
                            "package_travel": info.get("package_x", math.nan) - episode.start_x,
                        }
                        del running[slot]
                        start(slot)
    finally:
        for copy in copies:
            copy.close()
    return Episodes(
        **{field: np.asarray([record[field] for record in records]) for field in Episodes.__dataclass_fields__}
    )


def evaluate_communication(
    model: MAPPOC,
    env: gym.Env | str,
    n_eval_episodes: int = 10,
    deterministic: bool = True,
    sample_options: bool | None = None,
    fixed_trigger: FixedTrigger | None = None,
    seed: int | None = None,
) -> CommunicationReport:
    """Run a model's policies for whole episodes and report returns and communication savings.

    :param model: the trained model
    :param env: a joint env (not vectorised) or its registered id
    :param n_eval_episodes: number of episodes
    :param deterministic: mean of ``pi`` instead of samples, and the most likely options unless
        ``sample_options`` says otherwise
    :param sample_options: options sampled from ``mu`` (True) or its most likely ones (False)
        whatever ``deterministic`` says (None: as the policy's ``sample_options`` says when
        ``deterministic``, else sampled)
    :param fixed_trigger: options to use instead of ``mu``'s (e.g. a
        :class:`~sb3_detc.triggers.RandomTrigger`), with the model's control policy
    :param seed: seed of the first episode; episode ``k`` is reset with ``seed + k``, so that
        evaluations of other policies or triggers with the same seed run the same episodes
        (None: every episode continues the env's generator)
    :return: the averages
    """
    if n_eval_episodes < 1:
        raise ValueError(f"n_eval_episodes must be >= 1, got {n_eval_episodes}.")
    episodes = evaluate_episodes(
        model.policy,
        env,
        [None if seed is None else seed + k for k in range(n_eval_episodes)],
        deterministic=deterministic,
        sample_options=sample_options,
        fixed_trigger=fixed_trigger,
    )
    agent_rate = episodes.broadcasts.sum(axis=0) / episodes.lengths.sum()
    return CommunicationReport(
        mean_return=float(np.mean(episodes.returns)),
        mean_control_return=float(np.mean(episodes.control_returns)),
        std_control_return=float(np.std(episodes.control_returns)),
        broadcast_rate=float(agent_rate.mean()),
        savings=float(1 - agent_rate.mean()),
        agent_savings=1 - agent_rate,
        episodes=n_eval_episodes,
    )
