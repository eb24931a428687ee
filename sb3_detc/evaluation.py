"""Evaluation of communication and control: episode metrics, the episode runner and the package's protocol of modes.

* :class:`EpisodeCounter` counts episodes step by step from a joint env's infos: returns with
  and without the communication cost, broadcasts and savings per agent, inter-event times,
  package travel and failures. It is the one count of episode statistics: the episode runner
  and :class:`~sb3_detc.callbacks.CommMetricsCallback` (during training) both use it.
* :func:`evaluate_episodes` runs a policy for whole seeded episodes and returns them as
  :class:`Episodes`; :func:`evaluate_communication` averages them into a :class:`CommunicationReport`.
* :func:`evaluate_policy_modes` is the package's evaluation protocol, the one the studies
  (:mod:`sb3_detc.study`), ``python -m sb3_detc.compare`` and ``python -m sb3_detc.evaluate``
  run: the same seeded episodes in every mode of :data:`MODES`.
* :class:`ThresholdedOptions` makes a learned policy over options deterministic at a chosen
  rate; the protocol compares it with the fixed families at the learned rate as the mode
  ``thresholded`` (:func:`evaluate_thresholded`).

**Dependence of the trigger on the state.** A trigger that broadcasts with the same
probability in every state is a random skip; one whose probability of broadcasting follows the
state can send where a message is worth it. The protocol measures the difference as the mutual
information between an agent's option and the state it is taken in, over the states the
learned mode's episodes visit (:attr:`Episodes.option_state_information`):
``I(O; S) = H(mean_s p(s)) - mean_s H(p(s))``, in bits, with ``p(s)`` the agent's probability
of broadcasting in state ``s`` and ``H`` the binary entropy; the mean over the agents. It is the
entropy of state-independent options at the same rate minus that of the trigger's own: 0 for a
trigger that ignores the state (random skips), up to 1 bit; ``H(rate)`` for a deterministic
trigger whose options follow the state alone (e.g. send-on-delta), since then every ``H(p(s))`` is 0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from scipy.special import entr
from stable_baselines3.common.utils import obs_as_tensor

from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.mappoc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy, options_sampled
from sb3_detc.mappoc.sampling import FixedTrigger
from sb3_detc.network import interval_window
from sb3_detc.triggers import (
    PERIODIC_FAMILIES,
    TRIGGER_FAMILIES,
    FixedControl,
    RandomTrigger,
    StatelessTrigger,
    bracket_trigger,
)

__all__ = [
    "EVAL_SEED",
    "MAX_SIDE_BY_SIDE",
    "MODES",
    "SUCCESS_NO_FALL",
    "SUCCESS_TRAVEL",
    "CommunicationReport",
    "EpisodeCounter",
    "EpisodeRecord",
    "Episodes",
    "ThresholdedOptions",
    "binary_entropy",
    "carries_package",
    "evaluate_communication",
    "evaluate_episodes",
    "evaluate_fixed_family",
    "fixed_family_env",
    "evaluate_policy_modes",
    "evaluate_thresholded",
]

#: The modes of the protocol (:func:`evaluate_policy_modes`), in its order.
MODES = ("learned", "mode", "random_same_rate", "periodic", "never", "thresholded")

#: Seed of the first evaluation episode unless a study or a command says otherwise.
EVAL_SEED = 10_000

#: Fraction of evaluation episodes without a fall for a Multiwalker seed to succeed.
SUCCESS_NO_FALL = 0.9
#: Package travel of a successful seed relative to communication at every step with the same controller.
SUCCESS_TRAVEL = 0.5

#: Most envs that :func:`evaluate_episodes` runs side by side.
MAX_SIDE_BY_SIDE = 64


def binary_entropy(p: np.ndarray | float) -> np.ndarray:
    """Entropy of options that broadcast with probability ``p``, in bits (0 at 0 and 1, 1 at 0.5).

    :param p: probabilities of broadcasting
    :return: ``-p log2 p - (1 - p) log2 (1 - p)``, elementwise
    """
    p = np.asarray(p, dtype=np.float64)
    return (entr(p) + entr(1.0 - p)) / math.log(2.0)


def carries_package(metrics: dict[str, float]) -> bool:
    """Whether a Multiwalker seed carries the package: the travel part of the success criterion.

    :param metrics: a trial's evaluation metrics (``package_travel``, ``periodic_package_travel``)
    :return: True when its package travel is at least :data:`SUCCESS_TRAVEL` of the travel with
        communication at every step (the same controllers)
    """
    return metrics["package_travel"] >= SUCCESS_TRAVEL * metrics["periodic_package_travel"]


# ----------------------------------------------------------------------------- episode metrics
@dataclasses.dataclass
class EpisodeRecord:
    """One finished episode, as :class:`EpisodeCounter` counted it.

    :param returns: every agent's return, communication cost included (N,)
    :param control_returns: every agent's return without the communication cost (N,)
    :param length: steps
    :param broadcasts: every agent's broadcasts (N,)
    :param terminated: whether the episode terminated (rather than being truncated)
    :param failed: whether it ended by a failure: ``info["failed"]`` of its last step where the
        env reports it (Multiwalker: a fall or a dropped package, not reaching the end of the
        terrain), else whether it terminated
    :param package_travel: final minus initial ``info["package_x"]`` (NaN where the env does not report it)
    :param broadcast_probability: every agent's mean probability of broadcasting over the
        episode's steps (N,) (NaN where the probabilities were not given)
    :param option_entropy: every agent's mean entropy of its options over the episode's steps,
        :func:`binary_entropy` of the probabilities, in bits (N,) (NaN where they were not given)
    """

    returns: np.ndarray
    control_returns: np.ndarray
    length: int
    broadcasts: np.ndarray
    terminated: bool
    failed: bool
    package_travel: float
    broadcast_probability: np.ndarray
    option_entropy: np.ndarray


class EpisodeCounter:
    """Episodes of envs that run side by side, counted step by step from the joint env's infos.

    Every step of env ``e`` goes to :meth:`step` with the step's info (``broadcast``,
    ``agent_rewards`` and ``control_rewards`` of every agent, and ``package_x`` and ``failed``
    where the env reports them); every episode that starts goes to :meth:`start` with the info of
    its reset. :meth:`step` returns the :class:`EpisodeRecord` of the episode that the step ends,
    if it was started with :meth:`start`: an episode already running when the counting began
    (e.g. in a training run continued by another ``learn``) counts in the step statistics only.

    The step statistics since the counter was made or :meth:`clear` ed (e.g. one rollout):
    :attr:`steps` (steps of one env each), :attr:`broadcasts` (N,), :attr:`intervals` (per
    agent, the inter-event times: the numbers of steps between two consecutive broadcasts of the
    agent in one episode; the reset is not an event, and an interval counts when its closing
    broadcast is sent) and :attr:`episodes` (the records returned since).

    :param n_envs: number of envs counted side by side
    """

    def __init__(self, n_envs: int) -> None:
        self.n_envs = n_envs
        self.n_agents: int | None = None  # from the first step's broadcasts
        self._started = np.zeros(n_envs, bool)
        self._start_x = np.full(n_envs, math.nan)
        self.clear()

    def clear(self) -> None:
        """Forget the step statistics and the returned episodes (the episodes in progress go on)."""
        n = self.n_agents or 0
        self.steps = 0
        self.broadcasts = np.zeros(n, np.int64)
        self.intervals: list[list[int]] = [[] for _ in range(n)]
        self.episodes: list[EpisodeRecord] = []

    def _first_step(self, n_agents: int) -> None:
        """Make the per-env, per-agent counts (n_envs, N) once the number of agents is known.

        :param n_agents: number of agents N
        """
        shape = (self.n_envs, n_agents)
        self.n_agents = n_agents
        self._returns = np.zeros(shape)
        self._control_returns = np.zeros(shape)
        self._episode_broadcasts = np.zeros(shape, np.int64)
        self._probability = np.zeros(shape)
        self._entropy = np.zeros(shape)
        self._probability_steps = np.zeros(self.n_envs, np.int64)
        self._length = np.zeros(self.n_envs, np.int64)
        self._last_event = np.full(shape, -1, np.int64)
        self.broadcasts = np.zeros(n_agents, np.int64)
        self.intervals = [[] for _ in range(n_agents)]

    def start(self, env: int, reset_info: dict[str, Any] | None = None) -> None:
        """An episode starts in env ``env``: it is recorded when it ends.

        :param env: index of the env
        :param reset_info: the info of its reset (reads ``package_x`` where present; None: not known)
        """
        self._started[env] = True
        self._start_x[env] = float((reset_info or {}).get("package_x", math.nan))

    def step(
        self,
        env: int,
        info: dict[str, Any],
        terminated: bool,
        truncated: bool,
        broadcast_probability: np.ndarray | None = None,
    ) -> EpisodeRecord | None:
        """Count one step of env ``env``.

        :param env: index of the env
        :param info: the step's info: ``broadcast``, ``agent_rewards`` (with the communication cost)
            and ``control_rewards`` (without), each (N,), and where the env reports them
            ``package_x`` and ``failed``
        :param terminated: whether the step terminated the episode
        :param truncated: whether it truncated it
        :param broadcast_probability: every agent's probability of broadcasting in this step (N,)
            (None: not known)
        :return: the record of the episode this step ended, if it ended one that was started with
            :meth:`start`, else None
        :raises ValueError: if the info has no ``broadcast`` (not a joint sb3_detc env)
        """
        if "broadcast" not in info:
            raise ValueError("episode metrics need info['broadcast']: use a joint sb3_detc env (JointEnv).")
        broadcast = np.asarray(info["broadcast"], np.int64)
        if self.n_agents is None:
            self._first_step(len(broadcast))
        k = self._length[env]
        for i in np.flatnonzero(broadcast):
            if self._last_event[env, i] >= 0:
                self.intervals[i].append(int(k - self._last_event[env, i]))
            self._last_event[env, i] = k
        self.broadcasts += broadcast
        self.steps += 1
        self._episode_broadcasts[env] += broadcast
        self._returns[env] += info["agent_rewards"]
        self._control_returns[env] += info["control_rewards"]
        self._length[env] += 1
        if broadcast_probability is not None:
            self._probability[env] += broadcast_probability
            self._entropy[env] += binary_entropy(broadcast_probability)
            self._probability_steps[env] += 1
        if not (terminated or truncated):
            return None
        record = None
        if self._started[env]:
            given = self._probability_steps[env]
            record = EpisodeRecord(
                returns=self._returns[env].copy(),
                control_returns=self._control_returns[env].copy(),
                length=int(self._length[env]),
                broadcasts=self._episode_broadcasts[env].copy(),
                terminated=bool(terminated),
                failed=bool(info.get("failed", terminated)),
                package_travel=float(info.get("package_x", math.nan)) - self._start_x[env],
                broadcast_probability=self._probability[env] / given if given else np.full(self.n_agents, math.nan),
                option_entropy=self._entropy[env] / given if given else np.full(self.n_agents, math.nan),
            )
            self.episodes.append(record)
        self._started[env] = False
        for counts in (self._returns, self._control_returns, self._probability, self._entropy):
            counts[env] = 0.0
        self._episode_broadcasts[env] = 0
        self._probability_steps[env] = 0
        self._length[env] = 0
        self._last_event[env] = -1
        return record


@dataclasses.dataclass
class Episodes:
    """Results of a policy's episodes, one entry per episode (arrays of length ``episodes``).

    :param agent_returns: every agent's return, communication cost included (episodes, N)
    :param agent_control_returns: every agent's return without the communication cost (episodes, N)
    :param lengths: steps
    :param broadcasts: broadcasts of every agent (episodes, N)
    :param terminated: whether the episode terminated (rather than being truncated)
    :param failed: whether it ended by a failure (:attr:`EpisodeRecord.failed`)
    :param package_travel: final minus initial ``info["package_x"]`` (NaN where the env does not report it)
    :param broadcast_probability: every agent's mean probability of broadcasting (episodes, N)
        (NaN where not known: a fixed trigger without ``broadcast_probability``)
    :param option_entropy: every agent's mean entropy of its options in bits (episodes, N) (NaN where not known)
    """

    agent_returns: np.ndarray
    agent_control_returns: np.ndarray
    lengths: np.ndarray
    broadcasts: np.ndarray
    terminated: np.ndarray
    failed: np.ndarray
    package_travel: np.ndarray
    broadcast_probability: np.ndarray
    option_entropy: np.ndarray

    @classmethod
    def from_records(cls, records: Sequence[EpisodeRecord]) -> Episodes:
        """The episodes of some records, in their order.

        :param records: the episodes' records
        :return: their results side by side
        """
        return cls(
            agent_returns=np.array([r.returns for r in records]),
            agent_control_returns=np.array([r.control_returns for r in records]),
            lengths=np.array([r.length for r in records]),
            broadcasts=np.array([r.broadcasts for r in records]),
            terminated=np.array([r.terminated for r in records]),
            failed=np.array([r.failed for r in records]),
            package_travel=np.array([r.package_travel for r in records]),
            broadcast_probability=np.array([r.broadcast_probability for r in records]),
            option_entropy=np.array([r.option_entropy for r in records]),
        )

    @classmethod
    def mixture(cls, lower: Episodes, upper: Episodes, savings: float) -> tuple[Episodes, float]:
        """The expected results of two triggers mixed at a savings: one of them in every episode, drawn at random.

        Running ``lower``'s trigger in episode ``k`` with probability ``w`` and ``upper``'s
        otherwise has the expected results ``w lower + (1 - w) upper`` per episode and, with
        ``w`` set here, the expected savings ``savings`` over the episodes (broadcasts over
        agent-steps, both in expectation). So a family matches a rate exactly on the episodes
        that measured it (:class:`~sb3_detc.triggers.Bracket`). Booleans (``terminated``,
        ``failed``) become their probabilities.

        :param lower: the episodes of one trigger, savings at or below ``savings``
        :param upper: the same episodes with the other trigger, savings at or above ``savings``
        :param savings: the savings to meet, between the two's
        :return: the mixture's episodes, and ``w`` (1 where ``lower`` meets ``savings`` alone)
        :raises ValueError: if ``savings`` is not between the two's
        """
        if not lower.savings <= savings <= upper.savings:
            raise ValueError(
                f"savings {savings:g} are not between the two triggers' ({lower.savings:g}, {upper.savings:g})."
            )
        rate = 1.0 - savings  # broadcasts per agent-step: w B_l + (1 - w) B_u = rate (w S_l + (1 - w) S_u)
        broadcasts = [episodes.broadcasts.sum() for episodes in (lower, upper)]
        agent_steps = [episodes.lengths.sum() * episodes.broadcasts.shape[1] for episodes in (lower, upper)]
        denominator = (broadcasts[0] - broadcasts[1]) - rate * (agent_steps[0] - agent_steps[1])
        weight = (
            1.0 if denominator == 0 else float(np.clip((rate * agent_steps[1] - broadcasts[1]) / denominator, 0, 1))
        )
        mixed = {
            field.name: weight * np.asarray(getattr(lower, field.name), dtype=np.float64)
            + (1.0 - weight) * np.asarray(getattr(upper, field.name), dtype=np.float64)
            for field in dataclasses.fields(cls)
        }
        return cls(**mixed), weight

    @property
    def returns(self) -> np.ndarray:
        """Team-mean return of every episode, communication cost included (episodes,)."""
        return self.agent_returns.mean(axis=1)

    @property
    def control_returns(self) -> np.ndarray:
        """Team-mean return of every episode without the communication cost (episodes,)."""
        return self.agent_control_returns.mean(axis=1)

    @property
    def agent_savings(self) -> np.ndarray:
        """Every agent's savings over all episodes, ``1 - broadcasts_i / steps`` (N,)."""
        return 1.0 - self.broadcasts.sum(axis=0) / self.lengths.sum()

    @property
    def savings(self) -> float:
        """Communication savings over all episodes, ``1 - broadcasts / agent-steps``."""
        return float(self.agent_savings.mean())

    @property
    def option_state_information(self) -> float:
        """Mutual information between options and state over the visited states, in bits, the mean over the agents.

        Per agent ``H(mean p) - mean H(p)`` over every step of every episode (see the module's
        text); NaN where the probabilities of broadcasting are not known.
        """
        weights = self.lengths[:, None] / self.lengths.sum()
        mean_probability = (self.broadcast_probability * weights).sum(axis=0)
        mean_entropy = (self.option_entropy * weights).sum(axis=0)
        return float(np.mean(np.maximum(binary_entropy(mean_probability) - mean_entropy, 0.0)))


@dataclasses.dataclass
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


# ----------------------------------------------------------------------------- the episode runner
@dataclasses.dataclass
class _Running:
    """An episode in progress in one of the envs."""

    index: int  # position of its seed
    obs: dict[str, np.ndarray]


def evaluate_episodes(
    policy: MlpHybridPolicy,
    env: gym.Env | str,
    seeds: Sequence[int | None],
    deterministic: bool = True,
    sample_options: bool | None = None,
    fixed_trigger: FixedTrigger | None = None,
) -> Episodes:
    """Run a policy for whole episodes, one per seed, and record each (:class:`EpisodeCounter`).

    Where every episode has its seed and ``env`` can be made again (``env.spec``, as for an
    env from ``gym.make`` or an id, with wrappers that Gymnasium can make again), the episodes
    run side by side in ``env`` and copies made with ``gym.make(env.spec)`` (at most
    :data:`MAX_SIDE_BY_SIDE` at once), with one policy call per step for all of them;
    otherwise one after another in ``env``. Episode
    ``k`` is reset with ``seeds[k]`` either way, and the results are in the order of ``seeds``.
    The copies have the settings of ``env.spec``: what was changed in ``env`` after it was
    made (e.g. its broadcast cost set by hand) does not carry over, and a wrapper put around it
    by hand is made again only if it records its arguments (Gymnasium's ``RecordConstructorArgs``,
    as :class:`~sb3_detc.triggers.FixedControl` and :class:`~sb3_detc.triggers.ReceiverPredictions`
    do); give an env changed by hand without a spec. Where every episode has its
    seed, the policy's draws (options sampled from ``mu``, controls unless ``deterministic``)
    are seeded with the first (PyTorch's CPU generator, left as it was afterwards; a policy on
    a GPU draws from the GPU's): the same policy, env and seeds give the same episodes.
    The probabilities of broadcasting are recorded at every step: ``mu``'s
    (:meth:`~sb3_detc.mappoc.policies.MlpHybridPolicy.broadcast_probabilities`), or those of
    ``fixed_trigger`` where it has ``broadcast_probability(obs)``.

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
        sample_options = options_sampled(policy.sample_options, deterministic)
    policy.set_training_mode(False)
    low, high = env.action_space["control"].low, env.action_space["control"].high
    decide = None if fixed_trigger is None else _options_and_probabilities(fixed_trigger)
    seeded = all(seed is not None for seed in seeds)
    copies = []
    if seeded and env.spec is not None:
        try:
            copies = [gym.make(env.spec) for _ in range(min(len(seeds), MAX_SIDE_BY_SIDE) - 1)]
        except (ValueError, gym.error.Error):  # a wrapper that cannot be made again (the first copy fails)
            copies = []  # one episode after another
    envs = [env, *copies]
    counter = EpisodeCounter(len(envs))
    pending = iter(enumerate(seeds))
    running: dict[int, _Running] = {}  # env position -> its episode
    records: list[EpisodeRecord | None] = [None] * len(seeds)

    def start(slot: int) -> None:
        index, seed = next(pending, (None, None))
        if index is not None:
            obs, info = envs[slot].reset(seed=seed)
            counter.start(slot, info)
            running[slot] = _Running(index, obs)

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
                    obs = obs_as_tensor(batch, policy.device)
                    forced = None
                    if decide is None:
                        probability = policy.broadcast_probabilities(obs).cpu().numpy()
                    else:
                        options, probability = decide(batch)
                        forced = th.as_tensor(options, device=policy.device)
                    sampled, controls = policy.sample_actions(
                        obs, broadcast=forced, deterministic=deterministic, sample_options=sample_options
                    )
                sampled, controls = sampled.cpu().numpy(), np.clip(controls.cpu().numpy(), low, high)
                for row, slot in enumerate(slots):
                    obs, _, terminated, truncated, info = envs[slot].step(
                        {"broadcast": sampled[row], "control": controls[row]}
                    )
                    running[slot].obs = obs
                    record = counter.step(
                        slot, info, terminated, truncated, None if probability is None else probability[row]
                    )
                    if terminated or truncated:
                        records[running.pop(slot).index] = record
                        start(slot)
    finally:
        for copy in copies:
            copy.close()
    return Episodes.from_records(records)  # type: ignore[arg-type]


def _options_and_probabilities(
    trigger: FixedTrigger,
) -> Callable[[dict[str, np.ndarray]], tuple[np.ndarray, np.ndarray | None]]:
    """A fixed trigger's options and probabilities of broadcasting for a batch, each computed once.

    A stateless trigger's probabilities are its options (unless it defines its own
    ``broadcast_probability``); another trigger's come from its ``broadcast_probability`` (None
    without one).

    :param trigger: the fixed trigger
    :return: a function of a batch of joint observations: options (B, N) and probabilities (B, N) or None
    """
    if getattr(type(trigger), "broadcast_probability", None) is StatelessTrigger.broadcast_probability:

        def stateless(batch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
            options = trigger(batch)
            return options, options.astype(np.float64)

        return stateless
    probability = getattr(trigger, "broadcast_probability", None)

    def drawn(batch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
        return trigger(batch), None if probability is None else probability(batch)

    return drawn


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
    return CommunicationReport(
        mean_return=float(np.mean(episodes.returns)),
        mean_control_return=float(np.mean(episodes.control_returns)),
        std_control_return=float(np.std(episodes.control_returns)),
        broadcast_rate=1.0 - episodes.savings,
        savings=episodes.savings,
        agent_savings=episodes.agent_savings,
        episodes=n_eval_episodes,
    )


# ----------------------------------------------------------------------------- the protocol
def _episodes_json(episodes: Episodes) -> dict[str, Any]:
    """One evaluation mode's episodes as JSON lists, one entry per episode.

    The returns and the package travel are written at the precision the envs compute them in
    (float32, the shortest decimal that reads back as the same float32); the metrics of the
    protocol are computed before, at full precision.

    :param episodes: the mode's episodes
    :return: ``return``, ``control_return``, ``length``, ``broadcasts`` (of all agents), ``failed`` and
        ``package_travel`` (None where not reported) per episode, and ``savings`` over all of them
    """
    return {
        "return": float32_list(episodes.returns),
        "control_return": float32_list(episodes.control_returns),
        "length": episodes.lengths.tolist(),
        "broadcasts": episodes.broadcasts.sum(axis=1).tolist(),
        "failed": episodes.failed.tolist(),
        "package_travel": [None if math.isnan(x) else x for x in float32_list(episodes.package_travel)],
        "savings": episodes.savings,
    }


def float32_list(values: np.ndarray) -> list[float]:
    """Numbers as the shortest decimals that read back as the same float32 values.

    :param values: the numbers (any float array)
    :return: a list of Python floats, e.g. ``-9.123457`` for ``-9.123456789``
    """
    return [float(np.format_float_positional(x)) for x in np.asarray(values, dtype=np.float32)]


#: The linear system's ids, whose settings the env of predictive triggering (:data:`PREDICTED_ID`) takes.
LINEAR_IDS = ("sb3_detc/LinearETC-v0", "sb3_detc/LinearETC-LQR-v0")
#: The id of the linear system with LQR controls, which ``prediction=True`` puts on the predicted states.
PREDICTED_ID = "sb3_detc/LinearETC-LQR-v0"


def fixed_family_env(env: gym.Env, family: str) -> gym.Env:
    """The env in which a fixed trigger family runs: predictive triggering with LQR on the predicted states.

    :param env: the evaluation env (a joint env)
    :param family: a name from :data:`~sb3_detc.triggers.TRIGGER_FAMILIES`
    :return: ``env`` itself, or for ``"predictive"`` the linear system with its settings and the
        controls of :func:`~sb3_detc.triggers.lqr_on_predicted_states` (the model-based anchor),
        its observations the held broadcasts (not :class:`~sb3_detc.triggers.ReceiverPredictions`)
    :raises ValueError: for ``"predictive"`` on an env without a linear system
    """
    if family != "predictive":
        return env
    spec = env.spec
    if spec is None:  # run one episode after another: nothing to copy
        joint = env.unwrapped
        return FixedControl(joint, "lqr_on_predicted_states")
    if spec.id not in LINEAR_IDS:
        raise ValueError(f"predictive triggering needs the linear system ({', '.join(LINEAR_IDS)}), got {spec.id!r}.")
    # PredictiveTrigger predicts from the held broadcasts themselves: not on the env that shows the predictions
    kwargs = {**spec.kwargs, "prediction": True, "predicted_held": False}
    return gym.make(PREDICTED_ID, **kwargs)  # copies made from its spec run it too


def evaluate_fixed_family(
    policy: MlpHybridPolicy,
    env: gym.Env,
    family: str,
    savings: float,
    seeds: Sequence[int],
    tune_seeds: Sequence[int],
    tolerance: float = 0.01,
) -> tuple[str, Episodes]:
    """A fixed trigger family at exactly a given savings on the evaluation's episodes: a mixture of two of its triggers.

    The family's two triggers whose savings on the episodes ``seeds`` enclose ``savings`` are found by
    :func:`~sb3_detc.triggers.bracket_trigger` (a threshold family's search starts from the
    bracket found on the cheaper episodes ``tune_seeds``), with the policy's controls (or, for
    ``"predictive"``, LQR on the predicted states: :func:`fixed_family_env`); their mixture
    (:meth:`Episodes.mixture`) meets ``savings`` on the episodes exactly, so the family is
    compared at the same rate, not at a rate within a tolerance of it.

    :param policy: the policy whose controls act (the options come from the trigger)
    :param env: the evaluation env (a joint env)
    :param family: a name from :data:`~sb3_detc.triggers.TRIGGER_FAMILIES`
    :param savings: the savings to meet, in (0, 1)
    :param seeds: the evaluation episodes' seeds
    :param tune_seeds: the seeds of the episodes a threshold search starts on
    :param tolerance: the width in savings at which a threshold search stops
        (:func:`~sb3_detc.triggers.bracket_trigger`)
    :return: the mixture (e.g. ``0.25 x PeriodicTrigger(period=8, ...) + 0.75 x PeriodicTrigger(period=9, ...)``,
        or one trigger where it meets ``savings`` alone) and its expected episodes
    :raises SavingsNotReached: if no two triggers of the family enclose ``savings``
    :raises ValueError: for ``"predictive"`` on an env without a linear system, or savings outside (0, 1)
    """
    runs_in = fixed_family_env(env, family)
    return _matched(policy, runs_in, family, savings, seeds, tune_seeds, tolerance, system_or_env=env.unwrapped)


def _matched(
    policy: MlpHybridPolicy,
    env: gym.Env,
    family: str | Callable[[float], FixedTrigger],
    savings: float,
    seeds: Sequence[int],
    tune_seeds: Sequence[int],
    tolerance: float,
    **bracket_kwargs: Any,
) -> tuple[str, Episodes]:
    """A family's mixture at exactly a savings on the episodes ``seeds``, see :func:`evaluate_fixed_family`.

    :param policy: the policy whose controls act
    :param env: the env the triggers run in
    :param family: a name from :data:`~sb3_detc.triggers.TRIGGER_FAMILIES` or a callable from a threshold to a trigger
    :param savings: the savings to meet, in (0, 1)
    :param seeds: the evaluation episodes' seeds
    :param tune_seeds: the seeds of the episodes a threshold search starts on
    :param tolerance: the width in savings at which a threshold search stops
    :param bracket_kwargs: further arguments of :func:`~sb3_detc.triggers.bracket_trigger`
    :return: the mixture's description and its expected episodes
    """
    runs: list[tuple[FixedTrigger, Episodes]] = []

    def savings_of(trigger: FixedTrigger) -> float:
        runs.append((trigger, evaluate_episodes(policy, env, seeds, fixed_trigger=trigger)))
        return runs[-1][1].savings

    if family not in PERIODIC_FAMILIES and len(tune_seeds) < len(seeds):  # start near: a bracket on fewer episodes

        def tune_savings_of(trigger: FixedTrigger) -> float:
            return evaluate_episodes(policy, env, tune_seeds, fixed_trigger=trigger).savings

        start = bracket_trigger(family, tune_savings_of, savings, tolerance, **bracket_kwargs)
        bracket_kwargs.update(
            initial=math.sqrt(start.lower_parameter * start.upper_parameter),
            factor=max(start.upper_parameter / start.lower_parameter, 1.1),
        )
    bracket = bracket_trigger(family, savings_of, savings, tolerance, **bracket_kwargs)
    lower, upper = (next(run for trigger, run in runs if trigger is t) for t in (bracket.lower, bracket.upper))
    result, weight = Episodes.mixture(lower, upper, savings)
    if bracket.lower is bracket.upper:
        return repr(bracket.lower), result
    return f"{weight:.3f} x {bracket.lower!r} + {1 - weight:.3f} x {bracket.upper!r}", result


class ThresholdedOptions(StatelessTrigger):
    """A learned policy over options made deterministic: broadcast where ``mu``'s probability exceeds a threshold.

    The most likely option of ``mu`` (the protocol's ``mode``) is the threshold 0.5; other
    thresholds give the same ranking of states at other rates, so a policy over options that an
    entropy bonus or a short training keeps soft (it broadcasts with some probability in
    nearly every state) runs as a sharp rule at the rate it learned: :func:`evaluate_thresholded`
    tunes the threshold to a savings target. Stateless (a function of the observations alone,
    through the policy), so it serves as a fixed trigger wherever one is accepted.

    A policy with a window of broadcast intervals (``broadcast_interval``) keeps it at every
    threshold: silent where the window forbids a broadcast, broadcasting where it forces one.

    :param policy: the policy whose ``mu`` decides
    :param threshold: the probability of broadcasting above which an agent broadcasts, > 0 (1 and
        above: never, but where a window forces a broadcast)
    """

    def __init__(self, policy: MlpHybridPolicy, threshold: float) -> None:
        if isinstance(threshold, bool) or not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be a finite number > 0, got {threshold!r}.")
        self.policy = policy
        self.threshold = float(threshold)

    def __repr__(self) -> str:
        return f"ThresholdedOptions(threshold={self.threshold!r})"

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N): 1 where ``mu``'s probability exceeds the threshold.

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key
        """
        with th.no_grad():
            probability = self.policy.broadcast_probabilities(obs_as_tensor(obs, self.policy.device))
        options = (probability > self.threshold).cpu().numpy()
        if self.policy.broadcast_interval is not None:  # forced broadcasts have probability one, kept above 1
            options |= interval_window(np.asarray(obs["age"]), *self.policy.broadcast_interval)[1]
        return options.astype(np.int64)


def evaluate_thresholded(
    policy: MlpHybridPolicy,
    env: gym.Env,
    savings: float,
    seeds: Sequence[int],
    tune_seeds: Sequence[int],
    tolerance: float = 0.01,
) -> tuple[str, Episodes]:
    """The policy's ``mu`` thresholded at exactly a given savings on the evaluation's episodes.

    Two thresholds (:class:`ThresholdedOptions`) whose savings enclose ``savings`` are found
    and mixed as a fixed family's triggers are (:func:`evaluate_fixed_family`; the search
    starts from 0.5, ``mu``'s mode), with the policy's controls.

    :param policy: the policy whose ``mu`` is thresholded and whose controls act
    :param env: the evaluation env (a joint env)
    :param savings: the savings to meet, in (0, 1)
    :param seeds: the evaluation episodes' seeds
    :param tune_seeds: the seeds of the episodes the search starts on
    :param tolerance: the width in savings at which the search stops (:func:`~sb3_detc.triggers.bracket_trigger`)
    :return: the mixture's description and its expected episodes
    :raises SavingsNotReached: if no two thresholds enclose ``savings``
    :raises ValueError: for savings outside (0, 1)
    """

    def make_trigger(threshold: float) -> ThresholdedOptions:
        return ThresholdedOptions(policy, threshold)

    return _matched(policy, env, make_trigger, savings, seeds, tune_seeds, tolerance, initial=0.5)


def evaluate_policy_modes(
    policy: MlpHybridPolicy,
    env: gym.Env,
    episodes: int,
    seed: int,
    own_trigger: FixedTrigger | None = None,
    sample_options: bool | None = None,
    on_mode: Callable[[str, Episodes], None] | None = None,
    fixed_families: Sequence[str] = (),
    tune_episodes: int = 20,
) -> dict[str, Any]:
    """The package's evaluation protocol: the same seeded episodes in every communication mode.

    Episode ``k`` is reset with ``seed + k`` in every mode; the control policy acts with its
    mean. The modes (:data:`MODES`):

    * ``learned``: the policy's own trigger. Its options are sampled from the policy over
      options ``mu`` or its most likely ones, as ``sample_options`` says (the paper's entries
      sample, :class:`~sb3_detc.mappoc.policies.MlpHybridPolicy`), or they come from the fixed
      trigger the policy trained with, ``own_trigger``;
    * ``mode``: the most likely options of ``mu`` (only for a policy that learned its options,
      i.e. without ``own_trigger``; the ``learned`` mode's episodes where those take them too);
    * ``random_same_rate``: every agent skips at random with the ``learned`` mode's savings;
    * ``periodic``: every agent broadcasts at every step;
    * ``never``: no broadcasts after the reset;
    * ``fixed_<family>`` for every family of ``fixed_families``: the family at exactly the
      ``learned`` mode's savings on these episodes, the mixture of its two triggers whose savings
      enclose them (:func:`evaluate_fixed_family`; a threshold search starts on the first
      ``tune_episodes`` episodes); a family whose triggers do not enclose them, or that the env
      cannot run (``predictive`` needs the linear system), is left out and the reason recorded;
    * ``thresholded`` with ``fixed_families``, for a policy that learned its options: ``mu``
      made deterministic at exactly the ``learned`` mode's savings (:class:`ThresholdedOptions`,
      two thresholds mixed as the families' triggers are: :func:`evaluate_thresholded`; it runs
      only when families are compared), left out with its reason where no two thresholds enclose
      them (or the learned savings are 0 or 1).

    :param policy: the trained policy
    :param env: a joint env with the trial's settings (communication cost included)
    :param episodes: episodes per mode
    :param seed: seed of the first episode
    :param own_trigger: the fixed trigger the policy trained with (None: its policy over options)
    :param sample_options: the ``learned`` mode samples its options from ``mu`` (True) or takes
        the most likely ones (False) (None: as the policy's ``sample_options`` says)
    :param on_mode: called with every mode's name and episodes when they are done (e.g. to show progress)
    :param fixed_families: the fixed trigger families to compare at the learned rate, names from
        :data:`~sb3_detc.triggers.TRIGGER_FAMILIES` (default: none)
    :param tune_episodes: episodes the threshold searches of the families and of the ``thresholded`` mode start
        on (the first of the evaluation's; the match itself is on all of them)
    :return: ``episodes``, ``seed``, ``options`` (how the ``learned`` mode took its options:
        ``"sampled"``, ``"mode"`` or ``"fixed trigger"``), ``modes`` (mode -> per-episode lists
        and savings) and ``metrics``: ``return``, ``control_return`` and ``savings`` of the
        ``learned`` mode; ``<mode>_return`` and ``<mode>_control_return`` of every other mode and
        ``<mode>_savings`` of ``mode``, ``thresholded`` and ``random_same_rate``;
        ``learned_minus_random_control_return`` (the mean paired difference of the learned and
        the random control returns); ``option_state_information`` (the ``learned`` mode's
        dependence on the state, :attr:`Episodes.option_state_information`, where its
        probabilities of broadcasting are known); and where the env reports the package
        (Multiwalker) ``package_travel``, ``fall_rate`` and ``success`` of the ``learned`` mode,
        ``<mode>_package_travel`` of ``mode``, ``thresholded``, ``random_same_rate`` and ``periodic``, and
        ``mode_fall_rate``; with ``fixed_families`` also ``fixed`` (family -> its matched mixture, or
        why it was left out), ``best_fixed`` (the family with the highest mean control return) and the
        metrics ``fixed_<family>_control_return``, ``fixed_<family>_savings``,
        ``best_fixed_control_return`` and ``learned_minus_best_fixed_control_return`` (the mean
        paired difference of the learned and the best family's control returns); and where the
        ``thresholded`` mode ran, ``thresholded`` (its matched mixture, or why it was left out), the
        metric ``thresholded_savings`` and, with a best family,
        ``thresholded_minus_best_fixed_control_return`` (the mean paired difference)
    """
    unknown = [family for family in fixed_families if family not in TRIGGER_FAMILIES]
    if unknown:
        raise ValueError(f"fixed_families must be names from {TRIGGER_FAMILIES}, got {unknown}.")
    seeds = [seed + k for k in range(episodes)]
    if sample_options is None:
        sample_options = policy.sample_options
    if own_trigger is not None and hasattr(own_trigger, "fork"):
        own_trigger = own_trigger.fork(seed)
    results: dict[str, Episodes] = {}

    def run(mode: str, result: Episodes) -> Episodes:
        results[mode] = result
        if on_mode is not None:
            on_mode(mode, result)
        return result

    learned = run(
        "learned",
        evaluate_episodes(
            policy, env, seeds, deterministic=True, sample_options=sample_options, fixed_trigger=own_trigger
        ),
    )
    if own_trigger is None:
        run("mode", evaluate_episodes(policy, env, seeds, sample_options=False) if sample_options else learned)
    for mode, skip in (("random_same_rate", learned.savings), ("periodic", 0.0), ("never", 1.0)):
        trigger = RandomTrigger(float(np.clip(skip, 0.0, 1.0)), seed=seed)
        run(mode, evaluate_episodes(policy, env, seeds, deterministic=True, fixed_trigger=trigger))
    fixed: dict[str, str] = {}
    tune_seeds = seeds[: max(1, tune_episodes)]
    for family in fixed_families:
        try:
            tuned, result = evaluate_fixed_family(policy, env, family, learned.savings, seeds, tune_seeds)
        except ValueError as reason:  # SavingsNotReached among them
            fixed[family] = f"left out: {reason}"
            continue
        fixed[family] = tuned
        run(f"fixed_{family}", result)
    thresholded = None
    if fixed_families and own_trigger is None:
        try:
            tuned, result = evaluate_thresholded(policy, env, learned.savings, seeds, tune_seeds)
        except ValueError as reason:  # SavingsNotReached, or learned savings of 0 or 1: no rate to tune to
            thresholded = f"left out: {reason}"
        else:
            thresholded = tuned
            run("thresholded", result)
    metrics: dict[str, float] = {
        "return": float(np.mean(learned.returns)),
        "control_return": float(np.mean(learned.control_returns)),
        "savings": learned.savings,
    }
    others = [mode for mode in MODES[1:] if mode in results]
    for mode in others:
        metrics[f"{mode}_return"] = float(np.mean(results[mode].returns))
        metrics[f"{mode}_control_return"] = float(np.mean(results[mode].control_returns))
    for mode in ("mode", "thresholded", "random_same_rate"):
        if mode in results:
            metrics[f"{mode}_savings"] = results[mode].savings
    difference = learned.control_returns - results["random_same_rate"].control_returns
    metrics["learned_minus_random_control_return"] = float(np.mean(difference))
    information = learned.option_state_information
    if not math.isnan(information):
        metrics["option_state_information"] = information
    if not np.isnan(learned.package_travel).any():
        metrics["package_travel"] = float(np.mean(learned.package_travel))
        metrics["fall_rate"] = float(np.mean(learned.failed))
        for mode in ("mode", "thresholded", "random_same_rate", "periodic"):
            if mode in results:
                metrics[f"{mode}_package_travel"] = float(np.mean(results[mode].package_travel))
        if "mode" in results:
            metrics["mode_fall_rate"] = float(np.mean(results["mode"].failed))
        upright = 1.0 - metrics["fall_rate"] >= SUCCESS_NO_FALL
        metrics["success"] = float(upright and carries_package(metrics))
    compared = {family: results[f"fixed_{family}"] for family in fixed_families if f"fixed_{family}" in results}
    for family, result in compared.items():
        metrics[f"fixed_{family}_control_return"] = float(np.mean(result.control_returns))
        metrics[f"fixed_{family}_savings"] = result.savings
    best = max(compared, key=lambda family: float(np.mean(compared[family].control_returns)), default=None)
    if best is not None:
        metrics["best_fixed_control_return"] = float(np.mean(compared[best].control_returns))
        paired = learned.control_returns - compared[best].control_returns
        metrics["learned_minus_best_fixed_control_return"] = float(np.mean(paired))
        if "thresholded" in results:
            paired = results["thresholded"].control_returns - compared[best].control_returns
            metrics["thresholded_minus_best_fixed_control_return"] = float(np.mean(paired))
    options = "fixed trigger" if own_trigger is not None else "sampled" if sample_options else "mode"
    evaluation = {
        "episodes": episodes,
        "seed": seed,
        "options": options,
        "modes": {mode: _episodes_json(result) for mode, result in results.items()},
        "metrics": metrics,
    }
    if fixed_families:
        evaluation.update(fixed=fixed, best_fixed=best)
    if thresholded is not None:
        evaluation["thresholded"] = thresholded
    return evaluation
