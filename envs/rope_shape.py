"""RopeShape-v0: lay a rope onto a target curve on a table by pick-and-place (SoftGym's
RopeConfiguration)."""

from __future__ import annotations

import numpy as np

from .checks import check_positive
from .pick_place import (
    PICK_PLACE_MODES,
    PP_OBS_MODES,
    DragPlan,
    PickPlaceEnv,
    PickPlaceVectorEnv,
    finish_action,
)
from .rope_straighten import Rope, tangle
from .task import TaskSpec, ppo, sac

__all__ = ["SHAPES", "RopeShape", "RopeShapeController", "RopeShapeEnv", "RopeShapeVectorEnv",
           "curve"]

#: The family of target curves, in the order of their ids.
SHAPES = ("arc", "U", "S", "V", "zigzag")


def curve(shape: int, turns: np.ndarray, n: int, link: float) -> np.ndarray:
    """A curve of ``n`` points ``link`` m apart (a rope laid exactly onto it keeps its rods'
    lengths) of family ``SHAPES[shape]``, from its turning angles at the ``n - 2`` inner points,
    scaled by ``turns[0]`` (the total turn, rad) and ``turns[1]`` (a second parameter in
    [0, 1]); centred on the origin, its ends' chord along x."""
    k = n - 2
    tau = np.zeros(k)
    total, extra = float(turns[0]), float(turns[1])
    name = SHAPES[shape]
    if name == "arc":  # a circular arc: the turn spread evenly
        tau[:] = total / k
    elif name == "U":  # two straight legs and a half circle between them
        width = max(2, int(round((0.3 + 0.3 * extra) * k)))
        lo = (k - width) // 2
        tau[lo:lo + width] = np.pi / width
    elif name == "S":  # two arcs turning opposite ways
        tau[:k // 2] = total / (k // 2)
        tau[k - k // 2:] = -total / (k // 2)
    elif name == "V":  # one corner in the middle
        tau[k // 2] = total
    else:  # zig-zag: three corners turning alternately
        for j, at in enumerate((k // 4, k // 2, 3 * k // 4)):
            tau[at] = total * (1 if j % 2 == 0 else -1) * (0.7 + 0.3 * extra)
    heading = np.concatenate([[0.0], np.cumsum(tau)])
    steps = link * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    x = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    chord = x[-1] - x[0]
    if np.hypot(*chord) > 1e-9 * link:  # the ends' chord along x
        a = -np.arctan2(chord[1], chord[0])
        x = x @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    return x - x.mean(axis=0)


class RopeShape(Rope):
    """The RopeShape physics and task (see :class:`RopeShapeEnv`). Goal data (``target``):
    the target curve's ``num_particles`` points (m), then the shape's id."""

    p_goal = 0.0
    #: The goal's entries: the target curve at the observed particles (the keypoints', or
    #: every particle's).
    goal_per_point = True

    def __init__(self, num_envs: int = 1, *, action_mode: str = "pick_place",
                 num_grippers: int = 1, num_particles: int = 20, link: float = 0.025,
                 particle_mass: float = 0.01, bend_k: float = 1e-4, mu: float = 0.5,
                 view_half: float = 0.6, tolerance: float = 0.02, turn: float = 0.3,
                 dt: float = 0.002, integrator: str = "rattle", speed: float = 1.0,
                 grab_radius: float = 0.05, mouse_ks: float = 50.0, mouse_kd: float = 1.0,
                 hold_time: float = 0.1, settle_time: float = 1.0, rest_speed: float = 0.01,
                 chunk: int = 5, residual_limit: float = 0.01,
                 max_move: float = 0.05) -> None:
        self.tolerance = check_positive("tolerance", tolerance)
        self.turn = check_positive("turn", turn, maximum=10.0)
        n = check_positive("num_particles", num_particles, integer=True, minimum=8,
                           maximum=200)
        self.target_size = 2 * n + 1
        super().__init__(num_envs, num_particles=num_particles, link=link,
                         particle_mass=particle_mass, bend_k=bend_k, mu=mu,
                         view_half=view_half, action_mode=action_mode,
                         num_grippers=num_grippers, dt=dt, integrator=integrator, speed=speed,
                         grab_radius=grab_radius, mouse_ks=mouse_ks, mouse_kd=mouse_kd,
                         hold_time=hold_time, settle_time=settle_time, rest_speed=rest_speed,
                         chunk=chunk, residual_limit=residual_limit, max_move=max_move)

    def sample_episode(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The rope: a gentle random walk (heading turning by N(0, ``turn``^2) rad per link)
        at a random rotation, centred within 0.1 ``view_half`` of the origin; the target: a
        shape of :data:`SHAPES` (uniform), its total turn ~ U(pi/2, pi) (arc, S: U(pi/3,
        2pi/3) per arc, V: a corner of U(pi/3, 2pi/3), zig-zag: U(pi/3, pi/2) per corner), at
        a random rotation, centred within 0.1 ``view_half`` of the origin."""
        n, h = self.num_particles, self.view_half
        x = tangle(rng, n, self.link, self.turn) + rng.uniform(-0.1, 0.1, 2) * h
        shape = int(rng.integers(len(SHAPES)))
        low, high = {"arc": (np.pi / 2, np.pi), "U": (np.pi, np.pi),
                     "S": (np.pi / 3, 2 * np.pi / 3), "V": (np.pi / 3, 2 * np.pi / 3),
                     "zigzag": (np.pi / 3, np.pi / 2)}[SHAPES[shape]]
        turns = np.array([rng.uniform(low, high), rng.uniform()])
        c = curve(shape, turns, n, self.link)
        a = rng.uniform(-np.pi, np.pi)
        c = c @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
        c = c + rng.uniform(-0.1, 0.1, 2) * h
        return x, np.concatenate([c.ravel(), [shape]])

    def curves(self, target: np.ndarray) -> np.ndarray:
        """The target curves' points (k, n, 2) m of goal data (k, target_size)."""
        return target[:, :2 * self.n].reshape(len(target), self.n, 2)

    def shape_distance(self, x: np.ndarray, target: np.ndarray) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """The mean distance (m) between the rope's particles and their target points, in
        the better of the two orders along the rope, per copy; and whether that order is the
        reversed one."""
        c = self.curves(target)
        forward = np.linalg.norm(x - c, axis=2).mean(axis=1)
        backward = np.linalg.norm(x - c[:, ::-1], axis=2).mean(axis=1)
        return np.minimum(forward, backward), backward < forward

    def observed_order(self, x: np.ndarray) -> np.ndarray:
        """The rope listed in the order along it that the shape distance takes (reversed in
        the copies where the reversed order lies nearer the target curve), so that observed
        rope point ``i`` belongs on the observation's target point ``i``. The task cannot tell
        the rope's ends apart, so an agent should not have to: with the particles' own order,
        a rope point's target is one end of the curve or the other from one episode to the
        next."""
        flip = self.shape_distance(x, self.target)[1]
        return np.where(flip[:, None, None], x[:, ::-1], x)

    def progress(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Minus the shape distance (m): 0 on the curve."""
        return -self.shape_distance(x, target)[0]

    def success(self, x: np.ndarray, target: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The shape distance within ``tolerance``."""
        return -p <= self.tolerance

    def distance(self, p: np.ndarray) -> np.ndarray:
        """The shape distance (m): ``-p``."""
        return np.maximum(-p, 0.0)

    def goal_features(self, envs: np.ndarray) -> np.ndarray:
        """The target curve's points at the observed particles, normalised."""
        c = self.curves(self.target[envs])
        if self.obs_mode == "state":
            c = c[:, self.keypoints]
        return self.to_normalized(c).reshape(len(envs), -1)

    def target_segments(self) -> np.ndarray:
        """The target curves, as segments between consecutive points (num_envs, n - 1, 2, 2)."""
        c = self.curves(self.target)
        return np.stack([c[:, :-1], c[:, 1:]], axis=2)


class RopeShapeEnv(PickPlaceEnv):
    """
    ## Description

    SoftGym's RopeConfiguration on a table seen from above: lay a rope (20 particles joined by
    rods 2.5 cm long, weak angular springs, Coulomb friction on the table: RopeStraighten's)
    onto a target curve drawn per episode from a family of shapes (arc, U, S, V, zig-zag) at a
    random pose, by pick-and-place. Success: the mean distance between the rope's particles
    and their target points (in either direction along the rope, the better one) is at most
    2 cm. Each target is exactly as long as the rope.

    ## Action Space

    ``Box(-1, 1, (4 * num_grippers,), float32)``: per gripper the pick point and the place
    point in normalised view coordinates (``[-0.6, 0.6]^2`` m onto ``[-1, 1]^2``).

    ``action_mode="drag"`` (SoftGym's low-level mode): 3 numbers per gripper instead, a move
    of up to ``max_move`` (5 cm) along x and y and a grip flag (``> 0``: hold, or take the
    particle within ``grab_radius`` of the gripper; ``<= 0``: let go); each step lasts
    ``max_move / speed`` and the observation ends with the grippers' positions and holding
    flags (3 per gripper). See :mod:`envs.pick_place`.

    ## Observation Space

    ``obs_mode="state"``: ``Box(-10, 10, (40,), float32)``: the normalised positions of 10
    evenly spaced rope particles (0, 2, 4, 6, 8, 11, 13, 15, 17, 19), then the target curve's
    points for the same particles. ``obs_mode="particles"``: every particle, then the target
    point of every particle (80 floats). The rope is listed in the order along it that lies
    nearer the curve (the order the success test takes), so observed rope point ``i`` belongs
    on target point ``i``.

    ## Rewards

    ``r = 10 (Phi - Phi') - 0.1 + 10 success`` (``envs.rewards``), ``Phi`` the shape distance
    (m).

    ## Starting State

    The rope as a gentle random walk (heading turning by N(0, 0.3^2) rad per link) at a random
    rotation, the target a shape of the family (uniform) with random parameters at a random
    rotation, each centred within 6 cm of the origin; at rest.

    ## Episode End

    Termination on success or divergence; truncation after 40 steps. ``info`` holds
    ``progress`` (``-Phi``), ``normalized_performance`` (``1 - Phi / Phi_0``), ``settled``,
    ``distance`` (``Phi``), ``kinetic_energy``, ``constraint_residual``, ``is_success`` and
    ``diverged``.

    ## Arguments

    RopeStraighten's (``num_grippers``, ``num_particles``, ``link``, ``particle_mass``,
    ``bend_k``, ``mu``, ``view_half``, ``turn``, ``dt``, ``integrator``, ``speed``,
    ``grab_radius``, ``mouse_ks``, ``mouse_kd``, ``hold_time``, ``settle_time``,
    ``rest_speed``, ``chunk``, ``residual_limit``, ``max_move``) and ``tolerance`` (m);
    ``obs_mode``.

    ## Version History

    * v0: Initial version.
    """

    task_class = RopeShape


class RopeShapeVectorEnv(PickPlaceVectorEnv):
    """``num_envs`` RopeShape copies stepped as one particle system (see
    :class:`RopeShapeEnv`)."""

    task_class = RopeShape


class RopeShapeController:
    """The oracle: in the better order along the rope, pick the observed rope point furthest
    from its target point and place it there."""

    def __init__(self, task: RopeShape) -> None:
        self.task = task
        self.plan = DragPlan()  # (drag mode)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        t = self.task
        x = t.observed_points(obs)
        B, k = x.shape[0], x.shape[1]
        goal = t.to_world(t.goal_part(obs).reshape(B, k, 2))
        forward = np.linalg.norm(x - goal, axis=2)
        backward = np.linalg.norm(x - goal[:, ::-1], axis=2)
        flip = backward.mean(axis=1) < forward.mean(axis=1)
        goal = np.where(flip[:, None, None], goal[:, ::-1], goal)
        err = np.where(flip[:, None], backward, forward)
        rows = np.arange(B)
        j = np.argmax(err, axis=1)
        a = np.concatenate([t.to_normalized(x[rows, j]), t.to_normalized(goal[rows, j])],
                           axis=1)
        if t.num_grippers == 2:
            err2 = err.copy()
            err2[rows, j] = -1.0
            j2 = np.argmax(err2, axis=1)
            a = np.concatenate([a, t.to_normalized(x[rows, j2]), t.to_normalized(goal[rows, j2])],
                               axis=1)
        return finish_action(t, obs, a, self.plan)


#: The task's declaration (see :mod:`envs.task`).
TASK = TaskSpec(
    id="RopeShape-v0", env=RopeShapeEnv, vector_env=RopeShapeVectorEnv,
    action_modes=PICK_PLACE_MODES, scripted_agent=RopeShapeController,
    summary="lay a rope onto a target curve (arc, U, S, V, zig-zag) at a random pose by "
            "pick-and-place",
    hyperparams={"ppo": {"pick_place": ppo(300000, (128, 128), -2.5, points=10, n_steps=64,
                                           batch_size=256, gamma=0.5),
                         "drag": ppo(50000, (128, 128), -5.0, points=10, n_steps=64,
                                     batch_size=256, gamma=0.9, learning_rate=3e-5, imitate=40000,
                                     imitate_noise=0.003, imitate_updates=10000,
                                     max_episode_steps=100)},
                 "sac": {"pick_place": sac(100000, (256, 256), learning_starts=1000)}},
    notes="The shipped PPO settings (tuning seed 101): the pointer policy (envs.policies."
          "PointerPolicy, points 10: each gripper takes one observed rope point, chosen by a "
          "softmax over one shared score of each point, its target and their difference, and "
          "places it around that point's target; value function (128, 128); log_std_init -2.5; "
          "observations not normalised), gamma 0.5, 16 copies x 64 steps, batches of 256, 10 "
          "epochs, learning rate 3e-4, 300k steps. Seed 101 (a script outside the package, the "
          "same policy with the score network's default initialisation; periodic evaluations of "
          "30 episodes from seed 1,000,000): 0% at 50k, 60% at 100k, 97% at 150k and 200k, 100% "
          "at 250k (stopped). With the rope observed in the particles' own order, and before the "
          "pointer: PPO with gamma 0.9, learning rate 1e-3, 20 epochs, (128, 128), log_std_init "
          "-2.5 for 150k steps on tuning seed 100: 0% deterministic and stochastic (100 episodes "
          "from seed 5,000,000), return -4.00 / -3.96, normalized performance -0.01 / 0.01 (the "
          "policy leaves the rope alone; doing nothing returns -4.0). With the rope in the order "
          "that matches its target, an MLP policy ((128, 128), log_std_init -2 under a ceiling "
          "falling to -4.5, gamma 0.5, learning rate 1e-3, 20 epochs; seed 101): 0% to 250k, "
          "returns -3.85 to -3.92 (stopped); taking the same rope point every step returns -3.6 "
          "(normalized performance 0.26-0.30, 30 episodes), the keypoint oracle 10.6. A pointer "
          "whose mean is the softmax-weighted point and target, with Gaussian noise around it "
          "(scores from the whole observation, or one shared score per point; seed 101): 0-3% to "
          "250k (the noise shrinks to 0.005 and no other point is tried). The scripted agent "
          "with Gaussian noise of 0.05 on its actions succeeds in 14% "
          "(benchmarks/tabletop_noise.py). SAC (the project's settings, 1,000 random steps "
          "first) is untuned; with gamma 0.9 (RopeStraighten's SAC settings) on tuning seed 101, "
          "periodic evaluations of 20 deterministic episodes from seed 1,000,000: 0% to 50k "
          "steps, returns -4.00 to -4.40 (stopped at 50k). Drag mode: episodes of 100 steps "
          "(max_episode_steps, part of the mode's settings: one pick-and-place takes about ten "
          "drag steps, and at the registered 40 the scripted agent succeeds in 29%, at 100 in "
          "98%); the pointer policy in drag mode (each gripper takes one observed rope point, "
          "scored from the point, its target, their difference in action units, its offset "
          "from the gripper and the holding flag, and moves as the scripted agent's rule does "
          "for that point: to it, grip, to its target, let go), log_std_init -5 (0.3 mm of "
          "noise on a move: the rule lets go within 1 mm of the target, so a noisier gripper "
          "never does), started from a clone of the scripted agent (imitate 40,000 steps with "
          "noise 0.003, 10,000 updates of the scores by cross-entropy of the point the agent "
          "works on), gamma 0.9, 16 x 64, batches of 256, learning rate 3e-5, 50k steps. Seed "
          "101, 100 episodes from seed 5,000,000: 98% deterministic and stochastic (learning "
          "rate 3e-4: 96% / 95%). The clone alone (a script outside the package, 50 episodes "
          "from 2,000,000): 96% / 96%; with log_std_init -2.5 96% / 16% (4 mm of noise: the "
          "gripper never comes within 1 mm of the target and so never lets go); with 2,000 "
          "updates of the likelihood of the agent's moves instead of its choice (and the "
          "offsets in view units), 88% deterministic, and PPO with learning rate 1e-4 took "
          "that to 47-73% within 100k steps. An MLP (ClothFold's drag settings) with 100-step "
          "episodes: 0% at 60k steps (return -9.9; doing nothing returns -10).",
    variants=({"num_grippers": 2},), max_episode_steps=40, obs_modes=PP_OBS_MODES)
