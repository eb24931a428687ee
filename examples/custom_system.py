r"""Bring your own system: wrap a multi-agent system of your own and train it with MAPPOC.

The system here is a convoy of N vessels in a line that must hold one shared heading
(:class:`HeadingConsensus`). Only the lead vessel (agent 0) receives the operator's course
changes; the others learn about a turn only from the broadcasts of their neighbours. A
broadcast is worth its cost right after a vessel has turned and worth almost nothing while
the convoy sails straight, which is the situation event-triggered communication is made for.

Three steps make any system trainable with :class:`~sb3_detc.MAPPOC`:

1. subclass :class:`~sb3_detc.envs.system.CommunicatingSystem`: declare per agent its local
   observation, the message it would broadcast, the trigger features its policy over options
   sees and its control, and implement ``_reset_arrays`` and ``_step_arrays`` on arrays with
   the agent axis first (per-agent rewards, termination and truncation);
2. put it behind the event-triggered network (:class:`~sb3_detc.envs.EventTriggeredNetwork`,
   the PettingZoo view) and its joint view (:class:`~sb3_detc.envs.JointEnv`, the Gymnasium
   env that SB3 vectorises), as :func:`parallel_env` and :func:`joint_env` do;
3. register the joint view as a Gymnasium id in your own namespace. Importing this module
   registers ``myteam/Consensus-v0``, so ``gymnasium.make``, SB3's vectorised envs and
   rl-zoo3's ``--gym-packages`` all find it. A process that has not imported it (e.g. a
   worker of SB3's ``SubprocVecEnv``) can name it in the id: ``custom_system:myteam/Consensus-v0``.

Run the example (training, the evaluation table, one decentralised episode)::

    python examples/custom_system.py [--timesteps 150000] [--seed 0]

With the defaults (about 7 minutes of one core) it prints the control return of the learned
triggers next to random broadcasts at the same rate and broadcasting every step, on the same
50 seeded episodes.

Train the same id through rl-zoo3, with the hyperparameters of ``examples/custom_system.yml``.
``examples/`` must be on ``PYTHONPATH``, so that ``--gym-packages custom_system`` can import
this module (which registers the id) before the run starts::

    PYTHONPATH=examples python -m sb3_detc.train --algo mappoc --env myteam/Consensus-v0 \
        --gym-packages custom_system -conf examples/custom_system.yml
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch as th
from gymnasium import spaces
from gymnasium.utils import seeding

from sb3_detc import MAPPOC
from sb3_detc.callbacks import ControlFirstCallback
from sb3_detc.envs import CommunicatingSystem, EventTriggeredNetwork, JointEnv, SystemObs
from sb3_detc.evaluation import CommunicationReport, evaluate_communication
from sb3_detc.mappoc import AgentController, Inbox, run_decentralised_step
from sb3_detc.triggers import PeriodicTrigger, RandomTrigger

#: The Gymnasium id of the joint view, in a namespace of its own (not ``sb3_detc/``).
ENV_ID = "myteam/Consensus-v0"
#: The id with the module that registers it: MAPPOC's worker processes import the module
#: to make the env (``gymnasium.make("module:id")``), whoever started the training.
WORKER_ENV_ID = f"custom_system:{ENV_ID}"


# ----------------------------------------------------------------------------- 1. the system
class HeadingConsensus(CommunicatingSystem):
    """A convoy of N vessels in a line that holds one shared heading; only the lead hears course changes.

    **Dynamics** (first order, per agent): heading ``h_i`` (radians, relative to a nominal
    course) and turn rate ``u_i`` (the control, clipped to ``[-u_max, u_max]``)::

        h_i[k+1] = h_i[k] + dt u_i[k] + w_i[k],   w_i[k] ~ N(0, noise_std^2).

    The operator's course ``c`` is known to the lead (agent 0) only. After every step, with
    probability ``course_change_prob``, it is drawn anew from ``N(0, course_std^2)``. Initial
    headings and course are drawn from ``N(0, init_std^2)`` and ``N(0, course_std^2)``.

    **Cost** on the headings after the step and the applied turn rates: the lead pays
    ``q_course (h_0 - c)^2``, every pair of neighbours in the line pays
    ``q_agree (h_{i+1} - h_i)^2``, shared half and half, and every agent pays ``r u_i^2``::

        r_i = -(q_course [i = 0] (h_0 - c)^2 + 0.5 q_agree sum_{j neighbour of i} (h_j - h_i)^2 + r u_i^2).

    **What the agents see and say** (all of shape (N, 1)):

    * local observation: the course error ``c - h_i`` for the lead, 0 for the others (they
      receive no course commands);
    * message: the own heading ``h_i``. The network hands every agent the others' last
      broadcast headings relative to its own current heading, which is all a follower needs;
    * trigger features: the own heading. The policy over options sees it now and at the own
      last broadcast, i.e. how far the agent has turned since it last told the others.

    **Episodes** are truncated after ``max_cycles`` steps. With ``max_gap`` set, the convoy
    breaks up when two neighbours' headings differ by more than ``max_gap``: the episode
    terminates, every agent pays ``breakup_penalty`` once and ``info["failed"]`` is True
    (the info dict of every step has ``"failed"``).

    :param n_agents: number of vessels N (an integer >= 2); agent 0 is the lead
    :param dt: step length in seconds (> 0)
    :param q_course: weight of the lead's squared course error (>= 0)
    :param q_agree: weight of the squared heading difference between neighbours (>= 0)
    :param r: weight of the squared turn rate (>= 0)
    :param noise_std: standard deviation of the heading noise per step (>= 0)
    :param course_std: standard deviation of the operator's course (>= 0)
    :param course_change_prob: probability per step of a new course (in [0, 1])
    :param init_std: standard deviation of the initial headings (>= 0)
    :param u_max: largest turn rate in radians per second (> 0)
    :param max_cycles: episode length in steps (an integer >= 1)
    :param max_gap: heading difference between neighbours at which the convoy breaks up and
        the episode terminates (> 0), or None: it never breaks up
    :param breakup_penalty: reward charged to every agent when the convoy breaks up (>= 0)
    """

    metadata: dict[str, Any] = {"render_modes": [], "name": "heading_consensus_v0", "is_parallelizable": True}

    def __init__(
        self,
        n_agents: int = 4,
        dt: float = 0.2,
        q_course: float = 1.0,
        q_agree: float = 1.0,
        r: float = 0.01,
        noise_std: float = 0.02,
        course_std: float = 0.5,
        course_change_prob: float = 0.05,
        init_std: float = 0.3,
        u_max: float = 2.0,
        max_cycles: int = 100,
        max_gap: float | None = None,
        breakup_penalty: float = 10.0,
    ) -> None:
        super().__init__()
        if int(n_agents) != n_agents or n_agents < 2:
            raise ValueError(f"n_agents must be an integer >= 2, got {n_agents!r}.")
        if int(max_cycles) != max_cycles or max_cycles < 1:
            raise ValueError(f"max_cycles must be an integer >= 1, got {max_cycles!r}.")
        for name, value in [("q_course", q_course), ("q_agree", q_agree), ("r", r), ("noise_std", noise_std)]:
            _check_non_negative(name, value)
        for name, value in [("course_std", course_std), ("init_std", init_std), ("breakup_penalty", breakup_penalty)]:
            _check_non_negative(name, value)
        if not 0.0 <= course_change_prob <= 1.0:
            raise ValueError(f"course_change_prob must be in [0, 1], got {course_change_prob!r}.")
        if not (dt > 0 and u_max > 0 and (max_gap is None or max_gap > 0)):
            raise ValueError(f"dt, u_max and max_gap must be > 0, got {dt!r}, {u_max!r} and {max_gap!r}.")
        self.dt, self.q_course, self.q_agree, self.r = float(dt), float(q_course), float(q_agree), float(r)
        self.noise_std, self.course_std, self.init_std = float(noise_std), float(course_std), float(init_std)
        self.course_change_prob, self.u_max = float(course_change_prob), float(u_max)
        self.max_gap = None if max_gap is None else float(max_gap)
        self.breakup_penalty = float(breakup_penalty)
        self.max_cycles = int(max_cycles)  # a plain attribute: PettingZoo's parallel_api_test sets it
        self.render_mode = None

        # What CommunicatingSystem needs: agent names and the per-agent spaces.
        self.possible_agents = [f"vessel_{i}" for i in range(int(n_agents))]
        self.local_space = spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32)  # course error
        self.message_space = spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32)  # own heading
        self.trigger_space = spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32)  # own heading
        self.control_space = spaces.Box(-self.u_max, self.u_max, shape=(1,), dtype=np.float32)  # turn rate

        self.np_random, _ = seeding.np_random()
        self.heading = np.zeros(self.n_agents)
        self.course = 0.0
        self.steps = 0

    def _observe(self) -> SystemObs:
        heading = self.heading[:, None]  # (N, 1)
        course_error = np.zeros((self.n_agents, 1))
        course_error[0] = self.course - self.heading[0]  # only the lead knows the course
        return SystemObs(local=course_error, message=heading.copy(), trigger=heading.copy())

    def _reset_arrays(self, seed: int | None = None) -> tuple[SystemObs, dict[str, Any]]:
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        self.heading = self.init_std * self.np_random.standard_normal(self.n_agents)
        self.course = self.course_std * self.np_random.standard_normal()
        self.steps = 0
        return self._observe(), {}

    def _step_arrays(self, control: np.ndarray) -> tuple[SystemObs, np.ndarray, bool, bool, dict[str, Any]]:
        turn = np.clip(control[:, 0], -self.u_max, self.u_max)
        noise = self.noise_std * self.np_random.standard_normal(self.n_agents)
        self.heading = self.heading + self.dt * turn + noise
        self.steps += 1

        gaps = np.diff(self.heading)  # (N - 1,), the pairs (i, i + 1)
        disagreement = np.zeros(self.n_agents)
        disagreement[:-1] += 0.5 * self.q_agree * gaps**2
        disagreement[1:] += 0.5 * self.q_agree * gaps**2
        rewards = -(disagreement + self.r * turn**2)
        rewards[0] -= self.q_course * (self.heading[0] - self.course) ** 2

        failed = self.max_gap is not None and bool(np.any(np.abs(gaps) > self.max_gap))
        if failed:
            rewards -= self.breakup_penalty
        if self.np_random.random() < self.course_change_prob:  # the lead sees it from the next step on
            self.course = self.course_std * self.np_random.standard_normal()
        truncated = self.steps >= self.max_cycles
        return self._observe(), rewards, failed, truncated and not failed, {"failed": failed}


def _check_non_negative(name: str, value: float) -> None:
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}.")


# ----------------------------------------------------------------------------- 2. the network views
def parallel_env(broadcast_cost: float = 0.05, trigger: str = "default", **kwargs: Any) -> EventTriggeredNetwork:
    """PettingZoo parallel env: the convoy behind the event-triggered network.

    :param broadcast_cost: reward charged to an agent for every broadcast (default 0.05: a
        broadcast right after a turn saves more, one while sailing straight much less)
    :param trigger: features of the policy over options (see :class:`~sb3_detc.envs.EventTriggeredNetwork`);
        the default is the system's, the own heading
    :param kwargs: keyword arguments of :class:`HeadingConsensus`
    :return: the PettingZoo view
    """
    return EventTriggeredNetwork(HeadingConsensus(**kwargs), broadcast_cost=broadcast_cost, trigger=trigger)


def joint_env(**kwargs: Any) -> JointEnv:
    """Joint Gymnasium view (agent axis inside the arrays), registered as ``myteam/Consensus-v0``.

    :param kwargs: keyword arguments of :func:`parallel_env`
    :return: the joint view
    """
    return JointEnv(parallel_env(**kwargs))


# ----------------------------------------------------------------------------- 3. the Gymnasium id
# Registered on import, as sb3_detc registers its own ids; keywords of gymnasium.make reach
# joint_env, e.g. gymnasium.make(ENV_ID, broadcast_cost=0.1, n_agents=6).
if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=joint_env)


# ----------------------------------------------------------------------------- training and evaluation
def train(timesteps: int, seed: int) -> MAPPOC:
    """Train MAPPOC on ``myteam/Consensus-v0``: first the turn rates under random broadcasts, then when to broadcast.

    The settings are those of ``examples/custom_system.yml``. In the first half of the budget
    every agent broadcasts at random in half of the steps and only the control policies
    learn; in the second half they stay fixed and the policies over options learn when a
    broadcast is worth its cost (:class:`~sb3_detc.callbacks.ControlFirstCallback`).

    :param timesteps: environment steps
    :param seed: seed of the model and its environment
    :return: the trained model
    """
    model = MAPPOC(
        "MlpHybridPolicy",
        WORKER_ENV_ID,
        n_steps=1024,
        batch_size=256,
        n_epochs=10,
        learning_rate=3e-4,
        gamma=0.95,
        reward_scale=0.1,
        team_reward=True,
        broadcast_ent_coef=0.03,
        normalize_broadcast_advantage=True,
        policy_kwargs=dict(net_arch=[64, 64], learn_log_std=True, critic="afterstate", age_scale=0.0),
        seed=seed,
        device="cpu",
    )
    stages = ControlFirstCallback(switch=max(timesteps // 2, 1), unit="timesteps", trigger_learning_rate=1e-3)
    model.learn(timesteps, callback=stages)
    return model


def evaluate(model: MAPPOC, n_episodes: int, seed: int) -> dict[str, CommunicationReport]:
    """The learned triggers against random broadcasts at the same rate and against broadcasting every step.

    All rows use the model's control policies and the same episodes (same seed).

    :param model: the trained model
    :param n_episodes: evaluation episodes per row
    :param seed: seed of the first episode
    :return: one report per row, by name
    """
    learned = evaluate_communication(model, ENV_ID, n_episodes, seed=seed)
    random = RandomTrigger(skip_prob=learned.savings, seed=seed)
    return {
        "learned triggers": learned,
        "random, same rate": evaluate_communication(model, ENV_ID, n_episodes, fixed_trigger=random, seed=seed),
        "always broadcast": evaluate_communication(
            model, ENV_ID, n_episodes, fixed_trigger=PeriodicTrigger(1), seed=seed
        ),
    }


def print_table(reports: dict[str, CommunicationReport]) -> None:
    """Print one Markdown row per report: returns per agent and episode with and without the communication cost.

    :param reports: the reports of :func:`evaluate`, by name
    """
    print("| options | return | control return | savings |")
    print("|---|---|---|---|")
    for name, report in reports.items():
        print(f"| {name} | {report.mean_return:.2f} | {report.mean_control_return:.2f} | {report.savings:.3f} |")


def run_decentralised_episode(
    env: EventTriggeredNetwork, controllers: Sequence[AgentController], seed: int
) -> tuple[float, np.ndarray]:
    """One episode in which every vessel runs its own controller on its own inbox.

    Each vessel reads its own heading (its message) from its own compass, here
    ``env.system.last_obs.message``, and only its own row of it.

    :param env: the PettingZoo view (:func:`parallel_env`)
    :param controllers: one controller per agent, ``model.policy.agent_controller(i)``
    :param seed: seed of the episode
    :return: the team-mean return (communication cost included) and every agent's broadcasts
    """
    obs, _ = env.reset(seed=seed)
    inboxes = [Inbox(i, env.n_agents) for i in range(env.n_agents)]
    for inbox in inboxes:  # the initial headings count as received
        inbox.reset(env.system.last_obs.message)
    total, broadcasts = 0.0, np.zeros(env.n_agents, dtype=int)
    while env.agents:
        actions = run_decentralised_step(controllers, inboxes, obs, env.system.last_obs.message)
        obs, rewards, _, _, _ = env.step(actions)
        total += float(np.mean(list(rewards.values())))
        broadcasts += [actions[agent]["broadcast"] for agent in env.possible_agents]
    return total, broadcasts


def main(argv: Sequence[str] | None = None) -> None:
    """Train, evaluate against random and periodic broadcasts, and run the learned controllers decentralised.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=150_000, help="training steps")
    parser.add_argument("--seed", type=int, default=0, help="seed of training and evaluation")
    parser.add_argument("--episodes", type=int, default=50, help="evaluation episodes per row")
    args = parser.parse_args(argv)
    th.set_num_threads(1)  # small networks: one thread is fastest

    start = time.perf_counter()
    model = train(args.timesteps, args.seed)
    print(f"trained {args.timesteps} steps on {ENV_ID} in {time.perf_counter() - start:.0f} s")

    print(f"\nevaluation, {args.episodes} episodes, per agent and episode:")
    print_table(evaluate(model, args.episodes, seed=args.seed + 1000))

    env = parallel_env()
    controllers = [model.policy.agent_controller(i) for i in range(env.n_agents)]
    episode_return, broadcasts = run_decentralised_episode(env, controllers, seed=args.seed + 2000)
    steps = env.system.steps
    print(
        f"\ndecentralised episode: return {episode_return:.2f}, {broadcasts.sum()} broadcasts in {steps} steps "
        f"(per vessel: {', '.join(map(str, broadcasts))})"
    )


if __name__ == "__main__":
    main()
