"""Physics steps per second of the MuJoCo Warp backend (WarpBatchedSim) for many worlds.

Every world randomized as in Table II (benchmarks/sim_throughput.py), standing under jittered PD
targets, 5 physics steps of 1 ms per policy step; worlds whose base drops below 0.6 m are reset.
Two figures per N, both counting physics steps of all worlds:

- `device`: the S physics steps on the device alone (control switch, `mujoco_warp.step`, sensor
  recording; a CUDA graph on GPUs), synchronized: what the GPU physics gives;
- `sim.step`: the whole `BatchedSim.step`, with the action delay, the host<->device copies and the
  numpy decoding of the outputs: what the numpy environment gets today.

    .venv/bin/python benchmarks/sim_warp.py --device cuda [--worlds 1024 2048 4096 8192] [--seconds 10]
    .venv/bin/python benchmarks/sim_warp.py --device cpu  [--worlds 4 16]   # Warp's CPU device, reference only

The first run on a machine compiles MuJoCo Warp's kernels (minutes; cached in ~/.cache/warp).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from sim_ceiling import machine, standing_targets
from sim_throughput import TABLE_II

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.sim import SimConfig
from opt2skill.sim.devices import check_device
from opt2skill.sim.params import sample_uniform


def measure(robot, nworld: int, device: str, seconds: float, noise: float, seed: int = 0) -> dict:
    from opt2skill.sim.warp_sim import WarpBatchedSim, wp

    rng = np.random.default_rng(seed)
    built = time.perf_counter()
    sim = WarpBatchedSim(robot, nworld, SimConfig(nsubstep=5), device=device)
    targets = standing_targets(robot) + rng.normal(0.0, noise, (16, nworld, robot.nu))

    def reset(worlds):
        k = len(worlds)
        sim.reset(worlds, np.tile(robot.stand_qpos, (k, 1)), np.zeros((k, robot.nv)),
                  params=sample_uniform(rng, k, sim.nbody, sim.nu, TABLE_II))

    reset(np.arange(nworld))
    for t in range(2):  # compiles, captures the graph
        sim.step(targets[t])
    wp.synchronize_device(sim.device)
    setup = time.perf_counter() - built

    steps, resets, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        out = sim.step(targets[steps % 16])
        steps += 1
        fallen = np.flatnonzero((out.qpos[:, 2] < 0.6) | out.unstable)
        if len(fallen):
            reset(fallen)
            resets += len(fallen)
    full = steps * nworld * sim.nsubstep / (time.perf_counter() - start)

    calls, start = 0, time.perf_counter()
    with wp.ScopedDevice(sim.device):
        while time.perf_counter() - start < seconds:
            sim._run_substeps()
            calls += 1
            if calls % 10 == 0:
                wp.synchronize_device(sim.device)
        wp.synchronize_device(sim.device)
    device_only = calls * nworld * sim.nsubstep / (time.perf_counter() - start)
    sim.close()
    return {"worlds": nworld, "device": device_only, "sim.step": full, "resets": resets, "setup_s": setup}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="cuda, cuda:K, or cpu (Warp's CPU device); default: cuda "
                        "if MuJoCo Warp and a GPU are here, else nothing to measure (make bench)")
    parser.add_argument("--worlds", type=int, nargs="+", default=None)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--noise", type=float, default=0.05, help="std of the PD target jitter, rad")
    args = parser.parse_args()
    if args.device is None:
        try:
            check_device("cuda")
        except ConfigError as exc:
            print(f"skipped: {exc} (pass --device cuda or --device cpu to insist)")
            return
        args.device = "cuda"
    device = "cpu" if args.device in ("cpu", "warp-cpu") else args.device
    try:
        check_device("warp-cpu" if device == "cpu" else device)
    except ConfigError as exc:
        raise SystemExit(f"error: {exc}") from None
    worlds = args.worlds or ([4, 16] if device == "cpu" else [1024, 2048, 4096, 8192])
    from opt2skill.sim.warp_sim import wp

    print(f"{machine()}, warp {wp.__version__}, device {device} ({wp.get_device(device).name})")
    robot = load_robot("digit")
    print(f"{'worlds':>7} {'device phys/s':>14} {'sim.step phys/s':>16} {'policy steps/s':>15} {'resets':>7} {'setup s':>8}")
    for n in worlds:
        r = measure(robot, n, device, args.seconds, args.noise)
        print(f"{r['worlds']:>7} {r['device']:>14,.0f} {r['sim.step']:>16,.0f} {r['sim.step'] / 5:>15,.0f} "
              f"{r['resets']:>7} {r['setup_s']:>8.1f}", flush=True)


if __name__ == "__main__":
    main()
