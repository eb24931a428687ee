"""Replayed values of a broadcast: two copies of an env, one broadcasting and one silent, the same noise.

A critic estimates what an agent's broadcast is worth from returns whose noise is many times
larger than that worth, and on the linear system its estimate ranks the decisions unlike their
true value. Where the env can be copied, the value can be measured instead: at a decision of a
rollout, the env is copied twice; in one copy the agent broadcasts, in the other it stays silent,
and both then follow the current policy for a number of steps with the same random numbers (the
env's noise through its copied generator, the policy's samples through the same seeds). The
difference of the two copies' discounted rewards is a low-variance sample of
``Q_i(s, broadcast) - Q_i(s, silent)`` under the current policy (MAPPOC's
``broadcast_advantage="replayed"``).

:func:`replay` runs the copies of many decisions together, one batched policy evaluation per
step and branch; :func:`copyable_env` finds what to copy of a training env.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.utils import obs_as_tensor

#: How a batch of joint observations (B, N, ...) and the options to force (B, N) (None: ``mu`` decides)
#: become options (B, N) and sampled controls (B, N, m), drawing from PyTorch's global generator.
ReplayAct = Callable[[dict[str, np.ndarray], "np.ndarray | None"], tuple[np.ndarray, np.ndarray]]


class Replays(NamedTuple):
    """Replayed decisions of a rollout (K decisions, N agents).

    :param steps: the rollout step of every decision (K,)
    :param envs: the env of every decision (K,)
    :param agents: the deciding agent (K,)
    :param rewards: discounted sum of every agent's reward after a broadcast minus that after a silence (K, N),
        in the env's units (``info["agent_rewards"]``, the communication cost included)
    :param broadcasts: the same difference of every agent's discounted number of broadcasts (K, N)
    :param chances: the probability with which every decision was chosen for a replay (K,): weighted by its
        inverse, the replayed decisions stand for all of the rollout's in expectation
    """

    steps: np.ndarray
    envs: np.ndarray
    agents: np.ndarray
    rewards: np.ndarray
    broadcasts: np.ndarray
    chances: np.ndarray


def copyable_env(env: gym.Env) -> gym.Env:
    """What to copy of a training env: the env below the wrappers that keep books or check the API.

    SB3's ``Monitor`` and the package's ``RolloutWorker`` keep books of the training episodes (and a
    monitor file), Gymnasium's ``OrderEnforcing`` and ``PassiveEnvChecker`` check how the env is
    called; none of them changes what a step does, and a replay is not a training episode.

    :param env: one env of a vector env
    :return: the first wrapper (or the env) below the outermost such wrappers
    """
    from sb3_detc.mappoc.workers import RolloutWorker  # the workers' module imports the sampling's

    while isinstance(env, (Monitor, RolloutWorker, OrderEnforcing, PassiveEnvChecker)):
        env = env.env
    return env


def snapshot(env: gym.Env) -> gym.Env:
    """A copy of an env at its current state, its random generators included.

    :param env: the env (:func:`copyable_env` of a training env)
    :return: the copy
    :raises ValueError: if the env cannot be copied
    """
    try:
        return copy.deepcopy(env)
    except Exception as error:  # e.g. a simulator whose objects cannot be copied
        raise ValueError(
            f"broadcast_advantage='replayed' copies the training envs, and {env} cannot be copied "
            f"({type(error).__name__}: {error}); use another broadcast_advantage for this env."
        ) from error


def replay(
    act: ReplayAct,
    copies: list[gym.Env],
    observations: dict[str, np.ndarray],
    agents: np.ndarray,
    horizon: int,
    gamma: float,
    low: np.ndarray,
    high: np.ndarray,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Replay K decisions, each in two copies of its env: the agent broadcasts in one and stays silent in the other.

    In both copies of a decision the other agents' options of the first step, and everything
    later, come from ``act`` with the same seeds per step, so the two differ only through the
    agent's option. Every copy steps until its episode ends or ``horizon`` steps have passed.

    :param act: options and sampled controls of a batch (see :data:`ReplayAct`)
    :param copies: the K envs at the decisions, copies of their own: the silent branch steps them
    :param observations: their joint observations, (K, N, ...) per key
    :param agents: the deciding agent of every decision (K,)
    :param horizon: steps to follow (>= 1)
    :param gamma: discount factor
    :param low: lower bounds of the controls (N, m)
    :param high: upper bounds of the controls (N, m)
    :param seed: seed of the policy's samples
    :return: per decision and agent, the discounted reward of the broadcasting copy minus that of the silent
        one (K, N), and the same difference of discounted broadcasts (K, N)
    """
    k = len(copies)
    rows = np.arange(k)
    seeds = np.random.default_rng(seed).integers(2**31 - 1, size=horizon + 1)

    def draw(step_seed: int, obs: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        with th.random.fork_rng(devices=[]):  # the same numbers in both branches; the caller's stream untouched
            th.manual_seed(int(step_seed))
            return act(obs, forced)

    first, _ = draw(seeds[0], observations, None)  # the others' options of the first step
    totals = []
    for option in (1, 0):
        envs = [snapshot(env) for env in copies] if option == 1 else copies
        obs = {key: np.array(value) for key, value in observations.items()}
        alive = np.ones(k, bool)
        rewards, broadcasts = np.zeros((k, first.shape[1])), np.zeros((k, first.shape[1]))
        forced = first.copy()
        forced[rows, agents] = option
        for step in range(horizon):
            options, controls = draw(seeds[step + 1], obs, forced if step == 0 else None)
            controls = np.minimum(np.maximum(controls, low), high)
            for i in np.flatnonzero(alive):
                after, _, terminated, truncated, info = envs[i].step({"broadcast": options[i], "control": controls[i]})
                rewards[i] += gamma**step * np.asarray(info["agent_rewards"], dtype=np.float64)
                broadcasts[i] += gamma**step * options[i]
                for key, value in after.items():
                    obs[key][i] = value
                alive[i] = not (terminated or truncated)
            if not alive.any():
                break
        totals.append((rewards, broadcasts))
    (rewards_1, broadcasts_1), (rewards_0, broadcasts_0) = totals
    return rewards_1 - rewards_0, broadcasts_1 - broadcasts_0


def uniform_choice(n_envs: int, n_agents: int, share: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Which decisions of a step to replay: in every env with probability ``share``, one agent drawn uniformly.

    :param n_envs: envs B
    :param n_agents: agents N
    :param share: probability that an env's step has a replayed decision, in (0, 1]
    :param rng: the draws
    :return: the chosen agent per env, -1 where none (B,), and the probability with which it was chosen (B,)
    """
    agents = rng.integers(n_agents, size=n_envs)
    agents = np.where(rng.random(n_envs) < share, agents, -1)
    return agents, np.full(n_envs, share / n_agents)


def gradient_choice(probabilities: np.ndarray, share: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Which decisions of a step to replay: each with a chance in proportion to how far its replay would move ``mu``.

    A replayed decision moves the broadcast logit by ``p (1 - p) (Q(1) - Q(0))`` in expectation,
    ``p`` its probability of broadcasting: decisions far from ``mu``'s threshold carry next to no
    gradient. Decision ``(b, i)`` is chosen with probability ``pi_b w_bi / S_b``, with
    ``w = p (1 - p)``, ``S_b`` the sum of env ``b``'s weights and ``pi_b = min(1, share B S_b / sum S)``
    the probability that env ``b``'s step is replayed: ``share`` replays per env and step, as
    :func:`uniform_choice`, where ``mu`` is undecided. Decisions with ``p`` 0 or 1 (pinned) are never chosen.

    :param probabilities: every agent's probability of broadcasting, (B, N)
    :param share: mean number of replayed decisions per env and step, in (0, 1]
    :param rng: the draws
    :return: the chosen agent per env, -1 where none (B,), and the probability with which it was chosen (B,)
    """
    weights = probabilities * (1.0 - probabilities)
    totals = weights.sum(axis=1)
    n_envs = len(totals)
    whole = totals.sum()
    env_chance = np.minimum(1.0, share * n_envs * totals / whole) if whole > 0 else np.zeros(n_envs)
    picked = rng.random(n_envs) < env_chance
    cumulative = np.cumsum(weights, axis=1)
    draws = rng.random(n_envs) * totals
    agents = np.minimum((cumulative <= draws[:, None]).sum(axis=1), weights.shape[1] - 1)
    rows = np.arange(n_envs)
    chances = env_chance * weights[rows, agents] / np.where(totals > 0, totals, 1.0)
    return np.where(picked & (chances > 0), agents, -1), chances


def choose_uniformly(
    policy: Any, obs: dict[str, np.ndarray], share: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The decisions of a rollout's step to replay, one agent at random (:func:`uniform_choice`).

    :param policy: the policy that samples the rollout (not consulted)
    :param obs: the envs' observations of the step, (B, N, ...) per key
    :param share: probability that an env's step has a replayed decision, in (0, 1]
    :param rng: the draws
    :return: the chosen agent per env (-1: none) and its chance, (B,) each
    """
    n_envs, n_agents = obs["age"].shape[:2]
    return uniform_choice(n_envs, n_agents, share, rng)


def choose_by_gradient(
    policy: Any, obs: dict[str, np.ndarray], share: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The decisions of a rollout's step to replay, by ``mu``'s ``p (1 - p)`` (:func:`gradient_choice`).

    :param policy: the policy that samples the rollout: its ``broadcast_probabilities`` of the step
        (an extra pass of ``mu``)
    :param obs: the envs' observations of the step, (B, N, ...) per key
    :param share: mean number of replayed decisions per env and step, in (0, 1]
    :param rng: the draws
    :return: the chosen agent per env (-1: none) and its chance, (B,) each
    """
    with th.no_grad():
        probabilities = policy.broadcast_probabilities(obs_as_tensor(obs, policy.device))
    return gradient_choice(probabilities.cpu().numpy(), share, rng)


#: How a step's decisions can be chosen for replays, by the values of ``MAPPOC(replay_choice=...)``:
#: ``(policy, obs, share, rng) -> (agents, chances)`` (:func:`choose_uniformly`, :func:`choose_by_gradient`).
REPLAY_CHOICES: dict[str, Callable[..., tuple[np.ndarray, np.ndarray]]] = {
    "uniform": choose_uniformly,
    "gradient": choose_by_gradient,
}


def replayed_observations(observations: dict[str, np.ndarray], steps: np.ndarray, envs: np.ndarray) -> dict[str, Any]:
    """The rollout's observations at the replayed decisions.

    :param observations: the rollout's observations, (T, B, N, ...) per key
    :param steps: the decisions' steps (K,)
    :param envs: their envs (K,)
    :return: (K, N, ...) per key
    """
    return {key: value[steps, envs] for key, value in observations.items()}
