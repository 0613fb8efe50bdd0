"""QP differential inverse kinematics to keypoints, frame after frame (mink on the MuJoCo model).

Each frame's keypoints (sole placements, torso orientation and height or position, CoM xy, hands
relative to the torso) are weighted tasks of one QP per iteration,

    min_v  sum_i w_i || J_i v + e_i ||^2 + damping ||v||^2   s.t.  q_lo <= q + v <= q_hi,

solved with daqp through qpsolvers (mink's `solve_ik`, `ConfigurationLimit` keeping every joint in
its MJCF range). Iterations repeat until the soles are within `tolerance` of their targets or
`max_iter` is reached; each frame starts from the previous one. The feet weigh most: where the
keypoints conflict (a torso height the legs cannot reach), the feet are met and the torso gives.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mink
import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot

FEET = ("left_foot", "right_foot")
HANDS = ("left_hand", "right_hand")


@dataclass(frozen=True)
class IKWeights:
    foot_position: float = 100.0
    foot_orientation: float = 20.0
    base_orientation: float = 5.0
    base_position: float = 2.0  # per axis where a base position is given (height only for walks)
    com: float = 2.0  # CoM xy, where given
    hands: float = 0.5  # hand positions relative to the torso, where given
    posture: float = 0.02  # every joint toward the stand pose
    arm_posture: float = 0.5  # arm joints toward the stand pose (the walk's hand posture)


@dataclass(frozen=True)
class IKSettings:
    weights: IKWeights = field(default_factory=IKWeights)
    tolerance: float = 2e-4  # m: a frame is done when both soles are this close to their targets
    max_iter: int = 30  # QP iterations per frame (the first frame gets 10 times as many)
    damping: float = 1e-3  # Levenberg-Marquardt damping of every task
    solver: str = "daqp"

    def check(self) -> None:
        if not (0 < self.tolerance < 0.01 and self.max_iter >= 1 and self.damping >= 0):
            raise ConfigError("ik: tolerance must be in (0, 0.01) m, max_iter >= 1 and damping >= 0")
        if any(v < 0 for v in vars(self.weights).values()):
            raise ConfigError("ik weights must be >= 0")


@dataclass
class FrameTargets:
    """One frame's keypoints, world frame. None: that keypoint is not constrained."""

    feet: dict[str, tuple[np.ndarray, np.ndarray]]  # foot -> (sole position (3,), rotation (3, 3))
    base_rotation: np.ndarray  # (3, 3) of the base site
    base_position: np.ndarray  # (3,) of the base site; axes with zero weight are ignored
    base_axes: tuple[float, float, float] = (0.0, 0.0, 1.0)  # which base position axes count
    com_xy: np.ndarray | None = None
    hands_in_base: dict[str, np.ndarray] | None = None  # hand -> position in the base site's frame


@dataclass
class IKResult:
    qpos: np.ndarray  # (T, nq)
    foot_error: np.ndarray  # (T,) largest sole position error, m
    iterations: np.ndarray  # (T,)


class KeypointIK:
    """Inverse kinematics of one robot to a sequence of `FrameTargets`."""

    def __init__(self, robot: Robot, settings: IKSettings = IKSettings()):
        settings.check()
        self.robot, self.settings = robot, settings
        w = settings.weights
        model = robot.mj_model
        self.config = mink.Configuration(model, robot.stand_qpos.copy())
        ee = robot.config.end_effectors
        self.base_site = robot.config.imu_site
        lm = settings.damping
        self.feet = {f: mink.FrameTask(ee[f], "site", w.foot_position, w.foot_orientation, lm_damping=lm) for f in FEET}
        self.base = mink.FrameTask(self.base_site, "site", 0.0, w.base_orientation, lm_damping=lm)
        self.com = mink.ComTask(cost=np.zeros(3), lm_damping=lm)
        self.hands = {h: mink.FrameTask(ee[h], "site", 0.0, 0.0, lm_damping=lm) for h in HANDS if h in ee}
        posture_cost = np.full(model.nv, w.posture)
        posture_cost[:6] = 0.0
        arms = [i for g in ("left_arm", "right_arm") if g in robot.config.joint_groups
                for i in robot.config.group_indices(g)]
        posture_cost[6 + np.asarray(arms, dtype=int)] = max(w.posture, w.arm_posture)
        self.posture = mink.PostureTask(model, cost=posture_cost, lm_damping=lm)
        self.posture.set_target(robot.stand_qpos.copy())
        self.limits = [mink.ConfigurationLimit(model)]
        self._sites = {f: robot.site_id(ee[f]) for f in FEET}

    def _set(self, t: FrameTargets) -> list:
        w = self.settings.weights
        tasks = [self.posture]
        for foot, (pos, rot) in t.feet.items():
            self.feet[foot].set_target(_se3(rot, pos))
            tasks.append(self.feet[foot])
        self.base.set_position_cost(w.base_position * np.asarray(t.base_axes, dtype=float))
        self.base.set_target(_se3(t.base_rotation, t.base_position))
        tasks.append(self.base)
        if t.com_xy is not None and w.com > 0:
            self.com.set_cost(np.array([w.com, w.com, 0.0]))
            self.com.set_target(np.array([*t.com_xy, 0.0]))
            tasks.append(self.com)
        return tasks

    def _hand_tasks(self, t: FrameTargets) -> list:
        """Hand targets follow the torso: re-expressed in the world at every iteration."""
        if not t.hands_in_base:
            return []
        base = self.config.get_transform_frame_to_world(self.base_site, "site")
        out = []
        for hand, rel in t.hands_in_base.items():
            task = self.hands[hand]
            task.set_position_cost(self.settings.weights.hands)
            task.set_target(mink.SE3.from_translation(base.apply(np.asarray(rel, dtype=float))))
            out.append(task)
        return out

    def foot_error(self, t: FrameTargets) -> float:
        d = self.config.data
        return max((float(np.linalg.norm(d.site_xpos[self._sites[f]] - pos)) for f, (pos, _) in t.feet.items()),
                   default=0.0)

    def solve(self, targets: list[FrameTargets], q_start: np.ndarray | None = None) -> IKResult:
        s = self.settings
        self.config.update(np.array(self.robot.stand_qpos if q_start is None else q_start, dtype=float))
        n = len(targets)
        qpos = np.empty((n, self.robot.nq))
        err, iters = np.empty(n), np.zeros(n, dtype=int)
        for k, t in enumerate(targets):
            tasks = self._set(t)
            budget = s.max_iter * (10 if k == 0 else 1)
            e = self.foot_error(t)
            for it in range(budget):
                if e < s.tolerance and it >= 1:
                    break
                v = mink.solve_ik(self.config, tasks + self._hand_tasks(t), 1.0, s.solver, damping=s.damping,
                                  safety_break=False, limits=self.limits)
                self.config.integrate_inplace(v, 1.0)
                iters[k] += 1
                e = self.foot_error(t)
            qpos[k], err[k] = self.config.q, e
        return IKResult(qpos, err, iters)


def _se3(rot: np.ndarray, pos: np.ndarray) -> mink.SE3:
    return mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(np.asarray(rot, dtype=float)),
                                                  np.asarray(pos, dtype=float))
