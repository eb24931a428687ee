"""Evaluation of communication and control: returns with and without the communication cost, savings."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.mappoc.mappoc import MAPPOC, OptionOverride


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


def evaluate_communication(
    model: MAPPOC,
    env: gym.Env | str,
    n_eval_episodes: int = 10,
    deterministic: bool = True,
    deterministic_options: bool | None = None,
    option_override: OptionOverride | None = None,
    seed: int | None = None,
) -> CommunicationReport:
    """Run a model's policies for whole episodes and report returns and communication savings.

    :param model: the trained model
    :param env: a joint env (not vectorised) or its registered id
    :param n_eval_episodes: number of episodes
    :param deterministic: mode of ``mu`` and mean of ``pi`` instead of samples
    :param deterministic_options: mode (True) or samples (False) of ``mu`` whatever
        ``deterministic`` says (None: as ``deterministic``)
    :param option_override: options to use instead of ``mu``'s (e.g. a
        :class:`~sb3_detc.triggers.RandomTrigger`), with the model's control policy
    :param seed: seed of the first episode (the following ones continue its generator)
    :return: the averages
    """
    if isinstance(env, str):
        env = gym.make(env)
    if not isinstance(env.unwrapped, JointEnv):
        raise ValueError(f"evaluate_communication needs a joint sb3_detc env, got {env}.")
    if n_eval_episodes < 1:
        raise ValueError(f"n_eval_episodes must be >= 1, got {n_eval_episodes}.")
    policy = model.policy
    policy.set_training_mode(False)
    low, high = env.action_space["control"].low, env.action_space["control"].high
    returns, control_returns, broadcasts, steps = [], [], 0, 0
    for episode in range(n_eval_episodes):
        obs, _ = env.reset(seed=seed if episode == 0 else None)
        done, total, control_total = False, 0.0, 0.0
        while not done:
            batch = {key: value[None] for key, value in obs.items()}
            with th.no_grad():
                comm = None
                if option_override is not None:
                    comm = th.as_tensor(option_override(batch), device=policy.device)
                action = policy(
                    obs_as_tensor(batch, policy.device),
                    deterministic=deterministic,
                    comm=comm,
                    deterministic_options=deterministic_options,
                )
            options = action.comm[0].cpu().numpy()
            control = np.clip(action.control[0].cpu().numpy(), low, high)
            obs, reward, terminated, truncated, info = env.step({"comm": options, "control": control})
            total += reward
            control_total += float(np.mean(info["control_rewards"]))
            broadcasts = broadcasts + options
            steps += 1
            done = terminated or truncated
        returns.append(total)
        control_returns.append(control_total)
    agent_rate = np.asarray(broadcasts, dtype=float) / steps
    return CommunicationReport(
        mean_return=float(np.mean(returns)),
        mean_control_return=float(np.mean(control_returns)),
        std_control_return=float(np.std(control_returns)),
        broadcast_rate=float(agent_rate.mean()),
        savings=float(1 - agent_rate.mean()),
        agent_savings=1 - agent_rate,
        episodes=n_eval_episodes,
    )
