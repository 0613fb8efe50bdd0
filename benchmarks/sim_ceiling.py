"""The raw physics ceiling: mj_step throughput of the Digit model standing under PD, on this machine.

Two figures: a plain single-threaded MjData loop, and `mujoco.rollout` on all cores with many
worlds and long rollouts (the most C MuJoCo gives: no Python between physics steps), of the model
`load_robot` builds (the one `sim` runs on flat ground). They run in alternating 0.1 s blocks, so a
busy machine slows them alike.

    .venv/bin/python benchmarks/sim_ceiling.py [--seconds 4]
"""

from __future__ import annotations

import argparse
import copy
import datetime
import os
import platform
import time

import mujoco
import numpy as np
from mujoco import rollout

from opt2skill.model import load_robot
from opt2skill.model.standing import feedforward_ctrl
from opt2skill.model.statics import gravity_compensation

FULLPHYSICS, CTRL = mujoco.mjtState.mjSTATE_FULLPHYSICS.value, mujoco.mjtState.mjSTATE_CTRL.value


def standing_targets(robot) -> np.ndarray:
    """PD targets holding the stand pose: gravity compensation through the servo targets."""
    return feedforward_ctrl(robot, robot.stand_qpos, gravity_compensation(robot, robot.stand_qpos).torque)


def robot_model():
    robot = load_robot("digit")
    return robot, copy.deepcopy(robot.mj_model)


class SingleThread:
    """One standing robot stepped by `mj_step` in a Python loop (restarted every 5 s, see RawRollout)."""

    def __init__(self):
        robot, self.model = robot_model()
        self.data = mujoco.MjData(self.model)
        self.stand = robot.stand_qpos
        self.data.qpos[:], self.data.ctrl[:] = self.stand, standing_targets(robot)

    def run(self, seconds: float) -> tuple[int, float]:
        d, steps, start = self.data, 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            for _ in range(500):
                mujoco.mj_step(self.model, d)
            steps += 500
            if d.time > 5.0:
                d.time, d.qpos[:], d.qvel[:] = 0.0, self.stand, 0.0
        return steps, time.perf_counter() - start

    def close(self) -> None:
        pass


class RawRollout:
    """`nworld` standing robots rolled out `nstep` physics steps per call on all cores, each call
    continuing from the last one's states. `run` times whole calls.

    The PD stand is not asymptotically stable sideways: a robot left standing drifts and tips over
    after about 18 s. The robots restart from the stand state every 5 s of simulated time."""

    def __init__(self, nworld: int = 32, nstep: int = 100, nthread: int | None = None):
        robot, model = robot_model()
        nthread = nthread or os.cpu_count() or 1
        self.models = [copy.deepcopy(model) for _ in range(nworld)]
        self.datas = [mujoco.MjData(model) for _ in range(nthread)]
        self.pool = rollout.Rollout(nthread=nthread)
        d = mujoco.MjData(model)
        d.qpos[:] = robot.stand_qpos
        self.state0 = np.zeros((nworld, mujoco.mj_stateSize(model, FULLPHYSICS)))
        mujoco.mj_getState(model, d, self.state0[0], FULLPHYSICS)
        self.state0[:] = self.state0[0]
        self.initial = self.state0.copy()
        self.control = np.ascontiguousarray(np.broadcast_to(standing_targets(robot), (nworld, nstep, model.nu)))
        self.state = np.zeros((nworld, nstep, self.state0.shape[1]))
        self.sensordata = np.zeros((nworld, nstep, model.nsensordata))
        self.nstep = nstep

    def run(self, seconds: float) -> tuple[int, float]:
        """(physics steps, elapsed seconds) of whole calls made until `seconds` have passed."""
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            self.pool.rollout(self.models, self.datas, self.state0, self.control, control_spec=CTRL, skip_checks=True,
                              nstep=self.nstep, state=self.state, sensordata=self.sensordata)
            self.state0[:] = self.state[:, -1] if self.state[0, -1, 0] < 5.0 else self.initial
            steps += len(self.models) * self.nstep
        elapsed = time.perf_counter() - start
        assert np.all(self.state0[:, 3] > 0.9), "the robots fell: the ceiling must be measured standing"
        return steps, elapsed

    def close(self) -> None:
        self.pool.close()


def interleaved(runs: dict, seconds: float, block: float = 0.1) -> dict[str, float]:
    """Steps per second of each run, measured in alternating blocks so that all see the same load."""
    totals = {name: np.zeros(2) for name in runs}
    for run in runs.values():
        run.run(block)  # warm up
    for _ in range(max(1, int(round(seconds / block)))):
        for name, run in runs.items():
            totals[name] += run.run(block)
    return {name: steps / elapsed for name, (steps, elapsed) in totals.items()}


def machine() -> str:
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor())
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {cpu}, {os.cpu_count()} cores, load average {load}, "
            f"mujoco {mujoco.__version__}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="measuring time per figure")
    args = parser.parse_args()
    print(machine())
    runs = {"single thread (mj_step loop)": SingleThread(), "rollout on all cores": RawRollout()}
    for name, rate in interleaved(runs, args.seconds).items():
        print(f"ceiling  {name:28s} {rate:8.0f} physics steps/s")
    for run in runs.values():
        run.close()


if __name__ == "__main__":
    main()
