"""`opt2skill experiment table3` (Table III, Fig. 3, the history ablation) and `table4` (Table IV, Fig. 4, the
desk-height transfer), each one resumable command; `table3-pool` pools Table III over replicates."""

from __future__ import annotations

from pathlib import Path

import typer

from opt2skill.errors import ConfigError

app = typer.Typer(help="The paper's experiments, each one resumable command (docs/experiments.md).", no_args_is_help=True)


def _numbers(text: str | None, option: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"{option} expects comma-separated numbers, got '{text}'") from None


def _range(text: str | None, option: str) -> tuple[float, float] | None:
    values = _numbers(text.replace(":", ",") if text else None, option)
    if values is not None and len(values) != 2:
        raise ConfigError(f"{option} expects lo:hi, got '{text}'")
    return values


@app.command()
def table3(
    setting: str = typer.Option("quick", help="quick (minutes, a smoke run) or full (the paper's scale)."),
    out: Path = typer.Option(Path("experiments/table3"), help="Output folder (rerun the same command to resume)."),
    n_train: int = typer.Option(None, "--n-train", help="Training references per source."),
    n_test: int = typer.Option(None, "--n-test", help="Held-out references per source (another seed)."),
    duration: float = typer.Option(None, help="Seconds of each TO and IK walk (full: 14, as the paper)."),
    human_duration: float = typer.Option(None, "--human-duration", help="Seconds of each constructed human clip."),
    speed: str = typer.Option(None, help="Matched speed range lo:hi, m/s."),
    clearance: str = typer.Option(None, help="Matched clearance range lo:hi, m."),
    train_steps: int = typer.Option(None, "--train-steps", help="Environment steps per policy (the same for all)."),
    num_envs: int = typer.Option(None, "--num-envs", help="Simulated worlds while training."),
    histories: str = typer.Option(None, help="History lengths of the ablation rows, e.g. 0,5,10,15."),
    history: int = typer.Option(None, help="History length of the data rows (TO, IK, human; the paper's 10); one of "
                                "--histories."),
    stairs: str = typer.Option(None, help="Stair heights of the sweep, m, e.g. 0,0.04,0.08."),
    slopes: str = typer.Option(None, help="Slope angles of the sweep, degrees, e.g. 0,10,20."),
    sweep_trials: int = typer.Option(None, "--sweep-trials", help="Trials per terrain setting (yaw in +-25 deg)."),
    sweep_start: float = typer.Option(None, "--sweep-start", help="Distance to the terrain, m."),
    human: Path = typer.Option(None, "--human", help="Folder of AMASS .npz / BVH walking clips (default: constructed "
                               "clips); the last --n-test files are held out."),
    to_ablation: str = typer.Option(None, "--to-ablation", help="The TO policies' inputs (pos, pos_f, pos_t, pos_f_t)."),
    seed: int = typer.Option(None, help="Seed of the training references and training; held-out references use seed + 1."),
    train_seed: int = typer.Option(None, "--train-seed", help="Every policy's training seed instead of --seed: a "
                                   "replicate of an experiment on the same references (copy its data/ into --out)."),
    device: str = typer.Option(None, help="Training physics: cpu (C MuJoCo) or cuda (MuJoCo Warp on a GPU)."),
    mixed_precision: bool = typer.Option(False, "--mixed-precision", help="bf16 autocast in every policy's PPO update "
                                         "(train --mixed-precision; part of the experiment's settings)."),
    base_position: str = typer.Option(None, "--base-position", help="Every policy's base-position reward: task, on "
                                      "or off (train --base-position; part of the experiment's settings)."),
    noise_min: float = typer.Option(None, "--noise-min", help="Each world's least share of Table II's observation "
                                    "noise, in [0, 1] (train --noise-min; 1, the paper, by default)."),
    reward: list[str] = typer.Option(None, "--reward", help="A reward term's weight and kernel scale changed from "
                                     "Table I for every policy, NAME=WEIGHT[:SCALE] (repeatable; train --reward; "
                                     "e.g. base_lin_vel=0.3:8; part of the experiment's settings)."),
    workers: int = typer.Option(None, min=0, help="Generation processes, and policies trained at once on a CPU (0: every core)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bars."),
) -> None:
    """Table III (TO, IK, human; history 0/5/10/15) and Fig. 3 (stairs, slopes), resumable."""
    from opt2skill.envs.config import parse_reward
    from opt2skill.experiment.settings import resolve
    from opt2skill.experiment.table3 import run_table3
    from opt2skill.rl.processes import terminate_as_interrupt

    hist = _numbers(histories, "--histories")
    settings = resolve(setting, dict(
        n_train=n_train, n_test=n_test, duration=duration, human_duration=human_duration,
        speed=_range(speed, "--speed"), clearance=_range(clearance, "--clearance"), train_steps=train_steps,
        num_envs=num_envs, histories=tuple(int(h) for h in hist) if hist is not None else None, history=history,
        stairs=_numbers(stairs, "--stairs"), slopes=_numbers(slopes, "--slopes"), sweep_trials=sweep_trials,
        sweep_start=sweep_start, human=str(human) if human is not None else None, to_ablation=to_ablation, seed=seed,
        train_seed=train_seed, workers=workers, device=device, mixed_precision=mixed_precision or None,
        base_position=base_position, noise_min=noise_min, rewards=tuple(parse_reward(text) for text in reward) if reward else None))
    terminate_as_interrupt()  # a kill checkpoints the trainings in flight; the same command resumes
    run_table3(settings, out, progress=not quiet)


@app.command("table3-pool")
def table3_pool(
    folders: list[Path] = typer.Argument(..., help="Table III experiment folders that differ only in --train-seed (and --histories: "
                                                         "the history rows all of them trained are pooled)."),
    out: Path = typer.Option(Path("experiments/table3-pooled"), help="Folder of the pooled tables."),
) -> None:
    """Table III pooled over replicates (experiments differing only in their training seed and history rows)."""
    from opt2skill.experiment.pool import pool_table3

    pool_table3(list(folders), out)


def _timing(text: str | None) -> dict[str, float] | None:
    """'task' (the wipe's own phases) or 'phase=seconds,...'."""
    if text is None:
        return None
    if text.strip() == "task":
        return {}
    timing = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = item.partition("=")
        try:
            timing[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            raise ConfigError(f"--timing expects 'task' or phase=seconds,... (e.g. stroke=0.5,reach=0.5), got '{text}'")
    return timing


@app.command()
def table4(
    setting: str = typer.Option("quick", help="quick (minutes, a smoke run) or full (the paper's scale)."),
    out: Path = typer.Option(Path("experiments/table4"), help="Output folder (rerun the same command to resume)."),
    n_train: int = typer.Option(None, "--n-train", help="Training references (force and desk height sampled)."),
    n_test: int = typer.Option(None, "--n-test", help="Held-out references per force level (another seed)."),
    forces: str = typer.Option(None, help="Reference force levels of the evaluation, N, e.g. 0,5,10,15,20,25."),
    train_force: str = typer.Option(None, "--train-force", help="Training references' force range lo:hi, N."),
    desk_height: str = typer.Option(None, "--desk-height", help="Desk top range lo:hi of every reference, m."),
    ablations: str = typer.Option(None, help="Policies, e.g. pos,pos_f,pos_t,pos_f_t (pos_f_t required)."),
    train_steps: int = typer.Option(None, "--train-steps", help="Environment steps per policy (the same for all)."),
    distill_steps: int = typer.Option(None, "--distill-steps", help="Environment steps distilling the optimizer's "
                                      "feedback expert into each policy before its PPO steps (0: PPO from scratch, "
                                      "the paper's way; train --init distill)."),
    num_envs: int = typer.Option(None, "--num-envs", help="Simulated worlds while training."),
    history: int = typer.Option(None, help="Observation history length of every policy."),
    transfer_force: float = typer.Option(None, "--transfer-force", help="Force of the transfer test's reference, N."),
    transfer_height: float = typer.Option(None, "--transfer-height", help="Desk top of the transfer reference, m."),
    transfer_desks: str = typer.Option(None, "--transfer-desks", help="Desk tops it is tracked at, m, e.g. 0.9,1.0 "
                                       "('' for no transfer test)."),
    n_transfer: int = typer.Option(None, "--n-transfer", help="References of the transfer test."),
    timing: str = typer.Option(None, help="Wipe phase durations, s: 'task' (the task's own) or e.g. stroke=0.5,reach=0.5."),
    seed: int = typer.Option(None, help="Seed of the training references and training; held-out references use seed + 1."),
    device: str = typer.Option(None, help="Training physics: cpu (C MuJoCo) or cuda (MuJoCo Warp on a GPU)."),
    mixed_precision: bool = typer.Option(False, "--mixed-precision", help="bf16 autocast in every policy's PPO update "
                                         "(train --mixed-precision; part of the experiment's settings)."),
    workers: int = typer.Option(None, min=0, help="Generation processes, and policies trained at once on a CPU (0: every core)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bars."),
) -> None:
    """Table IV (Pos, Pos+F, Pos+T, Pos+F+T at six force levels), Fig. 4 and the desk-height transfer, resumable."""
    from opt2skill.experiment.settings import resolve
    from opt2skill.experiment.table4 import run_table4
    from opt2skill.rl.processes import terminate_as_interrupt
    from opt2skill.experiment.table4_settings import Table4Settings

    names = tuple(a.strip() for a in ablations.split(",") if a.strip()) if ablations is not None else None
    settings = resolve(setting, dict(
        n_train=n_train, n_test=n_test, forces=_numbers(forces, "--forces"), train_force=_range(train_force, "--train-force"),
        desk_height=_range(desk_height, "--desk-height"), ablations=names, train_steps=train_steps,
        distill_steps=distill_steps, num_envs=num_envs,
        history=history, transfer_force=transfer_force, transfer_height=transfer_height,
        transfer_desks=_numbers(transfer_desks, "--transfer-desks"), n_transfer=n_transfer, timing=_timing(timing),
        seed=seed, device=device, workers=workers, mixed_precision=mixed_precision or None), kind=Table4Settings)
    terminate_as_interrupt()
    run_table4(settings, out, progress=not quiet)
