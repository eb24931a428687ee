"""Decentralised execution of a MAPPOC model on the paper's modified Multiwalker.

Training is centralised (the option-value critic sees every walker's true state);
execution is not. After training, each walker needs only

* its own :class:`~sb3_detc.mappoc.AgentController` (``model.policy.agent_controller(i)``:
  its policy over options ``mu_i`` and its control policy ``pi_i``),
* its own sensors, and
* its own :class:`~sb3_detc.mappoc.Inbox`: the last message received from every other
  walker and its age, kept with the project's rule (:func:`sb3_detc.network.hold`,
  :func:`sb3_detc.network.advance_timer`).

Every step (:func:`~sb3_detc.mappoc.run_decentralised_step`): (a) every walker decides
from its own trigger features (package now and at its own last broadcast) whether to
broadcast; (b) the broadcasters' messages go out on the radio and every walker files them
in its inbox; (c) every walker views the others' held messages relative to its own current
message, with their ages, and computes its control; (d) here, the PettingZoo env is
stepped with ``{walker: {"broadcast": sent, "control": u}}``. At the start of an episode every
walker's initial message counts as received (age 0), as in the simulated network.

Where a message comes from: a real walker would read its absolute position and velocity
(x, y, vx, vy, the message of Sec. 2 of the method reference) from its own sensors. In
the simulation those readings are ``env.system.last_obs.message[i]``; walker ``i`` reads
only its own row. The PettingZoo observation is used only for what a walker knows itself
(``local``, ``trigger``, ``trigger_held``); its ``neighbours`` fields are ignored here,
because the inbox rebuilds them from the exchanged messages.

The default training (4096 steps, under a minute) only shows the mechanics: the walkers
will fall. The paper trains for about 6e6 steps (3000 iterations of 2048 steps); pass such
a model with ``--model``. Run::

    python examples/decentralised_multiwalker.py [--timesteps 4096] [--model model.zip]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
import torch as th

import sb3_detc  # noqa: F401  (registers sb3_detc/MultiwalkerETC-v0)
from sb3_detc.envs import multiwalker_etc_v0
from sb3_detc.envs.wrappers import EventTriggeredNetwork
from sb3_detc.mappoc import MAPPOC, AgentController, Inbox, run_decentralised_step


def own_sensor_readings(env: EventTriggeredNetwork) -> np.ndarray:
    """Every walker's current message (x, y, vx, vy) as it reads it from its own sensors, (N, 4)."""
    return env.system.last_obs.message


def run_episode(
    env: EventTriggeredNetwork, controllers: Sequence[AgentController], seed: int, deterministic: bool = True
) -> dict:
    """One episode of decentralised execution; returns returns, package travel and broadcasts per walker."""
    obs, infos = env.reset(seed=seed)
    walkers = env.possible_agents
    inboxes = [Inbox(i, env.n_agents) for i in range(env.n_agents)]
    for inbox in inboxes:  # the initial messages count as received, age 0
        inbox.reset(own_sensor_readings(env))
    start_x = infos[walkers[0]]["package_x"]
    returns, broadcasts, steps = np.zeros(len(walkers)), np.zeros(len(walkers), dtype=int), 0
    while env.agents:
        # (a)-(c): decide, exchange broadcasts, act; each walker uses only its own inputs and inbox
        actions = run_decentralised_step(controllers, inboxes, obs, own_sensor_readings(env), deterministic)
        # (d): the plant moves
        obs, rewards, _, _, _ = env.step(actions)
        returns += [rewards[w] for w in walkers]
        broadcasts += [actions[w]["broadcast"] for w in walkers]
        steps += 1
    # The PettingZoo infos carry only `broadcast` and `broadcasts`; the package position is in the Box2D world.
    travel = env.system.physics.package.position.x - start_x
    return {"steps": steps, "returns": returns, "travel": travel, "broadcasts": broadcasts}


def main(argv: Sequence[str] | None = None) -> None:
    """Train (or load) a model, then run it decentralised and print what happened."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=4096, help="training steps (the paper: about 6e6)")
    parser.add_argument("--model", help="load this saved MAPPOC model instead of training")
    parser.add_argument("--episodes", type=int, default=3, help="episodes of decentralised execution")
    parser.add_argument("--seed", type=int, default=0, help="seed of training and of the first episode")
    parser.add_argument(
        "--stochastic",
        action="store_true",
        help="sample the controls and the options (default: mean of pi, and the options as the policy's "
        "sample_options says: sampled from mu for the paper's entries, else its most likely option)",
    )
    args = parser.parse_args(argv)
    th.set_num_threads(1)  # small networks: one thread is fastest, and the machine may be shared
    th.manual_seed(args.seed)  # the controllers sample with torch's generator

    if args.model:
        model = MAPPOC.load(args.model, device="cpu")
        print(f"loaded {args.model}")
    else:
        start = time.perf_counter()
        model = MAPPOC("MlpHybridPolicy", "sb3_detc/MultiwalkerETC-v0", seed=args.seed, device="cpu")
        model.learn(args.timesteps)
        print(f"trained {args.timesteps} steps in {time.perf_counter() - start:.0f} s (a real run: ~6e6 steps)")

    env = multiwalker_etc_v0.parallel_env()
    controllers = [model.policy.agent_controller(i) for i in range(env.n_agents)]
    for k in range(args.episodes):
        result = run_episode(env, controllers, seed=args.seed + k, deterministic=not args.stochastic)
        savings = 1 - result["broadcasts"] / result["steps"]  # Gamma_i: against broadcasting every step
        per_walker = ", ".join(
            f"{w} {r:.1f} ({s:.0%} saved)"
            for w, r, s in zip(env.possible_agents, result["returns"], savings, strict=True)
        )
        print(
            f"episode {k}: {result['steps']} steps, return {result['returns'].mean():.1f}, "
            f"package travel {result['travel']:.2f} m | {per_walker}"
        )
    env.close()


if __name__ == "__main__":
    main()
