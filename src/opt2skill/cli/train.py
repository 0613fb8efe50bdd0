"""`opt2skill train | play`: train a tracking policy with PPO (resumable), roll a checkpoint out."""

from __future__ import annotations

import shlex
import signal
import sys
from pathlib import Path

import numpy as np
import typer

from opt2skill.cli.console import console, figures_table

app = typer.Typer()


def _terminate_as_interrupt() -> None:
    """SIGTERM ends training like Ctrl-C: the trainer checkpoints what it has before exiting."""

    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


@app.command()
def train(
    dataset: Path = typer.Option(..., "--dataset", help="Reference dataset directory (opt2skill generate)."),
    out: Path = typer.Option(..., "--out", help="Run directory; rerunning the same command resumes it."),
    steps: int = typer.Option(10_000_000, help="Environment steps to train for (all worlds together)."),
    num_envs: int = typer.Option(128, "--num-envs", help="Simulated worlds."),
    history: int = typer.Option(10, help="History length N (joint positions and actions, every 4 steps)."),
    ablation: str = typer.Option("pos_f_t", help="Reference force/torque inputs and rewards: pos, pos_f, pos_t, pos_f_t."),
    seed: int = typer.Option(0, help="Seed of everything random (episodes, randomization, noise, networks)."),
    threads: int = typer.Option(None, help="Physics and torch threads (default: every core)."),
    checkpoint_every: int = typer.Option(50, "--checkpoint-every", help="Iterations between checkpoints (also every 5 min)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Train a tracking policy on a dataset (PPO, rsl_rl); checkpoints, TensorBoard logs, resume."""
    from opt2skill.rl.session import TrainRequest
    from opt2skill.rl.session import train as run

    request = TrainRequest(dataset=dataset, out=out, steps=steps, num_envs=num_envs, history=history,
                           ablation=ablation, seed=seed, threads=threads, checkpoint_every=checkpoint_every,
                           command=shlex.join(["opt2skill", *sys.argv[1:]]))
    request.check()
    _terminate_as_interrupt()
    result = run(request, progress=not quiet)
    if result.get("already_done"):
        console.print(f"{out}: already trained to {result['env_steps']} environment steps (iteration "
                      f"{result['iteration']}); raise --steps to train further")
        return
    rows = [("iterations", str(result["iteration"])), ("environment steps", f"{result['env_steps']:,}"),
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
    run: Path = typer.Argument(..., help="Run directory (opt2skill train --out)."),
    n: int = typer.Option(4, "--n", help="References to roll out (the dataset's first N)."),
    randomize: bool = typer.Option(False, "--randomize", help="Keep Table II randomization on."),
    noise: bool = typer.Option(False, "--noise", help="Keep observation noise on."),
    seed: int = typer.Option(0, help="Seed of the rollouts."),
) -> None:
    """Roll the newest checkpoint out on a few references (deterministic actions, from frame 0)."""
    from opt2skill.rl.session import play as run_play

    result = run_play(run, n=n, randomize=randomize, noise=noise, seed=seed)
    console.print(f"{run}: checkpoint of iteration {result.policy.iteration} "
                  f"({result.policy.env_steps:,} environment steps)")
    table = figures_table("episodes", [], headers=("reference", "frames tracked / reference"))
    for m in result.motions:
        table.add_row(f"#{m.position} ({m.cause})", f"{m.steps + 1} / {m.reference_frames}")
    console.print(table)
    terms = result.motions[0].terms
    per_step = {k: np.mean([m.terms[k] / m.steps for m in result.motions]) for k in terms}
    rows = [("reward per step", f"{np.mean([m.reward / m.steps for m in result.motions]):.3f}")]
    rows += [(k, f"{v:.4f}") for k, v in per_step.items()]
    console.print(figures_table("reward terms, mean per step", rows, headers=("term", "value")))
    from opt2skill.eval.metrics import METRICS

    rows = []
    for name, (unit, _) in METRICS.items():
        values = [e[name] for e in result.errors if e[name] is not None and np.isfinite(e[name])]
        rows.append((f"{name} ({unit})", f"{np.mean(values):.3f}" if values else "-"))
    console.print(figures_table("tracking errors (eval.metrics), mean over references", rows, headers=("metric", "value")))
