"""Time to skill: plain PPO against distillation + PPO, same data, same held-out references, same cores.

Each pipeline trains for a fixed wall-clock budget on the training dataset; every `--eval-minutes`
of training the clock stops and the current actor (deterministic actions) tracks the held-out
references from frame 0 with randomization and noise off, as `opt2skill eval` does (`eval.rollout`
with `eval.evaluate.eval_config`: drifting away does not end the episode, falling does; the metrics
of `eval.metrics.tracking_errors`). Recorded against training wall-clock time:

- success rate (the reference tracked to its end without a termination), and the share of the
  references' frames tracked before any termination,
- E_ee-foot, E_joint, E_vel-x and E_pos-x, means over the held-out references (a fallen rollout is
  compared on the frames it has; E_pos-x skips stepping-in-place references, as the metric does).

It reports the time each pipeline first reaches the Opt2Skill row of the paper's Table III with
success >= 95 %, writes the curves as JSON and one plot.

1. **ppo**: `rl.trainer.Trainer` with the default PPOConfig, normalizer warm-up as `opt2skill train`.
2. **distill**: `rl.distill.Distiller` for `--distill-fraction` of the budget (its expert share and
   learning rate follow the elapsed fraction of that time), then PPO from the distilled actor as
   `opt2skill train --init distill` does (critic warm-up with the actor frozen, small action noise).

PPO's curriculum needs the planned total of steps: it is re-estimated at every iteration from the
measured rate and the remaining time, so the curriculum ends with the budget.

    .venv/bin/python benchmarks/time_to_skill.py --dataset data/walk --held-out data/walk_test \\
        [--budget-minutes 120] [--eval-minutes 10] [--num-envs 128] [--threads 2] [--out bench/tts]
"""

from __future__ import annotations

import argparse
import json
import textwrap
import time
from pathlib import Path

import numpy as np
import torch
from sim_ceiling import machine

from opt2skill.data.atomic import dumps
from opt2skill.data.reader import Dataset
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.eval.evaluate import eval_config
from opt2skill.eval.rollout import rollout
from opt2skill.model import load_robot
from opt2skill.rl.best import TABLE_III, TABLE_III_UNITS
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.distill import Distiller
from opt2skill.rl.distill_config import DistillConfig, distillation_tracking_config, finetune_tracking_config
from opt2skill.rl.distill_session import dataset_expert, finetune_trainer, set_actor_frozen, start_from_distilled
from opt2skill.rl.policy import Policy, build_actor
from opt2skill.rl.trainer import Schedule, Trainer

# Table III, Opt2Skill (walking): the row to reach, and the success rate required with it.
TARGET, UNITS = TABLE_III, TABLE_III_UNITS
MIN_SUCCESS = 0.95


class Clock:
    """Training wall-clock time: runs except while evaluating."""

    def __init__(self):
        self.spent, self._start = 0.0, time.perf_counter()

    def pause(self) -> None:
        self.spent += time.perf_counter() - self._start

    def resume(self) -> None:
        self._start = time.perf_counter()

    def now(self) -> float:
        return self.spent + time.perf_counter() - self._start


class Curve:
    """Evaluations of one pipeline on the held-out references, against training time."""

    def __init__(self, name: str, robot, references, config, threads: int, eval_seconds: float):
        self.name, self.robot, self.references, self.config, self.threads = name, robot, references, config, threads
        self.eval_seconds, self.points, self.clock = eval_seconds, [], Clock()
        self._next = 0.0

    def due(self) -> bool:
        return self.clock.now() >= self._next

    def evaluate(self, actor, stage: str, env_steps: int) -> dict:
        self.clock.pause()
        t = self.clock.spent
        training = actor.training
        policy = Policy(actor)  # a snapshot of the normalizer and the MLP (it sets the actor to eval mode)
        actor.train(training)
        rollouts = rollout(self.robot, self.references, policy, self.config, threads=self.threads)
        errors = [r.errors() for r in rollouts]
        point = {"minutes": t / 60, "stage": stage, "env_steps": env_steps,
                 "success": float(np.mean([not r.fell for r in rollouts])),
                 "tracked": float(np.mean([r.steps / (r.reference.num_frames - 1) for r in rollouts]))}
        for name in TARGET:
            values = [getattr(e, name) for e in errors if np.isfinite(getattr(e, name))]
            point[name] = float(np.mean(values)) if values else float("nan")
        point["reached"] = bool(point["success"] >= MIN_SUCCESS and all(point[k] <= v for k, v in TARGET.items()))
        self.points.append(point)
        print(f"  {self.name:8s} {stage:8s} {point['minutes']:6.1f} min {env_steps:>10,} steps  success "
              f"{100 * point['success']:5.1f} % (frames {100 * point['tracked']:5.1f} %)  " + "  ".join(f"{k} {point[k]:.3g}" for k in TARGET), flush=True)
        self._next = t + self.eval_seconds
        self.clock.resume()
        return point

    def time_to_target(self) -> float | None:
        return next((p["minutes"] for p in self.points if p["reached"]), None)


def ppo_phase(trainer: Trainer, curve: Curve, end: float, stage: str, warmup: int = 0, step_offset: int = 0) -> None:
    """PPO iterations until the curve's clock reaches `end` seconds; the curriculum's planned total is
    re-estimated from the measured rate so that it ends with the budget. The first `warmup`
    iterations train the critic only. `step_offset`: environment steps of earlier stages."""
    start_steps, start_time = trainer.env_steps, curve.clock.now()
    frozen = trainer.iteration < warmup
    if frozen:
        set_actor_frozen(trainer, True)
    while curve.clock.now() < end:
        if curve.due():
            curve.evaluate(trainer.alg.get_policy(), stage, step_offset + trainer.env_steps)
        done = trainer.env_steps - start_steps
        rate = done / (curve.clock.now() - start_time) if done else 0.0
        total = trainer.env_steps + max(int(rate * (end - curve.clock.now())), trainer.batch) if rate else 10**12
        trainer.train(Schedule(total), progress=False, stop_after=trainer.iteration + 1)
        if frozen and trainer.iteration >= warmup:
            set_actor_frozen(trainer, False)
            frozen = False
    curve.evaluate(trainer.alg.get_policy(), stage, step_offset + trainer.env_steps)


def plain_ppo(args, robot, dataset, task, curve: Curve) -> None:
    bank = ReferenceBank.from_dataset(robot, dataset, task.observations.end_effectors)
    with TrackingEnv(robot, bank, task, args.num_envs, seed=args.seed, threads=args.threads) as env:
        trainer = Trainer(env, PPOConfig(), seed=args.seed)
        trainer.warm_up_normalizers()
        ppo_phase(trainer, curve, args.budget_minutes * 60, "ppo")


def distill_then_ppo(args, robot, dataset, task, curve: Curve) -> None:
    distill = DistillConfig()
    distill_end = args.distill_fraction * args.budget_minutes * 60
    env_config = distillation_tracking_config(task, distill)
    bank = ReferenceBank.from_dataset(robot, dataset, env_config.observations.end_effectors)
    with TrackingEnv(robot, bank, env_config, args.num_envs, seed=args.seed, threads=args.threads) as env:
        torch.manual_seed(args.seed)
        actor = build_actor(distill.finetune_ppo(), env.actor_dim, env.critic_dim, env.nu)
        expert = dataset_expert(env, dataset, distill)
        distiller = Distiller(env, expert, actor, distill, seed=args.seed)
        while curve.clock.now() < distill_end:
            if curve.due() and distiller.iteration > 0:
                curve.evaluate(actor, "distill", distiller.env_steps)
            done = curve.clock.now() / distill_end  # the stage's schedule follows its time budget
            distiller.total_iterations = max(distiller.iteration + 1, round(distiller.iteration / max(done, 1e-9)))
            distiller.train_iteration()
        curve.evaluate(actor, "distill", distiller.env_steps)
        distilled = {"actor_state_dict": actor.state_dict(), "elapsed": 0.0}
        offset = distiller.env_steps
    finetune = finetune_tracking_config(task, distill)
    bank = ReferenceBank.from_dataset(robot, dataset, finetune.observations.end_effectors)
    with TrackingEnv(robot, bank, finetune, args.num_envs, seed=args.seed, threads=args.threads) as env:
        trainer = finetune_trainer(env, dataset, distill, None, args.seed)
        start_from_distilled(trainer, distilled)
        ppo_phase(trainer, curve, args.budget_minutes * 60, "ppo", warmup=distill.critic_warmup_iterations,
                  step_offset=offset)


class SavedCurve:
    """A curve read back from a time_to_skill.json (to plot pipelines run separately together)."""

    def __init__(self, name: str, points: list[dict]):
        self.name, self.points = name, points


def plot(curves: list[Curve], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("success", "success rate (%)", 100 * MIN_SUCCESS)] + [(k, f"{k} ({UNITS[k]})", v) for k, v in TARGET.items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.6))
    for ax, (key, label, target) in zip(axes, panels):
        for curve, color in zip(curves, ("tab:blue", "tab:orange", "tab:green", "tab:red")):
            x = [p["minutes"] for p in curve.points]
            y = [100 * p[key] if key == "success" else p[key] for p in curve.points]
            ax.plot(x, y, "o-", color=color, label=curve.name, markersize=3)
            if key == "success":
                ax.plot(x, [100 * p["tracked"] for p in curve.points], ":", color=color, label=f"{curve.name}: frames tracked")
            distilled = [p["minutes"] for p in curve.points if p["stage"] == "distill"]
            if distilled:  # the end of the distillation stage
                ax.axvline(distilled[-1], color=color, alpha=0.3, linestyle=":")
        ax.axhline(target, color="k", linestyle="--", linewidth=1, label="Table III" if key != "success" else "95 %")
        ax.set_xlabel("training wall-clock (min)")
        ax.set_title(label, fontsize=10)
        if key not in ("success",):
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle(textwrap.fill(title, 220), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", help="training dataset (with --keep-gains)")
    parser.add_argument("--held-out", help="dataset of held-out references")
    parser.add_argument("--n-eval", type=int, default=10, help="held-out references evaluated")
    parser.add_argument("--budget-minutes", type=float, default=120.0, help="training wall-clock per pipeline")
    parser.add_argument("--eval-minutes", type=float, default=10.0, help="training time between evaluations")
    parser.add_argument("--distill-fraction", type=float, default=0.25, help="share of the budget spent distilling")
    parser.add_argument("--num-envs", type=int, default=128)
    parser.add_argument("--threads", type=int, default=2, help="physics and torch threads")
    parser.add_argument("--pipelines", default="ppo,distill")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench/time_to_skill")
    parser.add_argument("--replot", nargs="+", metavar="JSON[:PIPELINE]",
                        help="only plot curves of earlier runs together (a file, or one pipeline of it)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        curves, machines = [], []
        for spec in args.replot:  # FILE or FILE:PIPELINE
            path, _, only = spec.partition(":")
            data = json.loads(Path(path).read_text())
            machines.append(data["machine"])
            curves += [SavedCurve(name, points) for name, points in data["curves"].items() if only in ("", name)]
        plot(curves, out / "time_to_skill.png", " | ".join(dict.fromkeys(machines)))
        print(f"wrote {out / 'time_to_skill.png'}")
        return
    if not (args.dataset or args.held_out):  # `make bench` runs every benchmark without arguments
        print("time_to_skill: skipped, needs --dataset and --held-out (or --replot)")
        return
    if not (args.dataset and args.held_out):
        parser.error("--dataset and --held-out are required (unless --replot)")
    torch.set_num_threads(args.threads)
    robot = load_robot("digit")
    dataset = Dataset.open(args.dataset)
    held_out = Dataset.open(args.held_out)
    references = [held_out[i] for i in range(min(args.n_eval, len(held_out)))]
    task = tracking_config(dataset.identity.get("task", ""))
    evaluation = eval_config(task)  # as `opt2skill eval`: drift is measured, not ended; falls end
    header = (f"{machine()}; {len(dataset)} training and {len(references)} held-out references; "
              f"{args.budget_minutes:g} min per pipeline, {args.num_envs} worlds, {args.threads} threads")
    print(header)
    curves = []
    for name in args.pipelines.split(","):
        run = {"ppo": plain_ppo, "distill": distill_then_ppo}[name]
        curve = Curve(name, robot, references, evaluation, args.threads, 60 * args.eval_minutes)
        run(args, robot, dataset, task, curve)
        curves.append(curve)
    summary = {name: c.time_to_target() for name, c in zip(args.pipelines.split(","), curves)}
    (out / "time_to_skill.json").write_text(dumps({"machine": header, "args": vars(args), "target": TARGET,
                                                   "min_success": MIN_SUCCESS, "time_to_target_minutes": summary,
                                                   "curves": {c.name: c.points for c in curves}}, indent=1) + "\n")
    plot(curves, out / "time_to_skill.png", header)
    print("\ntime to Table III's Opt2Skill row with success >= 95 %:")
    for c in curves:
        t, last = c.time_to_target(), c.points[-1]
        print(f"  {c.name:8s} {'not reached' if t is None else f'{t:.1f} min'};  last: success {100 * last['success']:.0f} %, "
              + ", ".join(f"{k} {last[k]:.3g} {UNITS[k]} (<= {v})" for k, v in TARGET.items()))
    print(f"wrote {out / 'time_to_skill.json'} and {out / 'time_to_skill.png'}")


if __name__ == "__main__":
    main()
