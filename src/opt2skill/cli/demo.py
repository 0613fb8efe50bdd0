"""`opt2skill demo` (`make demo`): the whole pipeline at a small, fast setting, for real.

1. generate a few walking references for training and a few more, with another seed, held out;
2. train a tracking policy briefly: distil the optimizer's feedback expert into the actor, then PPO
   (`opt2skill train --init distill`; docs/distill.md has the benchmark that chose it over plain
   PPO), or plain PPO with `--init scratch`;
3. evaluate it on the held-out references (Tables III and IV, with the paper's row beside it);
4. export it to ONNX and play it in the standalone 2 kHz player (the sim-to-sim gap as numbers);
5. render one rollout with its reference as a ghost;
then print where each output is. Every step resumes: rerunning the command skips the references and
training already done. The settings are the demo's, not the paper's: a few references and minutes
of training are not the paper's hours (the README gives the full-scale commands).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from opt2skill.cli.console import console, figures_table
from opt2skill.errors import ConfigError, DataError



@dataclass(frozen=True)
class DemoSettings:
    out: Path = Path("demo")
    robot: str = "digit"
    task: str = "walk"
    n_train: int = 3
    n_test: int = 2
    train_steps: int = 30_000  # PPO environment steps, all worlds together (20 iterations of 32 worlds)
    init: str = "distill"  # distill: the feedback expert distilled first (references keep their gains); scratch
    distill_steps: int = 60_000  # environment steps of distillation (init "distill")
    num_envs: int = 32
    workers: int = 0  # generation processes (0: every core)
    fps: int = 20
    seed: int = 0
    ranges: dict = field(default_factory=dict)

    def check(self) -> None:
        if self.n_train < 1 or self.n_test < 1:
            raise ConfigError(f"--n-train and --n-test must be >= 1, got {self.n_train} and {self.n_test}")
        if self.train_steps < 1 or self.num_envs < 1 or self.distill_steps < 1:
            raise ConfigError("--train-steps, --distill-steps and --num-envs must be >= 1")
        if self.init not in ("distill", "scratch"):
            raise ConfigError(f"--init must be 'distill' or 'scratch', got '{self.init}'")


def run_demo(s: DemoSettings) -> dict[str, Path]:
    s.check()
    os.environ["OMP_NUM_THREADS"] = "1"
    from opt2skill.deploy.export import export_policy
    from opt2skill.deploy.player import PlayerConfig
    from opt2skill.deploy.sim_to_sim import deploy_sim
    from opt2skill.eval.evaluate import EvalRequest, evaluate
    from opt2skill.eval.plots import plot_tracking
    from opt2skill.eval.render import render_video
    from opt2skill.rl import distill_session, session
    from opt2skill.trajopt.generate import GenerateRequest, generate

    out = Path(s.out)
    data = out / "data"
    train_dir, test_dir, run = data / f"{s.task}_train", data / f"{s.task}_test", out / "run"
    from opt2skill.tasks import task_info

    ranges = s.ranges or task_info(s.task).demo_ranges  # the task's own small, reliable setting
    starts: list[tuple[str, float]] = []

    def stage(name: str):
        console.rule(f"[bold]{name}")
        starts.append((name, time.perf_counter()))

    stage("1. references (trajectory optimization)")
    for directory, n, seed in ((train_dir, s.n_train, s.seed), (test_dir, s.n_test, s.seed + 1)):
        summary = generate(GenerateRequest(task=s.task, n=n, seed=seed, out=directory, robot=s.robot, workers=s.workers,
                                           ranges=ranges, keep_gains=s.init == "distill", command="opt2skill demo"))
        console.print(f"{directory}: {summary['counts']['accepted']} of {n} accepted")
    request = session.TrainRequest(dataset=train_dir, out=run, steps=s.train_steps, num_envs=s.num_envs, seed=s.seed,
                                   command="opt2skill demo")
    if s.init == "distill":
        stage("2. training (distillation of the optimizer's feedback expert, then PPO)")
        result = distill_session.train(request, s.distill_steps)
        console.print(f"{run}: {result.get('distill_env_steps', 0):,} environment steps of distillation, then "
                      f"PPO iteration {result['iteration']}, {result['env_steps']:,} environment steps")
    else:
        stage("2. training (PPO)")
        result = session.train(request)
        console.print(f"{run}: iteration {result['iteration']}, {result['env_steps']:,} environment steps")

    stage("3. evaluation on held-out references")
    request = EvalRequest(run=run, dataset=test_dir, n=s.n_test)
    try:
        report, rollouts = evaluate(request)
    except DataError as exc:  # every held-out reference was rejected by validation: say so, use the training ones
        console.print(f"[yellow]{exc}; evaluating on the training references instead[/]")
        request = EvalRequest(run=run, dataset=train_dir, n=s.n_test, split="training")
        report, rollouts = evaluate(request)
    from opt2skill.cli.eval import print_report
    from opt2skill.robots import find_robot_config

    eval_dir = request.default_out(_spec(run))
    paths = list(report.write(eval_dir))
    first = report.results[0]
    plot = plot_tracking(rollouts[0].reference, rollouts[0].tracked, eval_dir / "plots" / f"track_{first.index:06d}.png",
                         title=f"{report.title()}, reference #{first.index}", robot_config=find_robot_config(s.robot))
    print_report(report, [*paths, plot])
    shipped_paths = _evaluate_shipped(s.task, request, out / f"pretrained-{s.task}")

    stage("4. export (ONNX) and the standalone 2 kHz player")
    onnx_path, _ = export_policy(run, out / "policy.onnx")
    console.print(f"wrote {onnx_path}")
    player, _ = deploy_sim(onnx_path, Path(request.dataset), n=request.n, split=request.split, config=PlayerConfig())
    player_paths = player.write(out / "deploy-sim")
    print_report(player, player_paths)

    stage("5. video")
    video = render_video(_spec_robot(run), rollouts[0].tracked.qpos, out / "video.mp4",
                         ghost_qpos=rollouts[0].reference.qpos, fps=s.fps)
    console.print(f"wrote {video}: reference #{first.index} tracked by the policy, the reference as a ghost")

    outputs = {"training references": train_dir, "held-out references": test_dir, "run (checkpoints, logs)": run,
               "evaluation table": paths[1], "tracking plot": plot, "ONNX policy": onnx_path,
               "sim-to-sim table": player_paths[1], "video": video}
    if shipped_paths:
        outputs[f"shipped '{s.task}' policy on the same references"] = shipped_paths[1]
    ends = [t for _, t in starts[1:]] + [time.perf_counter()]
    console.rule("[bold]done")
    console.print(figures_table("time per stage", [(name, f"{end - t:.0f} s") for (name, t), end in zip(starts, ends)],
                                headers=("stage", "wall time")))
    for what, where in outputs.items():  # plain lines: a table would cut long paths
        console.print(f"{what}: {where}", soft_wrap=True)
    return outputs


def _evaluate_shipped(task: str, request, out: Path, root: Path | None = None) -> list[Path]:
    """The policy shipped for `task` (`opt2skill.pretrained`), if any, on the demo's held-out references,
    beside the demo's own few-minute policy: what hours of training give. Its report's paths."""
    import dataclasses

    from opt2skill.cli.eval import print_report
    from opt2skill.eval.evaluate import evaluate
    from opt2skill.pretrained import ROOT, names, pretrained_run

    root = root or ROOT
    if task not in names(root):
        return []
    shipped = dataclasses.replace(request, run=pretrained_run(task, root), checkpoint=None)
    console.print(f"[bold]the policy shipped with opt2skill for '{task}' (opt2skill eval --pretrained {task}), "
                  "on the same references:", soft_wrap=True)
    try:
        report, _ = evaluate(shipped)
    except DataError as exc:  # e.g. the demo fell back to its training references, which the shipped one never saw
        console.print(f"[yellow]not evaluated: {exc}[/]", soft_wrap=True)
        return []
    paths = list(report.write(out))
    print_report(report, paths)
    return paths


def _spec(run: Path):
    from opt2skill.rl.run import read_spec

    return read_spec(run)


def _spec_robot(run: Path):
    from opt2skill.model import load_robot

    return load_robot(_spec(run).robot)
