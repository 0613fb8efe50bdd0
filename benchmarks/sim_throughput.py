"""Policy steps per second of the batched simulator, against the raw physics ceiling, in one run.

For N = 16, 64 and 256 worlds: every world randomized as in Table II (link masses, friction,
gravity, Kp/Kd factors, motor strength, action delay 0-20 ms), 5 physics steps per policy step,
the robots standing under the ceiling's PD targets (`--noise` jitters them), fallen or diverged
worlds reset, and every world restarted after 5 s standing, as the ceiling's robots are (the PD
stand tips over sideways after about 18 s). The ceiling (benchmarks/sim_ceiling.py: 32 robots standing, 100 physics steps per
rollout call) runs in blocks alternating with the simulator's, so both see the same machine load;
the ratio counts 5 physics steps per policy step. Jittered targets cost the physics
more solver iterations, which the ceiling does not pay.

    .venv/bin/python benchmarks/sim_throughput.py [--seconds 6] [--worlds 16 64 256] [--rough] [--noise 0.05]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from sim_ceiling import RawRollout, interleaved, machine, standing_targets

from opt2skill.model import load_robot
from opt2skill.sim import MujocoBatchedSim, SimConfig, TerrainGrid, WorldParams, flat, rough
from opt2skill.sim.params import sample_uniform

TABLE_II = {"mass_scale": (0.9, 1.1), "friction_scale": (0.3, 1.0), "gravity_scale": (0.9, 1.1),
            "kp_factor": (0.9, 1.1), "kd_factor": (0.9, 1.1), "motor_strength": (0.95, 1.05), "delay": (0.0, 0.02)}


def table2_params(sim: MujocoBatchedSim, rng: np.random.Generator, k: int, with_rough: bool) -> WorldParams:
    p = sample_uniform(rng, k, sim.nbody, sim.nu, TABLE_II)
    if with_rough:  # half the worlds on one of the rough terrains
        p.terrain = np.where(rng.random(k) < 0.5, rng.integers(1, len(sim.terrains), k), 0)
    return p


class SimRun:
    """The simulator under test, stepped in timed blocks."""

    def __init__(self, nworld: int, with_rough: bool, noise: float, seed: int = 0):
        self.robot = load_robot("digit")
        terrains = [flat()] + ([rough(TerrainGrid(), 0.02, seed=s) for s in range(4)] if with_rough else [])
        self.sim = MujocoBatchedSim(self.robot, nworld, SimConfig(nsubstep=5), terrains=terrains)
        self.rng, self.with_rough, self.resets = np.random.default_rng(seed), with_rough, 0
        self.targets = standing_targets(self.robot) + self.rng.normal(0.0, noise, (64, nworld, self.robot.nu))
        self.steps = 0
        self.reset(np.arange(nworld))

    def reset(self, worlds: np.ndarray) -> None:
        k = len(worlds)
        self.sim.reset(worlds, np.tile(self.robot.stand_qpos, (k, 1)), np.zeros((k, self.robot.nv)),
                       params=table2_params(self.sim, self.rng, k, self.with_rough))

    def run(self, seconds: float) -> tuple[int, float]:
        """(policy steps of all worlds, elapsed seconds) until `seconds` have passed."""
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            out = self.sim.step(self.targets[self.steps % 64])  # targets drawn up front: time the simulator only
            self.steps += 1
            steps += self.sim.nworld
            down = out.unstable | (out.qpos[:, 2] - self.sim.z_offset < 0.7)
            self.resets += int(down.sum())
            again = np.flatnonzero(down | (out.time > 5.0))
            if again.size:
                self.reset(again)
        return steps, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0, help="measuring time per figure (each side)")
    parser.add_argument("--worlds", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--rough", action="store_true", help="also measure with half the worlds on rough terrain")
    parser.add_argument("--noise", type=float, default=0.0, help="std of the jitter added to the targets, rad")
    args = parser.parse_args()
    print(machine())
    ceiling = RawRollout()
    for nworld in args.worlds:
        for with_rough in (False, True) if args.rough else (False,):
            run = SimRun(nworld, with_rough, args.noise)
            rates = interleaved({"sim": run, "ceiling": ceiling}, args.seconds)
            rate, raw = rates["sim"], rates["ceiling"]
            run.sim.close()
            print(f"sim  N={nworld:4d} {'flat+rough' if with_rough else 'flat':10s} {rate:7.0f} policy steps/s "
                  f"= {5 * rate:6.0f} physics steps/s; ceiling {raw:6.0f}; {5 * rate / raw:6.1%} of the ceiling "
                  f"({run.resets} falls)")
    ceiling.close()


if __name__ == "__main__":
    main()
