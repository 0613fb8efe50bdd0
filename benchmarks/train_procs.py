"""PPO training end to end (collection and update) in one process against several (`--procs`), same batch.

On this machine's cores, one process with every core as threads (physics on a thread pool, torch
threads for the update) against P processes with an equal share of the cores each and 1/P of the
worlds (`rl.processes`: gradients averaged over the group), the iteration's batch the same. Printed:
environment steps/s over whole PPO iterations (collection plus the update), after one iteration of
warm-up, each setting measured in its own fresh processes. The references: a squat recorded in the
simulator (as benchmarks/env_throughput.py), the default PPO settings and Table II randomization.

    .venv/bin/python benchmarks/train_procs.py [--worlds 128] [--iterations 6] [--procs 1 2]
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from sim_ceiling import machine

from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.envs.recorded import record_reference, squat_targets
from opt2skill.model import load_robot
from opt2skill.rl import processes
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.trainer import Schedule, Trainer


def measure(worlds: int, iterations: int, threads: int) -> dict:
    """This process's part of the group: `worlds` worlds; the group's environment steps per second
    over `iterations` PPO iterations after one of warm-up (rank 0's clock, between barriers)."""
    group = processes.from_environment()
    torch.set_num_threads(threads)
    robot = load_robot("digit")
    config = tracking_config("recorded")
    bank = ReferenceBank.from_trajectories(robot, [record_reference(robot, squat_targets(robot, 400))],
                                           config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, worlds, seed=group.seed(0), threads=threads) as env:
        trainer = Trainer(env, PPOConfig(), seed=0, group=group)
        trainer.warm_up_normalizers()
        schedule = Schedule(total_steps=(iterations + 1) * trainer.batch)
        trainer.train(schedule, progress=False, stop_after=1)
        group.barrier()
        start = time.perf_counter()
        figures = trainer.train(schedule, progress=False)
        group.barrier()
        elapsed = time.perf_counter() - start
    return {"env_steps_per_s": iterations * trainer.batch / elapsed, "batch": trainer.batch,
            "collect_per_s": figures["perf/env_steps_per_s"], "learn_per_s": figures["perf/learner_samples_per_s"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=128, help="worlds of the whole group")
    parser.add_argument("--iterations", type=int, default=6, help="timed PPO iterations")
    parser.add_argument("--procs", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    print(machine())
    cores = os.cpu_count() or 1
    for procs in args.procs:
        threads = max(1, cores // procs)
        worlds = args.worlds // procs
        if procs == 1:
            result = measure(worlds, args.iterations, threads)
        else:
            result = processes.launch(procs, measure, worlds, args.iterations, threads)
        print(f"{procs} process(es) x {worlds} worlds x {threads} thread(s): {result['env_steps_per_s']:7.0f} "
              f"environment steps/s over whole iterations (batch {result['batch']}); while collecting "
              f"{result['collect_per_s']:6.0f}/s, update {result['learn_per_s']:6.0f} samples/s (summed over processes)")


if __name__ == "__main__":
    main()
