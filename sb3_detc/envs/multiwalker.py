"""The paper's modified Multiwalker (method.md, Sec. 5) on PettingZoo's own Multiwalker physics.

Against the stock ``pettingzoo.sisl.multiwalker_v9``: motor torque x1.5, no LIDAR (not even
computed), no neighbour information and no sensor noise in the observation, per-agent rewards
with a horizontal-speed potential shaping instead of the head-angle one, and Gymnasium seeding
(one generator per environment drives terrain, clouds and every walker's initial push).

The physics, terrain, package, clouds and drawing are the stock classes; only what has to
change is overridden: :class:`EtcBipedalWalker` (torque, no LIDAR, shared generator),
:class:`EtcContactDetector` (stock rules, cheaper look-ups) and :class:`EtcMultiWalkerEnv`
(fresh world per episode, one generator, off-screen rendering). :class:`MultiwalkerSystem`
exposes it as a :class:`~sb3_detc.envs.system.CommunicatingSystem`.
"""

from __future__ import annotations

from typing import Any

import Box2D
import numpy as np
import pygame
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo.sisl.multiwalker import multiwalker_base as stock
from pettingzoo.sisl.multiwalker.multiwalker_base import BipedalWalker, ContactDetector, MultiWalkerEnv

from sb3_detc.envs.system import CommunicatingSystem, SystemObs
from sb3_detc.validation import is_integer

#: Maximum number of walkers (the stock limit).
MAX_WALKERS = stock.MAX_AGENTS

#: Maximum motor torque of every joint: the stock 80 times 1.5.
MOTORS_TORQUE = 1.5 * stock.MOTORS_TORQUE

#: Hull x velocity (m/s) to the stock observation's normalised value, ``0.3 * (600 / 30) / 50 = 0.12``.
HULL_VX_SCALE = 0.3 * (stock.VIEWPORT_W / stock.SCALE) / stock.FPS

#: Hull y velocity (m/s) to the stock observation's normalised value, ``0.3 * (400 / 30) / 50 = 0.08``
#: (local state only).
HULL_VY_SCALE = 0.3 * (stock.VIEWPORT_H / stock.SCALE) / stock.FPS

#: Hull angular velocity (rad/s) to the stock observation's value, ``2 / 50``.
ANGULAR_VELOCITY_SCALE = 2.0 / stock.FPS

#: Velocity (m/s) to message units, for BOTH axes: the stock x factor 0.12. One factor keeps
#: relative velocities between agents consistent (the released code mixed 0.12 and 0.08).
MESSAGE_VELOCITY_SCALE = HULL_VX_SCALE

#: Hull x velocity (m/s) inside the speed potential ``-speed_penalty * |0.12 * vx|``.
SPEED_SHAPING_SCALE = HULL_VX_SCALE

#: Reward per metre of package travel and unit of ``forward_reward`` (stock: ``130 / SCALE``).
PROGRESS_SCALE = 130.0 / stock.SCALE

#: Number of local-state values: package (dx, dy, angle) then the walker's 14 own values.
N_LOCAL = 17

#: Broadcast marks in rendered frames: colours of a broadcast (disc) and of silence (ring),
#: radius and height above the hull centre in pixels.
BROADCAST_COLOR = (0, 170, 60)
SILENT_COLOR = (150, 150, 150)
MARKER_RADIUS = 6
MARKER_HEIGHT = 28

# Own-state row read from Box2D (see EtcBipedalWalker.raw_state) -> stock normalisation:
# hull angle, angular velocity, vx, vy, then per leg hip angle, hip speed, knee angle + 1, knee speed, contact.
_LEG_SCALE = (1.0, 1.0 / stock.SPEED_HIP, 1.0, 1.0 / stock.SPEED_KNEE, 1.0)
_OWN_SCALE = np.array((1.0, ANGULAR_VELOCITY_SCALE, HULL_VX_SCALE, HULL_VY_SCALE, *_LEG_SCALE, *_LEG_SCALE))
_OWN_OFFSET = np.array((0.0,) * 6 + (1.0,) + (0.0,) * 4 + (1.0,) + (0.0,) * 2)
_JOINT_SPEEDS = np.array((stock.SPEED_HIP, stock.SPEED_KNEE, stock.SPEED_HIP, stock.SPEED_KNEE), dtype=np.float64)


def motor_commands(control: np.ndarray) -> tuple[list, list]:
    """Apply the stock motor law with :data:`MOTORS_TORQUE` to controls of shape (..., 4).

    :param control: hip 1, knee 1, hip 2, knee 2 commands (only sign and magnitude up to 1 matter)
    :return: motor speeds ``sign(u) * max speed`` and maximum torques ``min(|u|, 1) * 120`` as lists
    """
    control = np.asarray(control, dtype=np.float64)
    return (np.sign(control) * _JOINT_SPEEDS).tolist(), (np.minimum(np.abs(control), 1.0) * MOTORS_TORQUE).tolist()


class EtcBipedalWalker(BipedalWalker):
    """Stock bipedal walker with 1.5x motor torque, no LIDAR and its environment's generator.

    :param world: the Box2D world
    :param init_x: initial hull x position (m)
    :param init_y: initial hull y position (m)
    :param np_random: the environment's generator (draws the initial push at every reset)
    """

    def __init__(self, world: Box2D.b2World, init_x: float, init_y: float, np_random: np.random.Generator) -> None:
        self.np_random = np_random
        super().__init__(world, init_x=init_x, init_y=init_y)

    def _seed(self, seed: int | None = None) -> list:
        # The stock walker owns a generator seeded like every other walker; ours is the env's.
        return []

    def _reset(self) -> None:
        super()._reset()
        self.lidar = []  # nothing is cast, and the stock render then draws no rays
        for joint in self.joints:
            joint.maxMotorTorque = MOTORS_TORQUE

    def set_motors(self, speeds: list[float], torques: list[float]) -> None:
        """Set motor speed and maximum torque of the joints (hip 1, knee 1, hip 2, knee 2).

        :param speeds: motor speeds (rad/s), one per joint
        :param torques: maximum motor torques (N m), one per joint
        """
        for joint, speed, torque in zip(self.joints, speeds, torques, strict=True):
            joint.motorSpeed = speed
            joint.maxMotorTorque = torque

    def apply_action(self, action: np.ndarray) -> None:
        """Set the motors from one action of 4 values, see :func:`motor_commands`.

        :param action: hip 1, knee 1, hip 2, knee 2 commands, shape (4,)
        """
        self.set_motors(*motor_commands(action))

    def raw_state(self) -> tuple:
        """Read the unscaled own state (SI units, 16 values).

        Hull angle, angular velocity, vx, vy, then per leg hip angle, hip speed, knee angle,
        knee speed, foot contact, then hull x, y.

        :return: the 16 values, in this order
        """
        hull = self.hull
        vel, pos = hull.linearVelocity, hull.position
        hip1, knee1, hip2, knee2 = self.joints
        return (
            hull.angle, hull.angularVelocity, vel.x, vel.y,
            hip1.angle, hip1.speed, knee1.angle, knee1.speed, self.legs[1].ground_contact,
            hip2.angle, hip2.speed, knee2.angle, knee2.speed, self.legs[3].ground_contact,
            pos.x, pos.y,
        )  # fmt: skip


class EtcContactDetector(ContactDetector):
    """Stock contact rules with hash look-ups instead of Python loops over all walkers per contact.

    A hull touching anything but the package marks its walker fallen; the package touching
    anything but a hull is game over; lower legs keep their ground contact flags.

    :param env: the environment whose walkers and package exist already
    """

    def __init__(self, env: EtcMultiWalkerEnv) -> None:
        super().__init__(env)
        self.hulls = {hash(walker.hull): i for i, walker in enumerate(env.walkers)}
        self.feet = {hash(leg): leg for walker in env.walkers for leg in (walker.legs[1], walker.legs[3])}
        self.package = hash(env.package)

    def _touch(self, body: int, other: int) -> None:
        """Apply the stock contact rules to one side of a contact: ``body`` touches ``other``.

        :param body: hash of the Box2D body whose rule applies (a hull, the package or a lower leg)
        :param other: hash of the Box2D body it touches
        """
        index = self.hulls.get(body)
        if index is not None and other != self.package:
            self.env.fallen_walkers[index] = True
        if body == self.package and other not in self.hulls:
            self.env.game_over = True
        foot = self.feet.get(body)
        if foot is not None:
            foot.ground_contact = True

    def BeginContact(self, contact: Box2D.b2Contact) -> None:  # noqa: N802 (Box2D name)
        """Update fallen walkers, game over and foot contacts when two bodies start touching.

        :param contact: the new contact (the bodies of its two fixtures are read)
        """
        a, b = hash(contact.fixtureA.body), hash(contact.fixtureB.body)
        self._touch(a, b)
        self._touch(b, a)

    def EndContact(self, contact: Box2D.b2Contact) -> None:  # noqa: N802 (Box2D name)
        """Clear the foot contact flag when a lower leg stops touching something.

        :param contact: the ended contact (the bodies of its two fixtures are read)
        """
        for body in (contact.fixtureA.body, contact.fixtureB.body):
            foot = self.feet.get(hash(body))
            if foot is not None:
                foot.ground_contact = False


class EtcMultiWalkerEnv(MultiWalkerEnv):
    """Stock Multiwalker physics with one generator, a fresh world per episode and off-screen drawing.

    ``self.np_random`` drives terrain, clouds and every walker's initial push; a new Box2D
    world per episode makes an episode depend on the seed only, not on earlier episodes. The
    stock ``step``/``observe`` are not used: :class:`MultiwalkerSystem` drives the world.
    Takes the stock constructor's keyword arguments.
    """

    def _seed(self, seed: int | None = None) -> list[int]:
        self.np_random, self.seed_val = seeding.np_random(seed)
        for walker in getattr(self, "walkers", []):
            walker.np_random = self.np_random
        return [self.seed_val]

    def setup(self) -> None:
        """Create a new world with walkers at their start positions (no bodies yet)."""
        self.world = Box2D.b2World()
        self.terrain = None
        self.package_scale = self.n_walkers / 1.75
        self.package_length = stock.PACKAGE_LENGTH / stock.SCALE * self.package_scale
        init_x = stock.TERRAIN_STEP * stock.TERRAIN_STARTPAD / 2
        self.start_x = [init_x + stock.WALKER_SEPERATION * i * stock.TERRAIN_STEP for i in range(self.n_walkers)]
        init_y = stock.TERRAIN_HEIGHT + 2 * stock.LEG_H
        self.walkers = [EtcBipedalWalker(self.world, x, init_y, self.np_random) for x in self.start_x]

    def reset(self) -> None:
        """Build a new episode: world, package, terrain, clouds, walkers (in the stock order)."""
        self.setup()
        self.game_over = False
        self.fallen_walkers = np.zeros(self.n_walkers, dtype=bool)
        self.frames = 0
        self.scroll = 0.0
        self.lidar_render = 0
        self._generate_package()
        self._generate_terrain(self.hardcore)
        self._generate_clouds()
        self.drawlist = [*self.terrain, self.package]
        for walker in self.walkers:
            walker._reset()
            self.drawlist += [*walker.legs, walker.hull]
        # Box2D keeps only a weak reference to the listener.
        self.contact_detector = EtcContactDetector(self)
        self.world.contactListener = self.contact_detector

    def render(self, close: bool = False) -> np.ndarray | None:
        """Stock drawing into an off-screen surface (no window, no display needed).

        :param close: drop the surface (:meth:`close`) instead of drawing, and return None
        :return: the frame, RGB (400, 600, 3) uint8, with ``render_mode="rgb_array"``; else None
        """
        if self.screen is None:
            self.screen = pygame.Surface((stock.VIEWPORT_W, stock.VIEWPORT_H))
        mean_x = sum(walker.hull.position.x for walker in self.walkers) / self.n_walkers
        self.scroll = (
            mean_x
            - stock.VIEWPORT_W / stock.SCALE / 5
            - (self.n_walkers - 1) * stock.WALKER_SEPERATION * stock.TERRAIN_STEP
        )
        return super().render(close)

    def draw_broadcasts(self, broadcast: np.ndarray) -> np.ndarray:
        """Mark every walker's option on the last drawn frame: a disc above a walker that broadcast, a ring otherwise.

        :param broadcast: the step's options (N,), 1 = broadcast
        :return: the marked frame, RGB (400, 600, 3) uint8
        """
        render_scale = stock.SCALE / self.package_scale / 0.75  # the stock drawing's scale
        for walker, sent in zip(self.walkers, broadcast, strict=True):
            x = (walker.hull.position.x - self.scroll) * render_scale
            y = stock.VIEWPORT_H - walker.hull.position.y * render_scale - MARKER_HEIGHT
            if sent:
                pygame.draw.circle(self.screen, BROADCAST_COLOR, (x, y), MARKER_RADIUS)
            else:
                pygame.draw.circle(self.screen, SILENT_COLOR, (x, y), MARKER_RADIUS, width=2)
        return np.transpose(np.array(pygame.surfarray.pixels3d(self.screen)), axes=(1, 0, 2))

    def close(self) -> None:
        """Drop the off-screen surface (pygame itself is left alone)."""
        self.screen = None


class MultiwalkerSystem(CommunicatingSystem):
    """The paper's modified Multiwalker: N walkers carry a package to the right.

    Per agent ``walker_i`` (all arrays agent axis first, float64):

    * local state (17): package relative to the walker (dx, dy divided by the package length,
      package angle), then the stock observation's 14 own values (hull angle,
      ``2 * angular velocity / FPS``, ``0.12 * vx``, ``0.08 * vy``, hip angle, hip speed / 4,
      knee angle + 1, knee speed / 6, ground contact of leg 1, the same for leg 2);
    * message (4): hull x, y divided by the package length, and hull vx, vy both times
      :data:`MESSAGE_VELOCITY_SCALE` (0.12; one factor for both axes);
    * trigger features (3): the package information, ``local[:, :3]``;
    * control (4): hip 1, knee 1, hip 2, knee 2 in [-1, 1] (motor speed sign and torque share).

    Reward of walker i at step k: ``forward_reward * 130 / SCALE * (package_x[k] - package_x[k-1])``
    plus the speed shaping ``phi_i[k] - phi_i[k-1]`` with ``phi_i = -speed_penalty * |0.12 * vx_i|``
    (vx in m/s), plus ``fall_reward`` if it fell. When any walker falls, the package touches the
    ground or leaves the terrain to the left, every walker gets ``terminate_reward`` and the
    episode terminates; it also terminates (no penalty) when the package passes the end of the
    terrain, and is truncated after ``max_cycles`` steps. ``info["package_x"]`` is the package's
    x position (m); ``info["failed"]`` (steps only) tells whether the step ended the episode
    by a fall or a dropped package. The Box2D world lives in :attr:`physics` (:class:`EtcMultiWalkerEnv`).

    :param n_walkers: number of walkers N (2 to 40)
    :param forward_reward: reward scale of package progress (one metre of package travel,
        ``package_x``, is worth about 21.7 with the default 5: :data:`PROGRESS_SCALE` times it)
    :param terminate_reward: reward of every walker when the episode fails
    :param fall_reward: extra reward of a walker that falls
    :param speed_penalty: coefficient c >= 0 of the horizontal-speed potential shaping
    :param max_cycles: episode length limit in steps (truncation)
    :param terrain_length: terrain length in terrain steps (stock default 200)
    :param render_mode: ``"rgb_array"`` or None
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array"],
        "name": "multiwalker_etc_v0",
        "render_fps": stock.FPS,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        n_walkers: int = 3,
        forward_reward: float = 5.0,
        terminate_reward: float = -100.0,
        fall_reward: float = -10.0,
        speed_penalty: float = 5.0,
        max_cycles: int = 400,
        terrain_length: int = stock.TERRAIN_LENGTH,
        render_mode: str | None = None,
    ) -> None:
        if not is_integer(n_walkers) or not 2 <= n_walkers <= MAX_WALKERS:
            raise ValueError(f"n_walkers must be an int between 2 and {MAX_WALKERS}, got {n_walkers!r}.")
        for name, value in (
            ("forward_reward", forward_reward),
            ("terminate_reward", terminate_reward),
            ("fall_reward", fall_reward),
            ("speed_penalty", speed_penalty),
        ):
            if not np.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}.")
        if speed_penalty < 0:
            raise ValueError(f"speed_penalty must be >= 0, got {speed_penalty!r}.")
        if not is_integer(max_cycles, 1):
            raise ValueError(f"max_cycles must be an int >= 1, got {max_cycles!r}.")
        min_terrain = stock.TERRAIN_STARTPAD + stock.TERRAIN_GRASS
        if not is_integer(terrain_length, min_terrain):
            raise ValueError(f"terrain_length must be an int >= {min_terrain} (terrain steps), got {terrain_length!r}.")
        if render_mode not in (None, *self.metadata["render_modes"]):
            modes = self.metadata["render_modes"]
            raise ValueError(f"render_mode must be one of {modes} or None, got {render_mode!r}.")
        super().__init__()
        self.n_walkers = int(n_walkers)
        self.forward_reward = float(forward_reward)
        self.terminate_reward = float(terminate_reward)
        self.fall_reward = float(fall_reward)
        self.speed_penalty = float(speed_penalty)
        self.max_cycles = int(max_cycles)
        self.terrain_length = int(terrain_length)
        self.render_mode = render_mode
        self.physics = EtcMultiWalkerEnv(
            n_walkers=self.n_walkers,
            position_noise=0.0,
            angle_noise=0.0,
            forward_reward=self.forward_reward,
            terminate_reward=self.terminate_reward,
            fall_reward=self.fall_reward,
            shared_reward=False,
            terminate_on_fall=True,
            remove_on_fall=False,
            terrain_length=self.terrain_length,
            max_cycles=self.max_cycles,
            render_mode=render_mode,
        )
        self.possible_agents = [f"walker_{i}" for i in range(self.n_walkers)]
        self.local_space = _unbounded(N_LOCAL)
        self.message_space = _unbounded(4)
        self.trigger_space = _unbounded(3)
        self.control_space = spaces.Box(low=np.float32(-1), high=np.float32(1), shape=(4,), dtype=np.float32)
        self._progress_coef = self.forward_reward * PROGRESS_SCALE
        self._end_x = (self.terrain_length - stock.TERRAIN_GRASS) * stock.TERRAIN_STEP
        self._package_x = 0.0
        self._potential = np.zeros(self.n_walkers)

    @property
    def np_random(self) -> np.random.Generator:
        """The generator of terrain, clouds and initial pushes (re-seeded by ``reset(seed)``)."""
        return self.physics.np_random

    @property
    def package_length(self) -> float:
        """Length of the package (m), the unit of positions in local states and messages."""
        return self.physics.package_length

    def _observe(self) -> tuple[SystemObs, np.ndarray, float]:
        """Read the world: observation, hull vx (m/s) per walker, package x (m)."""
        raw = np.array([walker.raw_state() for walker in self.physics.walkers])  # (N, 16)
        package = self.physics.package
        package_pos = package.position
        package_x = package_pos.x
        inv_length = 1.0 / self.physics.package_length
        local = np.empty((self.n_walkers, N_LOCAL))
        local[:, 0] = (package_x - raw[:, 14]) * inv_length
        local[:, 1] = (package_pos.y - raw[:, 15]) * inv_length
        local[:, 2] = package.angle
        np.multiply(raw[:, :14], _OWN_SCALE, out=local[:, 3:])
        local[:, 3:] += _OWN_OFFSET
        message = np.empty((self.n_walkers, 4))
        np.multiply(raw[:, 14:], inv_length, out=message[:, :2])
        np.multiply(raw[:, 2:4], MESSAGE_VELOCITY_SCALE, out=message[:, 2:])
        return SystemObs(local=local, message=message, trigger=local[:, :3].copy()), raw[:, 2], package_x

    def _speed_potential(self, vx: np.ndarray) -> np.ndarray:
        """Potential of the speed shaping, ``phi_i = -speed_penalty * |0.12 * vx_i|``.

        :param vx: hull x velocities (m/s), shape (N,)
        :return: potentials, shape (N,)
        """
        return -self.speed_penalty * np.abs(SPEED_SHAPING_SCALE * vx)

    def _reset_arrays(self, seed: int | None = None) -> tuple[SystemObs, dict[str, Any]]:
        """Build a new episode in :attr:`physics`, see :meth:`CommunicatingSystem._reset_arrays`.

        :param seed: seed that re-seeds the generator of terrain, clouds and initial pushes, or None to continue it
        :return: the first observation and ``{"package_x": package x position (m)}``
        """
        if seed is not None:
            self.physics._seed(int(seed))
        self.physics.reset()
        obs, vx, package_x = self._observe()
        self._package_x = package_x
        self._potential = self._speed_potential(vx)
        return obs, {"package_x": package_x}

    def _step_arrays(self, control: np.ndarray) -> tuple[SystemObs, np.ndarray, bool, bool, dict[str, Any]]:
        """Set the motors and advance the world by one frame, see :meth:`CommunicatingSystem._step_arrays`.

        :param control: hip 1, knee 1, hip 2, knee 2 commands of every walker, shape (N, 4) (see :func:`motor_commands`)
        :return: observation, rewards (N,), terminated (a failure or the package past the end of the terrain),
            truncated (after ``max_cycles`` frames), info with ``package_x`` (m) and ``failed``
        """
        physics = self.physics
        speeds, torques = motor_commands(control)
        for walker, speed, torque in zip(physics.walkers, speeds, torques, strict=True):
            walker.set_motors(speed, torque)
        physics.world.Step(1.0 / stock.FPS, 6 * 30, 2 * 30)  # the stock solver iterations
        physics.frames += 1

        obs, vx, package_x = self._observe()
        potential = self._speed_potential(vx)
        rewards = self._progress_coef * (package_x - self._package_x) + (potential - self._potential)
        self._package_x = package_x
        self._potential = potential
        fallen = physics.fallen_walkers
        failed = bool(physics.game_over or package_x < 0 or fallen.any())
        if failed:
            rewards += self.fall_reward * fallen + self.terminate_reward
        terminated = failed or package_x > self._end_x
        truncated = not terminated and physics.frames >= self.max_cycles
        return obs, rewards, terminated, truncated, {"package_x": package_x, "failed": failed}

    def render(self, broadcast: np.ndarray | None = None) -> np.ndarray | None:
        """RGB image (400, 600, 3) uint8 of the stock drawing (no LIDAR rays); None without render mode.

        :param broadcast: the step's options (N,) to mark above the walkers (a green disc: broadcast,
            a grey ring: silent); None: no marks
        :return: the frame, RGB (400, 600, 3) uint8, with the marks if ``broadcast`` is given; None without
            render mode
        """
        if self.render_mode is None:
            return None
        frame = self.physics.render()
        if broadcast is None:
            return frame
        return self.physics.draw_broadcasts(np.asarray(broadcast))

    def close(self) -> None:
        """Release the rendering surface."""
        self.physics.close()


def _unbounded(size: int) -> spaces.Box:
    """Unbounded float32 ``Box`` of one agent's vector.

    :param size: length of the vector
    :return: ``Box(-inf, inf, (size,), float32)``
    """
    return spaces.Box(low=-np.inf, high=np.inf, shape=(size,), dtype=np.float32)
