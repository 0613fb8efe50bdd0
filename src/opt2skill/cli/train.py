"""`opt2skill train | play`: train a tracking policy with PPO (resumable; optionally distilled from the
optimizer's feedback expert first), roll a checkpoint or the expert out."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import numpy as np
import typer

from opt2skill.cli.console import console, figures_table

app = typer.Typer()


def _say(line: str) -> None:
    console.print(line, highlight=False, soft_wrap=True)


def _warn_emulated_bf16(request) -> None:
    """One line when --mixed-precision would run the learner's bf16 on a CPU that emulates it."""
    from opt2skill.rl.config import native_bf16
    from opt2skill.sim.devices import learner_device

    if request.mixed_precision and learner_device(request.device, request.procs) == "cpu" and native_bf16() is False:
        _say("warning: --mixed-precision on a CPU without native bf16 (no avx512_bf16 or amx_bf16 in /proc/cpuinfo): "
             "the PPO update may run slower than in float32; benchmarks/env_throughput.py measures both")


@app.command()
def train(
    dataset: Path = typer.Option(..., "--dataset", help="Reference dataset directory (opt2skill generate)."),
    out: Path = typer.Option(..., "--out", help="Run directory; rerunning the same command resumes it."),
    steps: int = typer.Option(10_000_000, help="Environment steps to train for (all worlds together; "
                              "about 2 M per 30 minutes on 2 cores). Sets the curriculum's pace."),
    num_envs: int = typer.Option(128, "--num-envs", help="Simulated worlds."),
    history: int = typer.Option(10, help="History length N (joint positions and actions, every 4 steps)."),
    ablation: str = typer.Option("pos_f_t", help="Reference force/torque inputs and rewards: pos, pos_f, pos_t, pos_f_t."),
    seed: int = typer.Option(0, help="Seed of everything random (episodes, randomization, noise, networks)."),
    threads: int = typer.Option(None, help="Physics and torch threads (default: every core)."),
    checkpoint_every: int = typer.Option(50, "--checkpoint-every", help="Iterations between checkpoints (also every 5 min)."),
    init: str = typer.Option("scratch", "--init", help="scratch: PPO from an untrained actor; distill: distil the "
                             "optimizer's feedback expert into the actor first (dataset made with --keep-gains)."),
    distill_steps: int = typer.Option(2_000_000, "--distill-steps", help="Environment steps of distillation (--init distill)."),
    distill_noise: float = typer.Option(0.0, "--distill-noise", help="Factor in [0, 1] on Table II's observation noise "
                                        "the actor reads while distilling (the expert reads the true state)."),
    finetune: str = typer.Option("full", "--finetune", help="--init distill: what PPO trains after distillation: "
                                 "full (the distilled actor's weights) or residual (the distilled actor frozen, "
                                 "extra units learn a correction; rl.residual)."),
    pace: str = typer.Option("clock", "--pace", help="--init distill: the PPO stage's curriculum advances with the "
                             "steps (clock) or only while the worlds rarely fail (adaptive; rl.pace)."),
    sampling: str = typer.Option("uniform", "--sampling", help="Where episodes start: uniform (any reference, any "
                                 "frame) or adaptive (more often where worlds fail; envs.start_sampling)."),
    kp_scale: float = typer.Option(1.0, "--kp-scale", help="Servo stiffness for this policy: the robot's Kp times "
                                   "this, in [0.05, 2] (training, evaluation, export)."),
    held_out: Path = typer.Option(None, "--held-out", help="References of another seed: every --judge-every "
                                  "iterations the actor tracks them under Table II and noise; the best is kept "
                                  "in RUN/best (what eval and export take by default)."),
    judge_every: int = typer.Option(50, "--judge-every", help="Iterations between held-out judgements."),
    judge_n: int = typer.Option(10, "--judge-n", help="Held-out references per judgement."),
    device: str = typer.Option("cpu", "--device", help="Physics backend: cpu (C MuJoCo on every core) or cuda "
                               "(MuJoCo Warp on the GPU, and PPO learning there too; pip install "
                               "'opt2skill[gpu]', docs/training.md)."),
    procs: int = typer.Option(1, "--procs", help="Processes training together on this machine, each with "
                              "--num-envs worlds and its share of the cores; their gradients are averaged "
                              "(rl.processes; --init scratch). Under torchrun, torchrun's processes."),
    mixed_precision: bool = typer.Option(False, "--mixed-precision", help="bf16 autocast in PPO's update (weights and "
                                         "rollouts stay float32): 2.7 times the learner's speed on a CPU with "
                                         "AVX512-BF16, slower where bf16 is emulated; a GPU computes bf16 natively "
                                         "(docs/training.md)."),
    init_from: Path = typer.Option(None, "--init-from", help="A run (its newest checkpoint) or a checkpoint file of "
                                   "the same robot, task and inputs: PPO starts from its actor, critic and optimizer, "
                                   "the curriculum where that run left it (a fine-tune, e.g. with another "
                                   "--base-position; --init scratch)."),
    base_position: str = typer.Option("task", "--base-position", help="The base-position reward: task (as the "
                                      "task has it: Table I leaves it out for walking), on or off (a deviation "
                                      "from the paper, recorded in run.json)."),
    reward: list[str] = typer.Option([], "--reward", help="A reward term's weight and kernel scale changed from "
                                     "Table I, NAME=WEIGHT[:SCALE] (repeatable; e.g. base_lin_vel=0.3:8; a "
                                     "deviation from the paper, recorded in run.json). Terms: docs/envs.md."),
    noise_min: float = typer.Option(1.0, "--noise-min", help="The least share in [0, 1] of Table II's observation "
                                    "noise a world trains with: each world draws its share uniformly in [SHARE, 1] "
                                    "at every reset. 1 (the paper): every world at full noise; below 1 the policy "
                                    "also meets the noise-free world (a deviation from the paper, recorded in "
                                    "run.json; docs/experiments.md)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Train a tracking policy on a dataset (PPO, rsl_rl); checkpoints, TensorBoard logs, resume."""
    from opt2skill.envs.config import parse_reward
    from opt2skill.errors import ConfigError
    from opt2skill.rl import processes
    from opt2skill.rl.best import JudgeConfig
    from opt2skill.rl.session import TrainRequest
    from opt2skill.rl.session import train as run

    if init not in ("scratch", "distill"):
        raise ConfigError(f"--init must be 'scratch' or 'distill', got '{init}'")
    if init == "scratch" and (finetune != "full" or pace != "clock"):
        raise ConfigError("--finetune and --pace set the PPO stage after distillation: use them with --init distill")

    request = TrainRequest(dataset=dataset, out=out, steps=steps, num_envs=num_envs, history=history,
                           ablation=ablation, seed=seed, threads=threads, checkpoint_every=checkpoint_every,
                           command=shlex.join(["opt2skill", *sys.argv[1:]]), held_out=held_out, kp_scale=kp_scale, sampling=sampling,
                           judge=JudgeConfig(every=judge_every, n=judge_n, seed=seed), device=device,
                           procs=procs, mixed_precision=mixed_precision, base_position=base_position,
                           init_from=init_from, rewards=tuple(parse_reward(text) for text in reward),
                           noise_min=noise_min)
    request.check()
    _warn_emulated_bf16(request)
    processes.terminate_as_interrupt()
    if init == "distill":
        from opt2skill.rl.distill_session import train as run_distilled

        from opt2skill.rl.distill_config import DistillConfig

        distill = DistillConfig(noise=distill_noise, finetune=finetune, pace=pace)
        distill.check()  # before anything is read or written
        result = run_distilled(request, distill_steps, progress=not quiet, distill=distill, announce=_say)
    else:
        result = run(request, progress=not quiet, announce=_say)
    from opt2skill.rl.processes import from_environment

    if not from_environment().is_main:  # under torchrun: rank 0 reports
        return
    if result.get("already_done"):
        console.print(f"{out}: already trained to {result['env_steps']} environment steps (iteration "
                      f"{result['iteration']}); raise --steps to train further", soft_wrap=True)
        return
    rows = [("distillation environment steps", f"{result['distill_env_steps']:,}")] if "distill_env_steps" in result else []
    rows += [("iterations", str(result["iteration"])), ("environment steps", f"{result['env_steps']:,}"),
            ("wall time", f"{result['elapsed'] / 60:.1f} min"),
            ("reward per step (Table I)", f"{result['reward/step']:.3f}")]
    if "episode/length_s" in result:
        rows.append(("mean episode length", f"{result['episode/length_s']:.2f} s"))
    rows += [(k.split("/", 1)[1], f"{v:.4f}") for k, v in result.items() if k.startswith("reward_terms/")]
    rows += [("env steps/s", f"{result['perf/env_steps_per_s']:.0f}"),
             ("learner samples/s", f"{result['perf/learner_samples_per_s']:.0f}"),
             ("checkpoint", result["checkpoint"])]
    console.print(figures_table(f"training {out} (last iteration)", rows))


@app.command()
def play(
    run: Path = typer.Argument(None, help="Run directory (opt2skill train --out); optional with --expert --dataset "
                               "or --pretrained NAME --dataset."),
    pretrained: str = typer.Option(None, "--pretrained", help="A policy shipped with opt2skill instead of a RUN "
                                   "(e.g. walk); needs --dataset."),
    n: int = typer.Option(4, "--n", help="References to roll out (the dataset's first N)."),
    randomize: bool = typer.Option(False, "--randomize", help="Keep Table II randomization on."),
    noise: bool = typer.Option(False, "--noise", help="Keep observation noise on."),
    seed: int = typer.Option(0, help="Seed of the rollouts."),
    expert: bool = typer.Option(False, "--expert", help="Roll out the optimizer's feedback expert instead of the policy."),
    dataset: Path = typer.Option(None, "--dataset", help="The references (default: the run's dataset)."),
) -> None:
    """Roll a run's policy (its best checkpoint if it kept one, else the newest), a shipped policy, or
    the optimizer's feedback expert out on a few references (deterministic actions, from frame 0)."""
    from opt2skill.errors import ConfigError

    if expert and pretrained is not None:
        raise ConfigError("--expert plays the optimizer's feedback law, not a --pretrained policy: give one of them")
    if expert:
        from opt2skill.expert.play import play_expert
        from opt2skill.rl.run import read_spec

        if dataset is None and run is None:
            raise ConfigError("play --expert needs --dataset DIR or a RUN whose dataset to use")
        result = play_expert(dataset or Path(read_spec(run).dataset), n=n, randomize=randomize, seed=seed)
        console.print(f"{dataset or run}: the optimizer's feedback expert (PD targets at 200 Hz)", soft_wrap=True)
        _print_rollouts(result.motions, result.errors)
        return
    if expert is False and pretrained is not None:
        from opt2skill.cli.eval import policy_run

        run, _ = policy_run(run, pretrained, dataset=dataset)
    if run is None:
        raise ConfigError("give a RUN directory, --pretrained NAME --dataset DIR, or --expert --dataset DIR")
    from opt2skill.rl.session import play as run_play

    result = run_play(run, n=n, randomize=randomize, noise=noise, seed=seed, dataset=dataset)
    console.print(f"{run}: checkpoint of iteration {result.policy.iteration} "
                  f"({result.policy.env_steps:,} environment steps)", soft_wrap=True)
    _print_rollouts(result.motions, result.errors)


def _print_rollouts(motions, errors) -> None:
    """Per reference the frames tracked, the mean reward terms, and the eval.metrics tracking errors."""
    table = figures_table("episodes", [], headers=("reference", "frames tracked / reference"))
    for m in motions:
        table.add_row(f"#{m.position} ({m.cause})", f"{m.steps + 1} / {m.reference_frames}")
    console.print(table)
    terms = motions[0].terms
    per_step = {k: np.mean([m.terms[k] / m.steps for m in motions]) for k in terms}
    rows = [("reward per step", f"{np.mean([m.reward / m.steps for m in motions]):.3f}")]
    rows += [(k, f"{v:.4f}") for k, v in per_step.items()]
    console.print(figures_table("reward terms, mean per step", rows, headers=("term", "value")))
    from opt2skill.eval.metrics import METRICS

    rows = []
    for name, (unit, _) in METRICS.items():
        values = [e[name] for e in errors if e[name] is not None and np.isfinite(e[name])]
        rows.append((f"{name} ({unit})", f"{np.mean(values):.3f}" if values else "-"))
    console.print(figures_table("tracking errors (eval.metrics), mean over references", rows, headers=("metric", "value")))
