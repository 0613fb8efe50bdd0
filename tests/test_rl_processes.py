"""Data-parallel PPO (`rl.processes`, `opt2skill train --procs N`): processes with worlds of their own
train one policy. Real processes (spawned, gloo), real MuJoCo, real rsl_rl updates."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from envs_support import shared_dataset

from opt2skill.rl import processes
from opt2skill.rl.processes import Group
from opt2skill.rl.run import read_progress, read_run

CLI = [str(Path(sys.executable).parent / "opt2skill")]


@pytest.fixture(scope="module")
def squats(tmp_path_factory) -> Path:
    return shared_dataset(tmp_path_factory, "squat", 3)


@pytest.fixture(scope="module")
def squats_with_gains(tmp_path_factory) -> Path:
    return shared_dataset(tmp_path_factory, "squat", 3, keep_gains=True)


def _flat(module: torch.nn.Module) -> np.ndarray:
    return torch.cat([t.detach().flatten().double() for t in module.state_dict().values()]).numpy()


def train_two_iterations(dataset: Path, out: Path) -> dict:
    """One process of the group: 4 worlds of its own, two PPO iterations; its networks before and
    after, its first observations and its counters, saved as OUT/rank<r>.npz."""
    from opt2skill.data.reader import Dataset
    from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
    from opt2skill.model import load_robot
    from opt2skill.rl.config import PPOConfig
    from opt2skill.rl.trainer import Schedule, Trainer

    group = processes.from_environment()
    torch.set_num_threads(1)
    robot, config = load_robot("digit"), tracking_config("squat")
    bank = ReferenceBank.from_dataset(robot, Dataset.open(dataset), config.observations.end_effectors, use_cache=False)
    with TrackingEnv(robot, bank, config, 4, seed=group.seed(0), threads=1) as env:
        trainer = Trainer(env, PPOConfig(), seed=0, group=group)
        first = trainer.venv.get_observations()["actor"].numpy().copy()
        before = np.r_[_flat(trainer.alg.actor), _flat(trainer.alg.critic)]
        trainer.warm_up_normalizers()
        figures = trainer.train(Schedule(total_steps=2 * trainer.batch), progress=False)
        after = np.r_[_flat(trainer.alg.actor), _flat(trainer.alg.critic)]
        np.savez(Path(out) / f"rank{group.rank}.npz", before=before, after=after, first=first,
                 env_steps=trainer.env_steps, local_batch=trainer.local_batch, episodes=figures.get("episode/count", 0))
    return figures


def test_two_processes_keep_one_policy_trained_on_both_processes_worlds(squats, tmp_path):
    figures = processes.launch(2, train_two_iterations, squats, tmp_path)
    ranks = [np.load(tmp_path / f"rank{r}.npz") for r in range(2)]
    # Rank 0's networks were broadcast: both started equal; gradients and normalizer statistics were
    # averaged: both end equal, bit for bit, and training moved them.
    assert np.array_equal(ranks[0]["before"], ranks[1]["before"])
    assert np.array_equal(ranks[0]["after"], ranks[1]["after"])
    assert np.abs(ranks[0]["after"] - ranks[0]["before"]).max() > 1e-3
    # Each process steps worlds of its own (another seed: other references, start frames, randomization).
    assert not np.allclose(ranks[0]["first"], ranks[1]["first"])
    # The counters are the group's: two iterations of both processes' worlds.
    for rank in ranks:
        assert int(rank["env_steps"]) == 2 * 2 * int(rank["local_batch"])
    # Figures combined over the group: throughput summed, so above either process's alone.
    assert figures["perf/env_steps_per_s"] > 0 and "reward/step" in figures


def _train(squats: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    args = [*CLI, "train", "--dataset", str(squats), "--out", str(out), "--num-envs", "4", "--quiet", *extra]
    return subprocess.run(args, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_train_with_two_processes_writes_one_run_and_resumes_it(squats, tmp_path):
    out = tmp_path / "run"
    # Two iterations of 2 processes x 4 worlds x 48 steps, then two more on a resume.
    first = _train(squats, out, "--steps", "768", "--procs", "2")
    assert first.returncode == 0, first.stderr[-2000:]
    assert read_run(out)["identity"]["processes"] == 2
    progress = read_progress(out)
    assert [p["env_steps"] for p in progress] == [384, 768]
    assert (out / "checkpoints").is_dir() and len(list((out / "checkpoints").glob("*.pt"))) >= 1
    again = _train(squats, out, "--steps", "1536", "--procs", "2")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "resuming" in again.stdout and "from iteration 2" in again.stdout
    assert [p["env_steps"] for p in read_progress(out)] == [384, 768, 1152, 1536]
    assert len(json.loads((out / "run.json").read_text())["invocations"]) == 2
    # Another number of processes is another configuration: refused, nothing written.
    before = (out / "run.json").read_text()
    other = _train(squats, out, "--steps", "2000", "--procs", "1")
    assert other.returncode == 2 and "processes: 2 -> -" in other.stderr, other.stderr
    assert (out / "run.json").read_text() == before


@pytest.mark.parametrize("extra, message", [
    (("--procs", "0"), "--procs must be in [1, 64]"),
    (("--procs", "65"), "--procs must be in [1, 64]"),
])
def test_bad_process_counts_are_one_error(squats, tmp_path, extra, message):
    result = _train(squats, tmp_path / "run", "--steps", "100", *extra)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert not (tmp_path / "run").exists()


def test_each_process_draws_its_own_seed_and_rank_zero_keeps_the_given_one():
    one, two = Group(0, 2), Group(1, 2)
    assert one.seed(7) == 7 and two.seed(7) != 7 and two.seed(7) == Group(1, 4).seed(7)
    assert processes.ONE.rsl_rl() is None and two.rsl_rl() == {"global_rank": 1, "local_rank": 0, "world_size": 2}


def test_combined_figures_sum_counts_and_rates_and_average_the_rest():
    assert processes.summed("terminations/height") and processes.summed("perf/env_steps_per_s")
    assert not processes.summed("reward/step") and not processes.summed("episode/length_s")


@pytest.mark.slow
def test_torchrun_starts_the_same_training_and_rank_zero_alone_reports(squats, tmp_path):
    torchrun = Path(sys.executable).parent / "torchrun"
    out = tmp_path / "run"
    result = subprocess.run([str(torchrun), "--standalone", "--nproc-per-node", "2", "-m", "opt2skill", "train", "--dataset",
                             str(squats), "--out", str(out), "--num-envs", "4", "--steps", "384", "--quiet"],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.count("(last iteration)") == 1
    assert read_run(out)["identity"]["processes"] == 2
    assert [p["env_steps"] for p in read_progress(out)] == [384]


def distill_two_iterations(dataset: Path, out: Path) -> None:
    """One process of the group: the feedback expert distilled into an actor on 4 worlds of its own for
    two iterations; the actor before and after saved as OUT/distill<r>.npz."""
    from opt2skill.data.reader import Dataset
    from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
    from opt2skill.model import load_robot
    from opt2skill.rl.distill import Distiller
    from opt2skill.rl.distill_config import DistillConfig, distillation_tracking_config
    from opt2skill.rl.distill_session import dataset_expert
    from opt2skill.rl.policy import build_actor

    group = processes.from_environment()
    torch.set_num_threads(1)
    robot, dataset = load_robot("digit"), Dataset.open(dataset)
    distill = DistillConfig()
    config = distillation_tracking_config(tracking_config("squat"), distill)
    bank = ReferenceBank.from_dataset(robot, dataset, config.observations.end_effectors, use_cache=False)
    with TrackingEnv(robot, bank, config, 4, seed=group.seed(0), threads=1) as env:
        torch.manual_seed(0 if group.is_main else 1)  # different initializations: the group must start from rank 0's
        actor = build_actor(distill.student_ppo(), env.actor_dim, env.critic_dim, env.nu)
        distiller = Distiller(env, dataset_expert(env, dataset, distill), actor, distill, seed=0, group=group)
        before = _flat(actor)
        figures = distiller.train(2, progress=False)
        np.savez(Path(out) / f"distill{group.rank}.npz", before=before, after=_flat(actor),
                 env_steps=distiller.env_steps, local_batch=distiller.local_batch, loss=figures["distill/loss"])


def test_two_processes_distil_the_expert_into_one_actor(squats_with_gains, tmp_path):
    processes.launch(2, distill_two_iterations, squats_with_gains, tmp_path)
    ranks = [np.load(tmp_path / f"distill{r}.npz") for r in range(2)]
    assert np.array_equal(ranks[0]["before"], ranks[1]["before"])  # rank 0's actor, although rank 1 drew another
    assert np.array_equal(ranks[0]["after"], ranks[1]["after"])  # averaged gradients and normalizer statistics
    assert np.abs(ranks[0]["after"] - ranks[0]["before"]).max() > 1e-3
    for rank in ranks:
        assert int(rank["env_steps"]) == 2 * 2 * int(rank["local_batch"])
        assert float(rank["loss"]) == float(ranks[0]["loss"])  # the group's mean loss on both


@pytest.mark.slow
def test_distilled_training_runs_both_stages_in_two_processes(squats_with_gains, tmp_path):
    out = tmp_path / "run"
    result = _train(squats_with_gains, out, "--init", "distill", "--distill-steps", "400", "--steps", "384",
                    "--procs", "2")
    assert result.returncode == 0, result.stderr[-2000:]
    assert read_run(out)["identity"]["processes"] == 2
    assert read_progress(out / "distill")[-1]["env_steps"] > 0
    assert [p["env_steps"] for p in read_progress(out)] == [384]
    assert result.stdout.count("(last iteration)") == 1


def fail_on_rank_one() -> None:
    from opt2skill.errors import DataError

    if processes.from_environment().rank == 1:
        raise DataError("rank 1 found a bad file")
    processes.from_environment().barrier()  # rank 0 waits in a collective: it must be stopped, not hang


def test_an_input_error_in_one_process_stops_the_group_and_is_raised_as_itself():
    from opt2skill.errors import DataError

    with pytest.raises(DataError, match="rank 1 found a bad file"):
        processes.launch(2, fail_on_rank_one)


@pytest.mark.slow
def test_sigterm_stops_every_process_at_an_iteration_end_with_a_checkpoint(squats, tmp_path):
    import signal
    import time

    from opt2skill.rl import checkpoint

    out = tmp_path / "run"
    args = [*CLI, "train", "--dataset", str(squats), "--out", str(out), "--num-envs", "4", "--quiet", "--steps",
            "10000000", "--procs", "2", "--checkpoint-every", "1000"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 300
    while len(read_progress(out)) < 3 and time.monotonic() < end and proc.poll() is None:
        time.sleep(0.2)
    children = [int(p) for p in subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                                                 text=True).stdout.split()]
    # The two training processes (multiprocessing's resource tracker, a child too, leaves on its own
    # once its pipe closes).
    group = [pid for pid in children if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
    assert len(group) == 2
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=300)
    assert proc.returncode == 130

    def alive(pid: int) -> bool:  # running (not a zombie)
        try:
            return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
        except FileNotFoundError:
            return False

    assert not [pid for pid in group if alive(pid)]  # no process of the group outlives the command
    # Rank 0 checkpointed the last whole iteration (no periodic one was due): nothing logged is lost.
    logged = read_progress(out)[-1]["iteration"]
    assert checkpoint.load(checkpoint.latest(out))["iteration"] == logged >= 3


def test_the_command_shortens_openmp_spinning_before_torch_loads():
    """libgomp reads GOMP_SPINCOUNT once, when torch loads: the command sets it before any of its
    modules can load torch, and leaves a user's own spin setting alone (benchmarks/shared_cores.py)."""
    code = "import os, sys, opt2skill.cli.app; print(os.environ.get('GOMP_SPINCOUNT'), 'torch' in sys.modules)"
    base = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}

    def run(**env) -> str:
        return subprocess.run([sys.executable, "-c", code], env=base | env, capture_output=True, text=True,
                              check=True, timeout=120).stdout.strip()

    assert run() == "10000 False"
    assert run(GOMP_SPINCOUNT="300000") == "300000 False"
    assert run(OMP_WAIT_POLICY="ACTIVE") == "None False"


def test_interrupts_held_in_a_block_take_effect_when_it_ends():
    """A SIGTERM inside the block reaches its handler after the block's last statement, once however
    often it came; the handler is restored; a block that raises drops the held signal."""
    import signal

    reached, previous = [], signal.getsignal(signal.SIGTERM)

    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with processes.interrupts_held():
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGTERM)
                reached.append("after the signals")
        assert reached == ["after the signals"]
        assert signal.getsignal(signal.SIGTERM) is handler
        with pytest.raises(ValueError):  # the block's own error, not the interrupt
            with processes.interrupts_held():
                os.kill(os.getpid(), signal.SIGTERM)
                raise ValueError("the block failed")
        assert signal.getsignal(signal.SIGTERM) is handler
    finally:
        signal.signal(signal.SIGTERM, previous)
