"""The tracking environment and the PPO learner against the raw physics ceilings, in one run.

Prints on this machine:

1. the standing ceiling (benchmarks/sim_ceiling.py): `mujoco.rollout` of 32 standing robots, 100
   physics steps per call, on all cores (the issue's "mj_step physics steps/s of the Digit model");
2. the environment's policy steps/s for N = 16, 64 and 256 worlds with observations, rewards,
   terminations, resets and Table II randomization (rough terrain for half the resets), the
   robots tracking references (a dataset, or a squat recorded in the simulator) under PD targets
   near the reference plus noise like an exploring policy's, against two ceilings measured in
   alternating blocks beside it:
   - its own physics: the starts and controls of its simulator's batch calls (`mujoco.batch`) over
     100 policy steps, recorded, replayed in calls of 20 policy steps (100 physics steps) with
     nothing between them, on its models and thread pool (`SameWorkCeiling`): what the environment
     could reach if all its Python and the 5-step call granularity cost nothing;
   - the standing ceiling, counting 5 physics steps per policy step (a moving robot costs the
     physics more than a standing one, which no environment code can recover);
   and the share of the step spent inside the batch's calls; and the same work replayed in calls of
   one policy step (5 physics steps), as the environment calls the physics, which splits the gap to
   its own physics into what the short calls cost and what the environment's Python costs;
   and the host work outside the physics per world, with the rate it alone allows (what bounds a
   GPU backend fed by this environment);
3. the PPO learner's samples/s (rsl_rl update: 5 epochs of 4 mini-batches over 128 worlds x 48 steps,
   actor and critic [512, 512, 256, 256]) with 1 and 2 torch threads, in float32 and with bf16
   autocast (`train --mixed-precision`).

With `--device cuda` (MuJoCo Warp on the GPU, the PPO learner on the same GPU; `warp-cpu` runs the
same on Warp's CPU device, to check the plumbing) it runs whole PPO iterations instead, per N (default
1024 to 8192 worlds), and reports the environment's policy steps/s while collecting, the learner's
samples/s and the policy steps/s of training as a whole (collection and update), in float32 and with
bf16 autocast, against issue 18's target of 300 M steps in an hour (83.3k/s). There is no `rollout`
ceiling on that path.

    .venv/bin/python benchmarks/env_throughput.py [--dataset DIR] [--seconds 6] [--worlds 16 64 256]
    .venv/bin/python benchmarks/env_throughput.py --device cuda [--worlds 1024 2048 4096 8192] [--iterations 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from sim_ceiling import CTRL, RawRollout, interleaved, machine

from opt2skill.data.reader import Dataset
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.envs.recorded import record_reference, squat_targets
from opt2skill.model import load_robot
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.trainer import Trainer


def references(robot, dataset: str | None):
    if dataset:
        ds = Dataset.open(dataset)
        config = tracking_config(ds.identity.get("task", ""))
        return config, ReferenceBank.from_dataset(robot, ds, config.observations.end_effectors)
    config = tracking_config("recorded")
    traj = record_reference(robot, squat_targets(robot, 400))
    return config, ReferenceBank.from_trajectories(robot, [traj], config.observations.end_effectors)


class EnvRun:
    """The environment stepped in timed blocks by a reference-following noisy 'policy'."""

    def __init__(self, robot, config, bank, nworld: int, noise: float = 0.1, seed: int = 0):
        self.env = TrackingEnv(robot, bank, config, nworld, seed=seed)
        self.env.set_progress(1.0)  # full observation noise and penalties
        self.rng, self.noise = np.random.default_rng(seed), noise
        self.joints = bank.kin_cols["joint_pos"]
        self.physics = 0.0
        sim = self.env.sim
        rollout = self.raw_rollout = sim._batch.rollout

        def timed(nstep, control, **kwargs):  # time spent in the physics itself
            if self.recorded is not None:
                self.recorded.append((sim._rows.copy(), np.array(control)))
            start = time.perf_counter()
            out = rollout(nstep, control, **kwargs)
            self.physics += time.perf_counter() - start
            return out

        sim._batch.rollout = timed
        self.recorded: list[tuple[np.ndarray, np.ndarray]] | None = None  # (start, control) of each call while recording
        self.noises = self.rng.normal(0.0, noise, (64, nworld, robot.nu))
        self.steps, self.elapsed = 0, 0.0

    def step(self) -> None:
        env = self.env
        targets = env.bank.kin[env._row + 1][:, self.joints]
        env.step(env.actions_for_targets(targets) + self.noises[self.steps % 64])
        self.steps += 1

    def run(self, seconds: float) -> tuple[int, float]:
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            self.step()
            steps += self.env.num_envs
        elapsed = time.perf_counter() - start
        self.elapsed += elapsed
        return steps, elapsed

    def record(self, policy_steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The (start state, controls) of the physics calls of the next `policy_steps` steps."""
        self.recorded = []
        for _ in range(policy_steps):
            self.step()
        recorded, self.recorded = self.recorded, None
        return recorded


class SameWorkCeiling:
    """The environment's own physics without the environment: the starts (each world's state row,
    zero warm start) and controls of its batch calls (recorded from an `EnvRun`), replayed on its
    models and thread pool in calls of
    `block` policy steps (5 * block physics steps) with nothing between them. A block starts from the
    state its first policy step started from and then runs open loop on the recorded controls, which
    is the environment's exact trajectory until a world was reset or pushed inside the block; those
    worlds continue their old motion (a fall, mostly) for the rest of the block.

    This is the ceiling the environment can reach on this task: the standing ceiling (`RawRollout`)
    costs the physics less than tracking a motion does (contacts change, PD targets move), which no
    environment code can recover."""

    def __init__(self, run: EnvRun, policy_steps: int = 100, block: int = 20):
        sim = run.env.sim
        self.sim, self.rollout = sim, run.raw_rollout
        recorded = run.record(policy_steps)
        self.blocks = [
            (recorded[i][0], np.concatenate([control for _, control in recorded[i:i + block]], axis=1))
            for i in range(0, policy_steps - block + 1, block)
        ]
        self.nstep = self.blocks[0][1].shape[1]
        self.out = {"sensordata": np.zeros((sim.nworld, self.nstep, sim._out_sensor.shape[2]))}
        self.calls = 0

    def run(self, seconds: float) -> tuple[int, float]:
        """(policy steps of all worlds, elapsed seconds) of whole calls made until `seconds` have passed;
        the environment's worlds are put back as they were."""
        sim = self.sim
        saved = sim._rows.copy()
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            rows, control = self.blocks[self.calls % len(self.blocks)]
            sim._rows[:] = rows
            self.rollout(self.nstep, control, control_spec=CTRL, record=("sensordata",), out=self.out)
            self.calls += 1
            steps += sim.nworld * self.nstep // sim.nsubstep
        elapsed = time.perf_counter() - start
        sim._rows[:] = saved
        return steps, elapsed


def learner_rate(robot, config, bank, threads: int, repeats: int = 3, mixed_precision: bool = False) -> float:
    """Samples per second through PPO's update (epochs counted), on a real rollout of 128 worlds."""
    torch.set_num_threads(threads)
    ppo = PPOConfig(mixed_precision=mixed_precision)
    with TrackingEnv(robot, bank, config, 128, seed=0) as env:
        trainer = Trainer(env, ppo, None, seed=0)
        trainer.warm_up_normalizers()
        alg, venv = trainer.alg, trainer.venv
        obs = venv.get_observations()
        with torch.inference_mode():
            for _ in range(trainer.steps_per_env):
                obs, rewards, dones, extras = venv.step(alg.act(obs))
                alg.process_env_step(obs, rewards, dones, extras)
            alg.compute_returns(obs)
        times = []
        for _ in range(repeats):  # update() clears only the storage's counter: the data stays
            start = time.perf_counter()
            alg.update()
            times.append(time.perf_counter() - start)
        return trainer.batch * ppo.num_learning_epochs / min(times)


TARGET = 300e6 / 3600  # issue 18: the paper's 300 M steps in an hour on one GPU, learning included


def device_rates(robot, config, bank, device: str, nworld: int, iterations: int,
                 mixed_precision: bool = False) -> dict[str, float]:
    """Whole PPO iterations of `nworld` worlds with physics on `device` and the learner where
    `rl.trainer` puts it; medians over `iterations` after one untimed (kernels loaded, graphs captured)."""
    with TrackingEnv(robot, bank, config, nworld, seed=0, device=device) as env:
        trainer = Trainer(env, PPOConfig(mixed_precision=mixed_precision), None, seed=0)
        trainer.warm_up_normalizers()
        trainer.train_iteration()
        rows = [trainer.train_iteration() for _ in range(iterations)]
        return {"learner device": str(trainer.venv.device),
                "env": float(np.median([r["perf/env_steps_per_s"] for r in rows])),
                "learner": float(np.median([r["perf/learner_samples_per_s"] for r in rows])),
                "training": trainer.batch / float(np.median([r["perf/iteration_s"] for r in rows]))}


def on_device(robot, config, bank, device: str, worlds: list[int], iterations: int) -> None:
    from opt2skill.sim.devices import check_device

    check_device(device)
    print(f"device {device}: PPO iterations ({PPOConfig().steps_per_env(0.005)} steps of every world, then "
          f"{PPOConfig().num_learning_epochs} epochs), medians of {iterations}")
    for nworld in worlds:
        for mixed in (False, True):
            r = device_rates(robot, config, bank, device, nworld, iterations, mixed)
            print(f"env  N={nworld:5d} collecting {r['env']:9.0f} policy steps/s; learner on {r['learner device']} "
                  f"({'bf16 autocast' if mixed else 'float32'}): {r['learner']:9.0f} samples/s; training "
                  f"{r['training']:9.0f} policy steps/s = {r['training'] / TARGET:6.1%} of the 83.3k/s target")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", help="reference dataset (default: a squat recorded in the simulator)")
    parser.add_argument("--seconds", type=float, default=6.0, help="measuring time per figure (each side)")
    parser.add_argument("--worlds", type=int, nargs="+", default=None, help="default: 16 64 256 (cpu), "
                        "1024 2048 4096 8192 (cuda)")
    parser.add_argument("--device", default="cpu", help="cpu (C MuJoCo, against its ceilings), cuda, cuda:K or "
                        "warp-cpu (whole PPO iterations)")
    parser.add_argument("--iterations", type=int, default=5, help="timed PPO iterations per N (--device not cpu)")
    parser.add_argument("--no-learner", action="store_true", help="the environment's figures only (cpu)")
    args = parser.parse_args()
    print(machine())
    robot = load_robot("digit")
    config, bank = references(robot, args.dataset)
    if args.device != "cpu":
        on_device(robot, config, bank, args.device, args.worlds or [1024, 2048, 4096, 8192], args.iterations)
        return
    args.worlds = args.worlds or [16, 64, 256]
    ceiling = RawRollout()
    raw = interleaved({"ceiling": ceiling}, args.seconds)["ceiling"]
    print(f"ceiling  rollout, 32 standing robots, all cores: {raw:8.0f} physics steps/s "
          f"= {raw / 5:6.0f} policy steps/s at 5 physics steps each")
    for nworld in args.worlds:
        run = EnvRun(robot, config, bank, nworld)
        run.run(0.5)  # into the motion: resets and falls under way
        same = SameWorkCeiling(run)
        per_step = SameWorkCeiling(run, block=1)
        run.physics = run.elapsed = 0.0
        rates = interleaved({"env": run, "same": same, "per_step": per_step, "ceiling": ceiling}, args.seconds)
        rate, raw = rates["env"], rates["ceiling"]
        physics = run.physics / run.elapsed
        run.env.close()
        print(f"env  N={nworld:4d} {rate:7.0f} policy steps/s = {5 * rate:6.0f} physics steps/s; "
              f"{rate / rates['same']:6.1%} of its own physics in {same.nstep}-step calls ({rates['same']:6.0f} policy steps/s); "
              f"{5 * rate / raw:6.1%} of the standing ceiling ({raw:6.0f}); {physics:5.1%} of the step inside the batch's calls")
        # The environment calls the physics once per policy step: the same work in calls of one
        # policy step, with nothing between them, splits the gap into the calls' own cost and the rest
        print(f"         the same physics in {per_step.nstep}-step calls, as the environment calls it: "
              f"{rates['per_step']:6.0f} policy steps/s = {rates['per_step'] / rates['same']:6.1%} of the "
              f"{same.nstep}-step calls; the environment {rate / rates['per_step']:6.1%} of it")
        # Everything but the physics runs on one host core, whichever backend steps the worlds: its cost
        # per world bounds a GPU backend fed by this environment (issue 18's target: 83.3k policy steps/s)
        host = (1.0 - physics) * nworld / rate  # seconds per policy step
        print(f"         host work outside the physics: {host * 1e3:6.2f} ms per step = {host / nworld * 1e6:5.1f} us "
              f"per world; alone it caps any backend at {nworld / host:6.0f} policy steps/s")
    ceiling.close()
    for threads in () if args.no_learner else (1, 2):
        for mixed in (False, True):
            print(f"learner  {threads} torch thread(s), {'bf16 autocast' if mixed else 'float32'}: "
                  f"{learner_rate(robot, config, bank, threads, mixed_precision=mixed):8.0f} samples/s "
                  f"(5 epochs x 4 mini-batches of 1536, actor and critic [512, 512, 256, 256])")


if __name__ == "__main__":
    main()
