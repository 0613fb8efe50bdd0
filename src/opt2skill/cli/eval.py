"""`opt2skill eval | compare | sweep | export | deploy-sim`: the paper's evaluation of a policy, its
terrain sweeps, its ONNX export and the standalone 2 kHz sim-to-sim player (docs/eval.md,
docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from opt2skill.cli.console import console
from opt2skill.errors import ConfigError
from opt2skill.folder_lock import folder_lock
from opt2skill.output_paths import check_output_dir, check_output_file

app = typer.Typer()

DATASET_HELP = "References (a dataset directory); default: the run's training dataset."
# Options several commands share.
SPLIT = typer.Option("held-out", help="held-out (references the policy did not train on), training, or all.")
INDICES = typer.Option(None, help="Comma-separated generation indices instead of a split.")
RANDOMIZE = typer.Option(False, "--randomize", help="Table II randomization on.")
NOISE = typer.Option(False, "--noise", help="Table II observation noise on.")
THREADS = typer.Option(None, help="Physics and torch threads (default: every core).")
QUIET = typer.Option(False, "--quiet", help="No progress bar.")
CHECKPOINT = typer.Option(None, help="A checkpoint file of the run (default: the newest); RUN/distill/checkpoints/ "
                          "holds the distilled actor of an --init distill run.")


PRETRAINED = typer.Option(None, "--pretrained", help="A policy shipped with opt2skill instead of a RUN (e.g. walk); "
                          "its files are checked against their shipped hashes.")


def policy_run(run: Path | None, pretrained: str | None, checkpoint: Path | None = None,
               dataset: Path | None = None, references: bool = True) -> tuple[Path, Path | None]:
    """The run directory to read (RUN, or the shipped policy's) and, for a shipped policy, the folder
    in the working directory its outputs go to by default (nothing is written into the package).
    `references`: the command rolls the policy out on references (`dataset`, which a shipped policy
    needs given)."""
    if (run is None) == (pretrained is None):
        raise ConfigError("give a RUN directory or --pretrained NAME (one of them)")
    if pretrained is None:
        return Path(run), None
    from opt2skill.pretrained import pretrained_run

    if checkpoint is not None:
        raise ConfigError("--checkpoint names a checkpoint of a RUN; a --pretrained policy has one")
    shipped = pretrained_run(pretrained)
    if references and dataset is None:
        raise ConfigError(f"--pretrained {pretrained} ships without its training references: give --dataset DIR "
                          f"(references of its task, e.g. opt2skill generate walk --seed 1 --out data/walk_test)")
    return shipped, Path(f"pretrained-{pretrained}")


def _indices(text: str | None) -> tuple[int, ...]:
    if not text:
        return ()
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--indices expects comma-separated generation indices, got '{text}'") from None


def metric_table(title: str, columns: list[str], rows: list[tuple[str, list[str]]], dim: tuple[int, ...] = ()) -> Table:
    """Metrics as rows, policies as columns: narrow enough for a terminal."""
    table = Table(title=title, title_justify="left")
    table.add_column("metric")
    for i, col in enumerate(columns):
        table.add_column(col, justify="right", style="dim" if i in dim else None)
    for name, values in rows:
        table.add_row(name, *values)
    return table


def print_report(report, paths=()) -> None:
    """The report's figures on screen (the Markdown file has them in the paper's layout)."""
    from opt2skill.eval.report import PAPER_ROWS, TABLE_III, TABLE_IV, header, mean_se

    console.print(f"[bold]{report.title()}[/]: {report.policy.get('description', '')}")
    console.print(f"references: {report.references['note']}")
    s = report.summary()
    rows = [(header(m), [mean_se(s[m]), *(mean_se(v.get(m)) for v in PAPER_ROWS.values())]) for m in (*TABLE_III, *TABLE_IV)]
    extra = report.extra_rows()[0]
    rows += [("success (falls counted)", [extra[-2], *("-" for _ in PAPER_ROWS)]),
             ("mean episode length", [extra[-1], *("-" for _ in PAPER_ROWS)])]
    console.print(metric_table("mean ± SE over references (dim: the paper's Table III, a reference line only)",
                               [report.title(), *PAPER_ROWS], rows, dim=tuple(range(1, 1 + len(PAPER_ROWS)))))
    for p in paths:
        console.print(f"wrote {p}")


@app.command("eval")
def eval_command(
    run: Path = typer.Argument(None, help="Run directory (opt2skill train --out); or --pretrained NAME."),
    pretrained: str = PRETRAINED,
    dataset: Path = typer.Option(None, "--dataset", help=DATASET_HELP),
    n: int = typer.Option(20, "--n", help="References to evaluate on (the first N of the split)."),
    split: str = SPLIT,
    indices: str = INDICES,
    randomize: bool = RANDOMIZE,
    noise: bool = NOISE,
    pushes: bool = typer.Option(False, "--pushes", help="The training's pushes on (the paper's external "
                                "disturbances, not in Table II): every 2 to 6 s a base velocity change of up to "
                                "0.3 m/s in a random horizontal direction."),
    seed: int = typer.Option(0, help="Seed of the rollouts (randomization, noise, pushes)."),
    checkpoint: Path = CHECKPOINT,
    plots: int = typer.Option(3, help="Reference-against-tracked pages (PNG) for the first K references."),
    out: Path = typer.Option(None, help="Output directory (default: RUN/eval/<dataset>-<split>...)."),
    threads: int = THREADS,
    quiet: bool = QUIET,
) -> None:
    """Roll the policy out on held-out references; every metric of Tables III and IV, mean ± SE."""
    from opt2skill.rl.run import read_spec

    if plots < 0:
        raise ConfigError(f"--plots must be >= 0, got {plots}")
    run, elsewhere = policy_run(run, pretrained, checkpoint, dataset)
    spec = read_spec(run)  # a clear error for a directory that is not a run, before the slow imports
    from opt2skill.eval.evaluate import EvalRequest, evaluate, load_run_policy
    from opt2skill.eval.plots import plot_tracking

    request = EvalRequest(run=run, dataset=dataset, n=n, split=split, indices=_indices(indices), randomize=randomize,
                          noise=noise, pushes=pushes, seed=seed, checkpoint=checkpoint, threads=threads)
    default = request.default_out(spec)
    out = check_output_dir(out or (elsewhere / "eval" / default.name if elsewhere else default))
    policy = load_run_policy(run, checkpoint)  # the checkpoint checked before anything is written
    with folder_lock(out):
        report, rollouts = evaluate(request, progress=not quiet, run=policy)
        paths = list(report.write(out))
        from opt2skill.robots import find_robot_config

        config = find_robot_config(report.policy.get("robot", "digit")) if rollouts else None
        for r, result in list(zip(rollouts or [], report.results))[:plots]:
            paths.append(plot_tracking(r.reference, r.tracked, Path(out) / "plots" / f"track_{result.index:06d}.png",
                                       title=f"{report.title()}, reference #{result.index} ({result.cause})",
                                       robot_config=config))
    print_report(report, paths)


@app.command()
def export(
    run: Path = typer.Argument(None, help="Run directory (opt2skill train --out); or --pretrained NAME."),
    out: Path = typer.Option(..., "--out", help="ONNX file to write (e.g. policy.onnx)."),
    checkpoint: Path = CHECKPOINT,
    pretrained: str = PRETRAINED,
) -> None:
    """Write the actor as ONNX (normalization folded in) with the metadata a robot-side program needs."""
    check_output_file(out, suffix=".onnx")  # before the slow imports
    from opt2skill.deploy.export import export_policy

    run, _ = policy_run(run, pretrained, checkpoint, references=False)

    path, meta = export_policy(run, out, checkpoint)
    h = meta.history
    console.print(f"wrote {path}: {meta.obs_dim} observations ({len(meta.terms)} terms, history {h['samples']} x "
                  f"every {h['stride']} steps) -> {meta.nu} actions at {1 / meta.control['policy_dt']:.0f} Hz; "
                  f"run {meta.training['run']}, iteration {meta.training['iteration']}")


@app.command("deploy-sim")
def deploy_sim(
    policy: Path = typer.Argument(None, help="An exported policy (opt2skill export); or --pretrained NAME."),
    pretrained: str = PRETRAINED,
    dataset: Path = typer.Option(..., "--dataset", help="References (a dataset directory)."),
    n: int = typer.Option(20, "--n", help="References to play (the first N of the split)."),
    split: str = SPLIT,
    indices: str = INDICES,
    physics_dt: float = typer.Option(0.0005, "--physics-dt", help="Physics and PD period, s (0.0005: 2 kHz)."),
    latency: float = typer.Option(0.0, help="Extra latency from sensor reading to applied targets, s."),
    noise: float = typer.Option(0.0, help="Sensor noise as a factor of the training's Table II deviations."),
    seed: int = typer.Option(0, help="Seed of the sensor noise."),
    out: Path = typer.Option(None, help="Output directory (default: next to the ONNX file)."),
    quiet: bool = QUIET,
) -> None:
    """Play an exported policy in a standalone 2 kHz MuJoCo loop; the same metrics as eval."""
    from opt2skill.deploy.player import PlayerConfig
    from opt2skill.deploy.sim_to_sim import deploy_sim as run_player

    config = PlayerConfig(physics_dt=physics_dt, latency=latency, noise=noise, seed=seed)
    if (policy is None) == (pretrained is None):
        raise ConfigError("give an exported POLICY file or --pretrained NAME (one of them)")
    if pretrained is not None:
        from opt2skill.pretrained import pretrained_onnx

        policy = pretrained_onnx(pretrained)
        out = out or Path(f"pretrained-{pretrained}") / f"deploy-sim-{dataset.name}"
    out = check_output_dir(out or policy.with_suffix("").parent / f"{policy.stem}-deploy-sim-{dataset.name}")
    with folder_lock(out):
        report, _ = run_player(policy, dataset, n=n, split=split, indices=_indices(indices), config=config,
                               progress=not quiet)
        paths = report.write(out)
    print_report(report, paths)


@app.command()
def compare(
    runs: list[Path] = typer.Argument(..., help="Two or more run directories; the first is the baseline."),
    dataset: Path = typer.Option(None, "--dataset", help="References; default: the first run's training dataset."),
    n: int = typer.Option(20, "--n", help="References (the first N held out from every run)."),
    split: str = SPLIT,
    indices: str = INDICES,
    randomize: bool = RANDOMIZE,
    noise: bool = NOISE,
    seed: int = typer.Option(0, help="Seed of the rollouts."),
    out: Path = typer.Option(None, help="Output directory (default: FIRST_RUN/eval/compare)."),
    threads: int = THREADS,
    quiet: bool = QUIET,
) -> None:
    """Several runs on the same references, side by side, with Wilcoxon signed-rank p-values."""
    from opt2skill.eval.compare import compare as run_compare
    from opt2skill.eval.report import TABLE_III, TABLE_IV, header, label

    out = check_output_dir(out or Path(runs[0]) / "eval" / "compare")
    with folder_lock(out):
        result = run_compare(runs, dataset=dataset, n=n, split=split, indices=_indices(indices), randomize=randomize,
                             noise=noise, seed=seed, threads=threads, progress=not quiet)
        written = result.write(out)
    console.print(f"references: {result.references.note}")
    metrics = (*TABLE_III, *TABLE_IV)
    table_rows = result.rows()
    columns = [row[0] for row in table_rows]
    rows = [(header(m), [row[1 + i] for row in table_rows]) for i, m in enumerate(metrics)]
    rows.append(("success (falls counted)", [row[-1] for row in table_rows]))
    console.print(metric_table("mean ± SE over the same references (dim: the paper's Table III)", columns, rows,
                               dim=tuple(range(len(result.reports), len(columns)))))
    p_rows = result.p_rows()
    console.print(metric_table("Wilcoxon signed-rank p-values (two-sided, paired by reference)", [r[0] for r in p_rows],
                               [(label(m), [r[1 + i] for r in p_rows]) for i, m in enumerate(metrics)]))
    for path in written:
        console.print(f"wrote {path}")


@app.command()
def sweep(
    run: Path = typer.Argument(None, help="Run directory (opt2skill train --out); or --pretrained NAME."),
    pretrained: str = PRETRAINED,
    terrain: str = typer.Option(..., "--terrain", help="stairs (step heights) or slope (angles)."),
    step: float = typer.Option(None, help="Grid step: m of step height (default 0.02) or degrees (default 2.5)."),
    maximum: float = typer.Option(None, "--max", help="Largest setting: m (default 0.16) or degrees (default 20)."),
    values: str = typer.Option(None, help="Comma-separated settings instead of a grid (m or degrees)."),
    trials: int = typer.Option(10, help="Trials per setting (initial yaw uniform in +-yaw-range)."),
    yaw_range: float = typer.Option(25.0, "--yaw-range", help="Initial yaw range, degrees."),
    dataset: Path = typer.Option(None, "--dataset", help="Where the reference comes from; default: the run's dataset."),
    index: int = typer.Option(None, help="Generation index of the reference (default: held out, near 1 m/s)."),
    start: float = typer.Option(1.0, help="Distance from the start position to the terrain, m (along +x)."),
    step_length: float = typer.Option(0.3, "--step-length", help="Stair tread, m."),
    n_steps: int = typer.Option(10, "--n-steps", help="Stairs before the landing."),
    tolerance: float = typer.Option(0.1, help="Share of the reference distance the robot may fall short by."),
    seed: int = typer.Option(0, help="Seed of the yaws."),
    video: bool = typer.Option(False, "--video", help="Also render the first trial of the hardest setting."),
    checkpoint: Path = CHECKPOINT,
    out: Path = typer.Option(None, help="Output directory (default: RUN/eval/sweep-<terrain>)."),
    threads: int = THREADS,
    quiet: bool = QUIET,
) -> None:
    """Success rate on stairs or slopes of growing difficulty (the paper's Fig. 3): table and plot."""
    from opt2skill.eval.sweep import SweepSettings, check_reaches_terrain, default_values, sweep_reference

    if values:
        try:
            grid = tuple(float(v) for v in values.split(","))
        except ValueError:
            raise ConfigError(f"--values expects comma-separated numbers, got '{values}'") from None
    else:
        grid = default_values(terrain, step, maximum)
    settings = SweepSettings(terrain=terrain, values=grid, trials=trials, yaw_range=yaw_range, start=start,
                             step_length=step_length, n_steps=n_steps, tolerance=tolerance, seed=seed)
    settings.check()
    from opt2skill.data.reader import Dataset
    from opt2skill.eval.evaluate import load_run_policy

    run, elsewhere = policy_run(run, pretrained, checkpoint, dataset)
    out = check_output_dir(out or (elsewhere or Path(run)) / "eval" / f"sweep-{terrain}")
    source = load_run_policy(run, checkpoint)
    ds = Dataset.open(dataset or source.spec.dataset)
    reference, info = sweep_reference(ds, source, run, index)
    check_reaches_terrain(reference, settings, info["description"])  # before the slow part
    console.print(f"reference: {info['description']}", highlight=False, soft_wrap=True)
    with folder_lock(out):
        _run_sweep(source, reference, info, settings, out, video, threads, quiet)


def _run_sweep(source, reference, info, settings, out: Path, video: bool, threads, quiet: bool) -> None:
    """The sweep's trials, then its outputs in `out` (held locked)."""
    from opt2skill.eval.sweep import run_sweep, write_sweep

    terrain, trials, yaw_range = settings.terrain, settings.trials, settings.yaw_range
    result, rollouts = run_sweep(source, reference, info, settings, threads=threads, progress=not quiet)
    written = []
    if video:
        from opt2skill.eval.render import render_video

        hardest = settings.values[-1]
        trial = rollouts[hardest][0]
        written.append(render_video(source.robot, trial.tracked.qpos, out / "sweep.mp4", ghost_qpos=trial.reference.qpos,
                                    terrain=result.terrains[hardest]))
    written = [*write_sweep(result, out, source.info["name"]), *written]
    table = Table(title=f"{terrain} sweep: success rate ({trials} trials, yaw in +-{yaw_range:g} deg)", title_justify="left")
    for col in ("setting", "success", "falls", "mean progress"):
        table.add_column(col, justify="right")
    for row in result.rows():
        table.add_row(*row)
    console.print(table)
    for path in written:
        console.print(f"wrote {path}")
