"""Bad input and concurrent writers, through the command line (in this process, to stay fast): every
case exits with status 2 and one line naming the problem before any work, and leaves what was
already written byte for byte as it was (checksums before and after).

Real data: the shared three-squat dataset and a run trained on it for two iterations (eval_support).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import onnx
import pytest
import torch
from envs_support import shared_dataset
from eval_support import gliding, shared_run, write_dataset

from opt2skill.cli.app import main
from opt2skill.cli.option_help import limit_help, set_help
from opt2skill.data.reader import Dataset
from opt2skill.data.trajfile import read_trajectory, write_trajectory
from opt2skill.deploy.export import export_policy
from opt2skill.errors import DataError, DataWarning
from opt2skill.folder_lock import LOCK_FILE, folder_lock
from opt2skill.rl import checkpoint
from opt2skill.rl.distill_session import train as train_distilled
from opt2skill.rl.run import read_progress
from opt2skill.rl.session import TrainRequest

TRAIN = ("--num-envs", "4", "--checkpoint-every", "1", "--threads", "1", "--quiet")
STEP = 4 * 48  # environment steps of one iteration with 4 worlds


@pytest.fixture(scope="module")
def run_and_data(tmp_path_factory):
    return shared_run(tmp_path_factory)


@pytest.fixture
def data(run_and_data, tmp_path) -> Path:
    """A private copy of the three-squat dataset, to damage."""
    copy = tmp_path / "squat3"
    shutil.copytree(run_and_data[1], copy, ignore=shutil.ignore_patterns("cache", ".lock"))
    return copy


@pytest.fixture
def run(run_and_data, tmp_path) -> Path:
    """A private copy of the trained run (two iterations)."""
    copy = tmp_path / "run"
    shutil.copytree(run_and_data[0], copy, ignore=shutil.ignore_patterns("eval", ".lock"))
    return copy


def checksums(root: Path) -> dict[str, str]:
    """Every file's SHA-256 (the writers' lock files aside)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(root).rglob("*")) if p.is_file() and p.name != LOCK_FILE}


@dataclasses.dataclass
class Result:
    code: int
    out: str
    err: str


def cli(capsys, *args) -> Result:
    """`opt2skill ARGS` in this process (the entry point itself: its exit status and output). What
    a command sets for its process (torch threads, the SIGTERM handler) is restored for the next test."""
    capsys.readouterr()
    argv, threads, on_term = sys.argv, torch.get_num_threads(), signal.getsignal(signal.SIGTERM)
    sys.argv = ["opt2skill", *map(str, args)]
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv
        torch.set_num_threads(threads)
        signal.signal(signal.SIGTERM, on_term)
    out, err = capsys.readouterr()
    return Result(code, " ".join(out.split()), err)


def refused(result: Result, *fragments: str) -> str:
    """Status 2, no traceback, one error line (warnings aside) holding every fragment; that line."""
    assert result.code == 2, (result.out, result.err)
    assert "Traceback" not in result.err + result.out
    errors = [line for line in result.err.splitlines() if line.strip() and not line.startswith("warning:")]
    assert len(errors) == 1, result.err
    line = errors[0]
    for fragment in fragments:
        assert fragment in line, line
    return line


# ------------------------------------------------------------------ one writer per folder


def test_a_second_train_on_the_same_run_is_refused_naming_the_holder(run, run_and_data, capsys):
    with folder_lock(run):
        before = checksums(run)
        result = cli(capsys, "train", "--dataset", run_and_data[1], "--out", run, "--steps", 3 * STEP, *TRAIN)
        refused(result, f"another process is writing {run}", f"pid {os.getpid()} on {socket.gethostname()}", "since ")
        assert checksums(run) == before


def test_the_distillation_stage_holds_the_same_lock(tmp_path_factory, tmp_path):
    with_gains = shared_dataset(tmp_path_factory, "squat", 3, keep_gains=True)
    out = tmp_path / "distilled"
    with folder_lock(out):
        with pytest.raises(DataError, match=f"another process is writing {out}.*pid {os.getpid()}"):
            train_distilled(TrainRequest(dataset=with_gains, out=out, steps=STEP, num_envs=4), 1000, progress=False)
        assert [p.name for p in out.iterdir()] == [".lock"]  # nothing of a run was started


def test_a_lock_left_by_a_killed_writer_is_taken_over_and_the_resume_is_said(run, run_and_data, capsys):
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from opt2skill.folder_lock import folder_lock\n"
         "with folder_lock(sys.argv[1]):\n    print('held', flush=True); time.sleep(120)", str(run)],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    result = cli(capsys, "train", "--dataset", run_and_data[1], "--out", run, "--steps", 3 * STEP, *TRAIN)
    assert result.code == 0, result.err
    assert f"pid {holder.pid}" in result.err and "no longer running" in result.err and "taking it over" in result.err
    assert f"resuming {run} from iteration 2 (checkpoint {run}/checkpoints/model_00000002.pt)" in result.out
    assert [r["iteration"] for r in read_progress(run)] == [1, 2, 3]  # no gap, no duplicate


def test_eval_and_sweep_outputs_are_locked(run, run_and_data, tmp_path, capsys):
    out = run / "eval" / "mine"
    travelling = write_dataset(tmp_path / "glide", [gliding(Dataset.open(run_and_data[1])[0], 2.0)])
    with folder_lock(out):
        refused(cli(capsys, "eval", run, "--indices", "0", "--out", out, "--quiet"), "another process is writing")
        refused(cli(capsys, "sweep", run, "--terrain", "stairs", "--values", "0", "--trials", "1", "--out", out,
                    "--dataset", travelling), "another process is writing")
        assert [p.name for p in out.iterdir()] == [".lock"]


# ------------------------------------------------------------------ damaged datasets


def test_files_not_named_like_a_record_are_skipped_with_a_warning(data, tmp_path, capsys):
    shutil.copy(data / "trajectories" / "000001.h5", data / "trajectories" / "000001 (copy).h5")
    with pytest.warns(DataWarning, match=r"skipped 1 file.*000001 \(copy\)\.h5"):
        ds = Dataset.open(data)
    assert list(ds.indices) == [0, 1, 2]
    before = checksums(data)
    result = cli(capsys, "inspect", data, "--index", "1", "--out", tmp_path)  # a folder: the file goes in it
    assert result.code == 0, result.err
    assert "warning:" in result.err and "000001 (copy).h5" in result.err
    assert f"wrote {tmp_path / 'inspect_000001.png'}" in result.out and (tmp_path / "inspect_000001.png").stat().st_size
    # generate resumes around it and says that a smaller --n removes nothing
    result = cli(capsys, "generate", "squat", "--n", "2", "--workers", "1", "--out", data, "--quiet")
    assert result.code == 0, result.err
    assert "000001 (copy).h5" in result.err and "--n 2 is smaller, so nothing was removed" in result.out
    logs = ("dataset.json", "summary.json")  # the run is logged; every record stays as it was
    assert {k: v for k, v in checksums(data).items() if k not in logs} == {k: v for k, v in before.items() if k not in logs}


def _damage(data: Path) -> None:
    """Four bad files among three good ones: truncated, random bytes, a foreign HDF5 file, a copy
    of trajectory 1 saved as 42."""
    traj = data / "trajectories"
    blob = (traj / "000000.h5").read_bytes()
    (traj / "000000.h5").write_bytes(blob[: len(blob) // 3])
    (traj / "000002.h5").write_bytes(np.random.default_rng(0).bytes(4096))
    with h5py.File(traj / "000043.h5", "w") as f:
        f["x"] = np.arange(3)
    shutil.copy(traj / "000001.h5", traj / "000042.h5")


BAD = ("4 bad trajectory files", "000000.h5 is not a readable HDF5 file", "000002.h5 is not a readable HDF5 file",
       "000042.h5 holds trajectory 1, not 42", "000043.h5 is an HDF5 file but holds no opt2skill trajectory",
       "quarantine/", "opt2skill generate squat --n 3")


def test_bad_files_are_reported_together_and_do_not_block_other_indices(run, data, capsys):
    _damage(data)
    before = checksums(data)
    refused(cli(capsys, "validate", data, "--workers", "1", "--quiet"), *BAD)
    refused(cli(capsys, "generate", "squat", "--n", "3", "--workers", "1", "--out", data, "--quiet"), *BAD)
    refused(cli(capsys, "train", "--dataset", data, "--out", run.parent / "new", *TRAIN), *BAD)
    assert not (run.parent / "new").exists()
    ds = Dataset.open(data)
    with pytest.raises(DataError, match="000042.h5 holds trajectory 1, not 42"):
        ds.meta(ds.position(42))
    assert ds[ds.position(1)].num_frames > 100  # the good one reads
    result = cli(capsys, "eval", run, "--dataset", data, "--indices", "1", "--out", run.parent / "ev", "--plots", "0",
                 "--quiet")
    assert result.code == 0, result.err
    assert json.loads((run.parent / "ev" / "eval.json").read_text())["references"]["indices"] == [1]
    assert checksums(data) == before


def test_nan_or_inf_in_a_trajectory_array_is_named(data, tmp_path, capsys):
    path = data / "trajectories" / "000001.h5"
    traj = read_trajectory(path)
    qpos = traj.qpos.copy()
    qpos[7, 9] = np.nan
    write_trajectory(path, dataclasses.replace(traj, qpos=qpos), 1)
    before = checksums(data)
    refused(cli(capsys, "train", "--dataset", data, "--out", tmp_path / "new", *TRAIN),
            "000001.h5:/traj_000001/qpos holds NaN or infinity (first at row 7)", "quarantine/")
    assert not (tmp_path / "new").exists()
    wrench = traj.contact_wrench.copy()
    wrench[3, 0, 2] = np.inf
    write_trajectory(path, dataclasses.replace(traj, contact_wrench=wrench), 1)
    with pytest.raises(DataError, match=r"contact_wrench holds NaN or infinity \(first at row 3\)"):
        Dataset.open(data)[1]
    assert {k: v for k, v in checksums(data).items() if "000001" not in k} == \
        {k: v for k, v in before.items() if "000001" not in k}


def test_a_dataset_made_with_another_robot_file_is_refused(data, tmp_path, capsys):
    header = json.loads((data / "dataset.json").read_text())
    header["identity"]["robot_hash"] = "0" * 64
    (data / "dataset.json").write_text(json.dumps(header))
    before = checksums(data)
    refused(cli(capsys, "train", "--dataset", data, "--out", tmp_path / "new", *TRAIN),
            "was made with a different 'digit' robot file (hash 000000000000")
    assert checksums(data) == before and not (tmp_path / "new").exists()


# ------------------------------------------------------------------ runs and checkpoints


def test_a_checkpoint_from_another_robot_is_refused_before_anything_is_written(run, run_and_data, capsys):
    newest = checkpoint.latest(run)
    data = torch.load(newest, weights_only=False)
    data["identity"] = {**data["identity"], "robot": "atlas", "robot_hash": "0" * 64}
    torch.save(data, newest)
    before = checksums(run)
    refused(cli(capsys, "train", "--dataset", run_and_data[1], "--out", run, "--steps", 3 * STEP, *TRAIN),
            "model_00000002.pt is a checkpoint of another policy: robot 'atlas'")
    refused(cli(capsys, "eval", run, "--indices", "0", "--quiet"), "checkpoint of another policy: robot 'atlas'")
    assert checksums(run) == before


def test_a_failed_checkpoint_write_keeps_the_previous_checkpoint(run, run_and_data, capsys, monkeypatch):
    kept = {k: v for k, v in checksums(run).items() if k.startswith("checkpoints")}
    logged = (run / "progress.jsonl").read_text()

    def full_disk(obj, path, *args, **kwargs):
        Path(path).write_bytes(b"half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    refused(cli(capsys, "train", "--dataset", run_and_data[1], "--out", run, "--steps", 3 * STEP, *TRAIN),
            "cannot write checkpoint", "model_00000003.pt (No space left on device)",
            "the previous checkpoint model_00000002.pt is intact")
    assert {k: v for k, v in checksums(run).items() if k.startswith("checkpoints")} == kept  # no temporary left
    assert (run / "progress.jsonl").read_text().startswith(logged)
    monkeypatch.undo()
    result = cli(capsys, "train", "--dataset", run_and_data[1], "--out", run, "--steps", 3 * STEP, *TRAIN)
    assert result.code == 0 and "from iteration 2" in result.out, result.err
    assert [r["iteration"] for r in read_progress(run)] == [1, 2, 3]


# ------------------------------------------------------------------ outputs and artifacts before the work


@pytest.fixture
def a_file(tmp_path) -> Path:
    path = tmp_path / "taken.txt"
    path.write_text("mine\n")
    return path


def test_output_paths_are_checked_before_the_work(run, run_and_data, a_file, tmp_path, capsys):
    data = run_and_data[1]
    onnx_path = tmp_path / "policy.onnx"
    export_policy(run, onnx_path)
    cases = [
        (("eval", run, "--indices", "0", "--out", a_file), f"--out {a_file} is a file; give a directory"),
        (("deploy-sim", onnx_path, "--dataset", data, "--indices", "0", "--out", a_file), "is a file; give a directory"),
        (("generate", "squat", "--n", "1", "--out", a_file), "is a file; give a directory"),
        (("export", run, "--out", a_file / "x.onnx"), f"{a_file} is a file, so no directory can be made there"),
        (("inspect", data, "--out", a_file / "x.png"), f"{a_file} is a file, so no directory can be made there"),
        (("render", data, "--out", a_file / "x.mp4"), "is a file, so no directory can be made there"),
        (("sweep", run, "--terrain", "slope", "--values", "0", "--out", a_file), "is a file; give a directory"),
        (("generate", "squat", "--n", "0", "--out", tmp_path / "none"), "--n must be >= 1"),
    ]
    for args, message in cases:
        refused(cli(capsys, *args), message)
    assert a_file.read_text() == "mine\n" and not (tmp_path / "none").exists()
    assert list(run.glob("*deploy-sim*")) == [] and not (run / "eval").exists()


def _widened(onnx_path: Path, out: Path, declared: int | str) -> Path:
    """The exported policy with one action too many (the metadata unchanged), its output size
    declared as `declared`."""
    model = onnx.load(str(onnx_path))
    graph = model.graph
    old = graph.output[0].name
    graph.initializer.append(onnx.numpy_helper.from_array(np.zeros((1, 1), np.float32), "extra"))
    graph.node.append(onnx.helper.make_node("Concat", [old, "extra"], ["wide"], axis=-1))
    graph.output.pop()
    graph.output.append(onnx.helper.make_tensor_value_info("wide", onnx.TensorProto.FLOAT, ["batch", declared]))
    onnx.save(model, str(out))
    return out


def test_an_onnx_with_the_wrong_number_of_actions_is_refused_before_playback(run, run_and_data, tmp_path, capsys):
    exported, _ = export_policy(run, tmp_path / "policy.onnx")
    for declared, message in ((21, "the network outputs [21] values; its metadata describes 20 actions"),
                              ("n", "the network outputs shape (1, 21) for one observation; its metadata describes "
                               "20 actions")):
        bad = _widened(exported, tmp_path / f"wide_{declared}.onnx", declared)
        out = tmp_path / f"played_{declared}"
        refused(cli(capsys, "deploy-sim", bad, "--dataset", run_and_data[1], "--n", "1", "--out", out, "--quiet"),
                message)
        assert not (out / "eval.json").exists()


def test_a_sweep_refuses_a_motion_that_does_not_walk(run, capsys):
    refused(cli(capsys, "sweep", run, "--terrain", "stairs", "--values", "0.02", "--trials", "1", "--quiet"),
            "moves its base 0.0", "the terrain starts 1 m ahead", "walks at least 1.5 m")
    assert not (run / "eval").exists()


def test_set_and_limit_help_list_names_and_ranges(capsys):
    assert "depth in [0, 0.2] m (default 0:0.15)" in set_help() and "speed in [0, 1.5] m/s" in set_help()
    assert "foot_slip 5 mm" in limit_help() and "replay_fall_time" in limit_help()
    result = cli(capsys, "generate", "--help")
    assert result.code == 0 and "step_duration" in result.out and "foot_slip" in result.out
