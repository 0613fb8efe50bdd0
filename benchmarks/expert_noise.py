"""How far does the optimizer's feedback expert get when it reads what the actor reads? (issue 13)

A policy distilled from the expert can at best act like the expert fed the actor's inputs. This
measures that "perfect student": the expert (`EnvExpert`, the DDP law with the world's own gains)
reading the actor's latest observation (`ExpertConfig(reads="observations")`: joint positions and
velocities, base velocities and tilt, with the environment's Table II observation noise times a
factor) tracks held-out walks from frame 0, in the nominal world or under Table II's full
randomization (rough ground included), with every servo Kp times a stiffness factor (the expert's
target follows the read joint position at a gain of 1 - K_q / Kp, so a softer servo passes less of
the reading's error into torque). `--channels` puts the noise on chosen readings only.

Printed as a Markdown table and written as JSON: success (tracked to the end), frames tracked.

    .venv/bin/python benchmarks/expert_noise.py --dataset data/walk_test [--n 8] [--servo reference,state] [--stiffness 1,0.4] \\
        [--noise 0,0.25,0.5,1] [--worlds nominal,table2] [--channels all|joint_pos,base_lin_vel,...]
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
from opt2skill.envs.config import NoiseConfig, nominal_ranges
from opt2skill.envs.evaluation import track
from opt2skill.eval.evaluate import eval_config
from opt2skill.expert.acting import EnvExpert, ExpertConfig
from opt2skill.model import load_robot

CHANNELS = tuple(f.name for f in dataclasses.fields(NoiseConfig))


class Filtered:
    """The expert acting on filtered readings: a complementary filter per channel, as a robot's state
    estimator would run. Joint positions integrate the read joint velocities and are pulled toward the
    read positions by `gain` per step; the tilt (projected gravity) is carried by the read angular
    rate and pulled toward the read gravity; base linear velocity is low-passed with the same gain.
    The angular rate and joint velocities are used as read (the expert survives their noise)."""

    def __init__(self, expert: EnvExpert, gain: float):
        self.expert, self.gain, self.estimate = expert, gain, None

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        env, k = self.expert.env, self.gain
        read, dt = env.readings, env.sim.policy_dt
        if self.estimate is None:
            self.estimate = dataclasses.replace(read, joint_pos=read.joint_pos.copy(), base_lin_vel=read.base_lin_vel.copy(),
                                                gravity=read.gravity.copy())
        else:
            e = self.estimate
            e.joint_pos = (1 - k) * (e.joint_pos + dt * read.joint_vel) + k * read.joint_pos
            e.base_lin_vel = (1 - k) * e.base_lin_vel + k * read.base_lin_vel
            g = e.gravity - dt * np.cross(read.base_ang_vel, e.gravity)  # a world vector seen from a turning body
            e.gravity = (1 - k) * g + k * read.gravity
            e.joint_vel, e.base_ang_vel = read.joint_vel, read.base_ang_vel
        env.readings = self.estimate
        try:
            return self.expert.act()[0]
        finally:
            env.readings = read


def measure(robot, references, task: str, stiffness: float, table2: bool, noise: float, channels: tuple[str, ...],
            seed: int, threads: int, filter_gain: float = 1.0, servo: str = "reference") -> dict:
    config = eval_config(tracking_config(task), randomize=True, noise=True)
    full = config.observations.noise
    kept = NoiseConfig(**{c: getattr(full, c) if c in channels else 0.0 for c in CHANNELS})
    r = config.randomization
    ranges = r.ranges() if table2 else nominal_ranges(r)
    ranges["kp_factor"] = tuple(stiffness * x for x in ranges["kp_factor"])
    config = dataclasses.replace(config, randomization=dataclasses.replace(r, **ranges),
                                 observations=dataclasses.replace(config.observations, noise=kept))
    n = len(references)
    bank = ReferenceBank.from_trajectories(robot, references, config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, n, seed=seed, threads=threads) as env:
        env.set_progress(1.0)
        env.noise_factor = noise
        expert = EnvExpert(env, references, ExpertConfig(reads="observations", servo=servo))
        motions = track(env, expert if filter_gain >= 1 else Filtered(expert, filter_gain), np.arange(n))
    frames = sum(m.steps for m in motions) / sum(m.reference_frames - 1 for m in motions)
    return {"servo": servo, "stiffness": stiffness, "table2": table2, "noise": noise, "channels": list(channels), "filter": filter_gain,
            "success": float(np.mean([not m.fell for m in motions])), "frames_tracked": float(frames)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, help="walks generated with --keep-gains")
    parser.add_argument("--n", type=int, default=8)
    parser.add_argument("--stiffness", default="1", help="factors on every servo Kp, comma-separated")
    parser.add_argument("--noise", default="0,0.25,0.5,1", help="factors on Table II's observation noise")
    parser.add_argument("--worlds", default="nominal,table2", help="nominal and/or table2")
    parser.add_argument("--channels", default="all", help=f"noisy readings: all, or some of {', '.join(CHANNELS)}; "
                        "'each' runs every channel alone")
    parser.add_argument("--filter", default="1", help="complementary-filter gains per step, comma-separated (1: none)")
    parser.add_argument("--servo", default="reference", help="the expert's servo forms, comma-separated: "
                        "reference and/or state (ExpertConfig.servo)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("bench/expert_noise.json"))
    args = parser.parse_args()
    if args.dataset is None:  # `make bench` runs every benchmark without arguments
        print("expert_noise: skipped, needs --dataset (walks generated with --keep-gains)")
        return
    dataset = Dataset.open(args.dataset)
    robot = load_robot(dataset.identity.get("robot", "digit"))
    references = [dataset[i] for i in range(min(args.n, len(dataset)))]
    task = dataset.identity.get("task", "")
    channel_sets = ([(c,) for c in CHANNELS] if args.channels == "each" else
                    [CHANNELS if args.channels == "all" else tuple(args.channels.split(","))])
    rows = []
    print(f"{machine()}; {len(references)} walks of {args.dataset}")
    print("| servo | Kp factor | world | noisy readings | filter gain | noise factor | success | frames tracked | s |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for servo, s in [(v, float(x)) for v in args.servo.split(",") for x in args.stiffness.split(",")]:
        for world in args.worlds.split(","):
            for channels, gain in [(c, float(g)) for c in channel_sets for g in args.filter.split(",")]:
                for f in [float(x) for x in args.noise.split(",")]:
                    start = time.perf_counter()
                    row = measure(robot, references, task, s, world == "table2", f, channels, args.seed, args.threads, gain, servo)
                    rows.append(row)
                    named = "all" if channels == CHANNELS else ", ".join(channels)
                    print(f"| {servo} | {s:g} | {'Table II' if world == 'table2' else 'nominal'} | {named} | {gain:g} | {f:g} | "
                          f"{row['success']:.0%} | {row['frames_tracked']:.0%} | {time.perf_counter() - start:.0f} |",
                          flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "dataset": str(args.dataset), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
