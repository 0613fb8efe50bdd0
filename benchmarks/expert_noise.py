"""How robust is the optimizer's feedback expert, read through noisy sensors, and how does the servos'
stiffness change that? (issue 13's diagnosis: the expert's PD target follows the *measured* joint
position at gain 1 - K_q / Kp, so a stiff servo passes (Kp - K_q) sigma of torque noise.)

For each servo-stiffness factor s (every Kp times s; Kd unchanged) and each condition, the expert
(`EnvExpert`, the DDP law with the world's own gains) tracks held-out walks from frame 0, reading
its state through Table II's observation noise times a factor (joint positions and velocities, base
linear and angular velocity, and the base tilt for the projected gravity). Conditions: the nominal
world, and Table II's full randomization (rough ground included) with its Kp range scaled by s.
Printed and written as JSON: success (tracked to the end) and the share of frames tracked.

    .venv/bin/python benchmarks/expert_noise.py --dataset data/walk_test [--n 10] [--stiffness 1,0.5,0.3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from sim_ceiling import machine

from opt2skill.data.reader import Dataset
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.envs.config import nominal_ranges
from opt2skill.envs.evaluation import track
from opt2skill.eval.evaluate import eval_config
from opt2skill.expert.acting import EnvExpert
from opt2skill.geometry import quat_mul
from opt2skill.model import load_robot


class NoisyReadings:
    """The expert acting on a noisy copy of each world's state (Table II's sigmas times `factor`)."""

    def __init__(self, expert: EnvExpert, factor: float, seed: int):
        self.expert, self.factor, self.rng = expert, factor, np.random.default_rng(seed)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        env = self.expert.env
        if self.factor == 0:
            return self.expert.act()[0]
        true = env.state
        noise, f, n, nu = env.config.observations.noise, self.factor, env.num_envs, env.nu
        seen = dataclasses.replace(true, qpos=true.qpos.copy(), qvel=true.qvel.copy())
        dq = f * noise.joint_pos * self.rng.standard_normal((n, nu))
        dqd = f * noise.joint_vel * self.rng.standard_normal((n, nu))
        seen.qpos[:, 7:] += dq
        seen.qvel[:, 6:] += dqd
        seen.joint_pos = true.joint_pos + dq
        seen.joint_vel = true.joint_vel + dqd
        seen.qvel[:, 0:3] += f * noise.base_lin_vel * self.rng.standard_normal((n, 3))
        seen.qvel[:, 3:6] += f * noise.base_ang_vel * self.rng.standard_normal((n, 3))
        tilt = f * noise.gravity * self.rng.standard_normal((n, 2))  # a projected-gravity error is a tilt
        half = 0.5 * np.linalg.norm(tilt, axis=1, keepdims=True)
        axis = np.concatenate([tilt, np.zeros((n, 1))], 1) / np.maximum(2 * half, 1e-12)
        seen.qpos[:, 3:7] = quat_mul(true.qpos[:, 3:7], np.concatenate([np.cos(half), np.sin(half) * axis], 1))
        env.state = seen
        try:
            return self.expert.act()[0]
        finally:
            env.state = true


def measure(robot, references, task: str, stiffness: float, randomize: bool, noise: float, seed: int,
            threads: int) -> dict:
    config = eval_config(tracking_config(task), randomize=True)
    r = config.randomization
    ranges = r.ranges() if randomize else nominal_ranges(r)
    kp = tuple(stiffness * x for x in ranges["kp_factor"])
    config = dataclasses.replace(config, randomization=dataclasses.replace(r, **{**ranges, "kp_factor": kp}))
    n = len(references)
    bank = ReferenceBank.from_trajectories(robot, references, config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, n, seed=seed, threads=threads) as env:
        env.set_progress(1.0)
        policy = NoisyReadings(EnvExpert(env, references), noise, seed)
        motions = track(env, policy, np.arange(n))
    frames = sum(m.steps for m in motions) / sum(m.reference_frames - 1 for m in motions)
    return {"stiffness": stiffness, "table2": randomize, "noise": noise,
            "success": float(np.mean([not m.fell for m in motions])), "frames_tracked": float(frames)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True, help="walks generated with --keep-gains")
    parser.add_argument("--n", type=int, default=10)
    parser.add_argument("--stiffness", default="1,0.5,0.3,0.2", help="factors on every servo Kp")
    parser.add_argument("--noise", default="0,0.5,1", help="factors on Table II's observation noise")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("bench/expert_noise.json"))
    args = parser.parse_args()
    dataset = Dataset.open(args.dataset)
    robot = load_robot(dataset.identity.get("robot", "digit"))
    references = [dataset[i] for i in range(min(args.n, len(dataset)))]
    task = dataset.identity.get("task", "")
    rows = []
    print(f"{machine()}; {len(references)} walks of {args.dataset}")
    print("| Kp factor | world | noise factor | success | frames tracked | s |\n| --- | --- | --- | --- | --- | --- |")
    for s in [float(x) for x in args.stiffness.split(",")]:
        for randomize in (False, True):
            for f in [float(x) for x in args.noise.split(",")]:
                start = time.perf_counter()
                row = measure(robot, references, task, s, randomize, f, args.seed, args.threads)
                rows.append(row)
                print(f"| {s:g} | {'Table II' if randomize else 'nominal'} | {f:g} | {row['success']:.0%} | "
                      f"{row['frames_tracked']:.0%} | {time.perf_counter() - start:.0f} |", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "dataset": str(args.dataset), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
