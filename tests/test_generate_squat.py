"""Dataset generation end to end with the real squat task: kill and resume, reproducibility, failures,
bad input, validate and inspect."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from opt2skill.data.reader import Dataset
from opt2skill.data.record import FRAME_FIELDS
from opt2skill.data.store import ACCEPTED, FAILED, read_json
from opt2skill.data.trajfile import read_trajectory
from opt2skill.model import load_robot
from opt2skill.trajopt.generate import GenerateRequest, generate, process_results
from opt2skill.trajopt.jobs import Job
from opt2skill.tasks import get_task

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "COLUMNS": "200"}


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "opt2skill", *args], env=ENV, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory) -> Path:
    """`generate squat --n 3 --workers 1`, killed with SIGKILL once the first trajectory is stored, then rerun."""
    out = tmp_path_factory.mktemp("gen") / "squat"
    command = [sys.executable, "-m", "opt2skill", "generate", "squat", "--n", "3", "--seed", "0",
               "--workers", "1", "--out", str(out), "--keep-gains", "--quiet"]
    proc = subprocess.Popen(command, env=ENV, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while not list((out / "trajectories").glob("*.h5")):
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() < deadline, "no trajectory stored in time"
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # the worker, if it has not noticed its parent died yet
    except ProcessLookupError:
        pass
    killed = sorted(p.name for p in (out / "trajectories").glob("*.h5"))
    assert 1 <= len(killed) < 3, killed  # killed mid-run
    result = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


def test_resume_after_a_kill_keeps_every_trajectory_once(killed_and_resumed):
    out = killed_and_resumed
    files = sorted(p.name for p in out.rglob("*") if p.is_file() and p.parent.name != "gen")
    assert [f for f in files if f.endswith(".h5")] == ["000000.h5", "000001.h5", "000002.h5"]
    assert not [f for f in files if f.endswith(".tmp")]
    ds = Dataset.open(out)
    assert list(ds.indices) == [0, 1, 2]
    for traj in ds:
        assert traj.validation["accepted"] and traj.provenance["command"].startswith("opt2skill generate squat")
        assert traj.knots["gains"].dtype == np.float32 and traj.validation["figures"]["replay_feedback_fallen"] == 0
    header = ds.header
    assert len(header["runs"]) == 2 and header["identity"]["seed"] == 0
    summary = ds.summary()
    assert summary["counts"] == {"accepted": 3, "rejected": 0, "failed": 0} and summary["missing"] == []
    assert summary["solve_time"]["count"] == 3 and summary["validation_time"]["median"] > 0
    coverage = summary["coverage"]["depth"]
    assert coverage["range"] == [0.0, 0.15] and sum(coverage["accepted_per_bin"]) == 3
    assert summary["figures"]["id_residual_frames_max"]["max"] < 1e-6


def test_same_seed_same_parameters_and_arrays_whatever_workers_order_or_resume(killed_and_resumed, tmp_path):
    summary = generate(GenerateRequest(task="squat", n=2, seed=0, out=tmp_path / "again", workers=2), progress=False)
    assert summary["counts"][ACCEPTED] == 2
    first = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "again" / "trajectories").iterdir()}
    # A larger --n adds the missing index only.
    summary = generate(GenerateRequest(task="squat", n=3, seed=0, out=tmp_path / "again", workers=2), progress=False)
    assert summary["counts"][ACCEPTED] == 3 and summary["requested"] == 3
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "again" / "trajectories").iterdir() if p.name in first} == first
    space = get_task("squat", load_robot("digit")).param_space()
    resumed, again = Dataset.open(killed_and_resumed), Dataset.open(tmp_path / "again")
    for i in range(3):
        a, b = resumed[i], again[i]
        assert a.params == b.params == space.sample(0, i)
        for name in FRAME_FIELDS:
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_validate_and_inspect_on_a_generated_dataset(killed_and_resumed, tmp_path):
    result = cli("validate", str(killed_and_resumed), "--workers", "1", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "3 trajectories re-validated" in result.stdout and "every recomputed figure equals" in result.stdout
    assert "not recomputed" not in result.stdout  # the gains are stored: the feedback replay is redone too
    assert "id_residual_frames_rms" in result.stdout and "task.depth_error" in result.stdout

    png = tmp_path / "one.png"
    result = cli("inspect", str(killed_and_resumed), "--index", "1", "--out", str(png))
    assert result.returncode == 0, result.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 30_000

    # A stored figure that does not match the stored arrays is reported, and the command fails.
    copy = tmp_path / "copy"
    shutil.copytree(killed_and_resumed, copy)
    path = copy / "trajectories" / "000002.h5"
    traj = read_trajectory(path)
    traj.validation["figures"]["foot_slip"] = 0.0
    import json

    with h5py.File(path, "a") as f:
        f["traj_000002"].attrs["validation"] = json.dumps(traj.validation)
    result = cli("validate", str(copy), "--workers", "1", "--quiet")
    assert result.returncode == 1
    assert "#2 foot_slip: stored 0" in result.stdout


def test_bad_input_exits_2_with_one_clear_line(killed_and_resumed, tmp_path):
    result = cli("generate", "squat", "--n", "1", "--set", "depth=0.1:0.5", "--out", str(tmp_path / "x"))
    assert result.returncode == 2
    assert "parameter 'depth' = 0.5 m is outside its allowed range [0, 0.2] m" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "x").exists()
    result = cli("generate", "squat", "--n", "1", "--set", "speed=0:1", "--out", str(tmp_path / "x"))
    assert result.returncode == 2 and "unknown parameter 'speed'; parameters: depth" in result.stderr
    # Resuming an existing dataset with other settings names the difference and writes nothing.
    before = sorted(p.name for p in killed_and_resumed.rglob("*"))
    result = cli("generate", "squat", "--n", "4", "--seed", "1", "--workers", "1", "--out", str(killed_and_resumed))
    assert result.returncode == 2 and "seed: dataset has 0, this command 1" in result.stderr
    assert sorted(p.name for p in killed_and_resumed.rglob("*")) == before


def test_task_config_overrides_reach_the_solve_and_the_identity(tmp_path):
    """`--config key=value` sets the task config of every solve (the record's provenance says so);
    it is part of the dataset's identity, and a bad key or form is one line, exit 2, nothing written."""
    out = tmp_path / "tuned"
    result = cli("generate", "squat", "--n", "1", "--workers", "1", "--out", str(out), "--quiet",
                 "--config", "solver.reg_increase_below=0.2", "--config", "solver.keep_gains=false")
    assert result.returncode == 0, result.stderr
    record = read_trajectory(next((out / "trajectories").glob("*.h5")))
    assert record.provenance["task_config"]["solver"]["reg_increase_below"] == 0.2
    assert read_json(out / "dataset.json", "header")["identity"]["task_config"]["solver.reg_increase_below"] == 0.2
    result = cli("generate", "squat", "--n", "2", "--workers", "1", "--out", str(out))
    assert result.returncode == 2 and "task_config: dataset has" in result.stderr
    for item, message in (("solver.nope=1", "unknown config key 'solver.nope'; keys here: dt,"),
                          ("solver.reg_increase_below", "--config expects key=value"),
                          ("solver.reg_increase_below=0.7", "solver.reg_increase_below must be in (0, 0.5)")):
        result = cli("generate", "squat", "--n", "1", "--out", str(tmp_path / "x"), "--config", item)
        assert result.returncode == 2 and message in result.stderr and result.stderr.count("\n") == 1, result.stderr
        assert not (tmp_path / "x").exists()


def _edit_recorded_settings(path: Path, edit) -> None:
    """Rewrite a stored trajectory's provenance task settings, as another version would have made them."""
    import json

    with h5py.File(path, "r+") as f:
        group = f[next(iter(f.keys()))]
        provenance = json.loads(group.attrs["provenance"])
        edit(provenance["task_config"])
        group.attrs["provenance"] = json.dumps(provenance)


def test_a_resume_with_other_task_settings_than_the_recorded_is_refused(tmp_path):
    """A dataset whose trajectories were solved with other task settings (a default changed by an
    upgrade: not in the identity, but in every trajectory's provenance) is not resumed into a mix; a
    setting the record does not have (a field added since) does not block the resume."""
    out = tmp_path / "squat"
    assert cli("generate", "squat", "--n", "1", "--workers", "1", "--out", str(out), "--quiet").returncode == 0
    stored = next((out / "trajectories").glob("*.h5"))
    _edit_recorded_settings(stored, lambda c: c["solver"].update(reg_increase_below=0.3))
    before = sorted(p.name for p in out.rglob("*"))
    result = cli("generate", "squat", "--n", "2", "--workers", "1", "--out", str(out))
    assert result.returncode == 2, result.stderr
    assert "solved with other task settings" in result.stderr and "solver.reg_increase_below: recorded 0.3" in result.stderr
    assert result.stderr.count("\n") == 1 and sorted(p.name for p in out.rglob("*")) == before

    def older(c):  # the record of a version without this field, otherwise the same settings
        c["solver"]["reg_increase_below"] = get_task("squat", load_robot("digit")).config.solver.reg_increase_below
        del c["solver"]["commit_tol"]

    _edit_recorded_settings(stored, older)
    result = cli("generate", "squat", "--n", "2", "--workers", "1", "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert len(list((out / "trajectories").glob("*.h5"))) + len(list((out / "rejected").glob("*.h5"))) == 2


class _CrashOnLoad:
    """Unpickling this in a worker kills the worker process as it receives its job."""

    def __reduce__(self):
        return (os._exit, (13,))


class _CrashInSolve:
    """A parameter whose value kills the worker process in the middle of the task's solve."""

    def __float__(self):
        os._exit(14)


def _job(index: int, params: dict, task: str = "squat") -> Job:
    from opt2skill.data.validate import ValidationConfig

    return Job(task, "digit", {}, index, 0, params, ValidationConfig().as_dict(), "test")


def test_a_crashed_worker_costs_one_item_and_the_batch_goes_on():
    jobs = [_job(0, {"depth": _CrashOnLoad()}), _job(1, {"depth": _CrashInSolve()}), _job(2, {"depth": 0.05}),
            _job(3, {}, task="no_such_task")]
    results = {r.outcome.index: r.outcome for r in process_results(jobs, workers=1, timeout=None)}
    for index, code in ((0, 13), (1, 14)):
        assert results[index].status == FAILED and results[index].reasons == ["worker_crash"]
        assert f"exit code {code}" in results[index].message
    assert results[2].status == ACCEPTED
    assert results[3].reasons == ["error"] and "unknown task 'no_such_task'" in results[3].message


def test_timeouts_are_recorded_and_redone_only_when_asked(tmp_path):
    request = GenerateRequest(task="squat", n=1, seed=5, out=tmp_path / "t", workers=1, timeout=0.01)
    summary = generate(request, progress=False)
    assert summary["counts"][FAILED] == 1 and summary["reasons"] == {"timeout": 1}
    record = read_json(tmp_path / "t" / "failed" / "000000.json", "failure")
    assert record["params"] == get_task("squat", load_robot("digit")).param_space().sample(5, 0)
    relaxed = GenerateRequest(task="squat", n=1, seed=5, out=tmp_path / "t", workers=1)
    assert generate(relaxed, progress=False)["counts"][FAILED] == 1  # resume does not redo failures
    summary = generate(GenerateRequest(**{**relaxed.__dict__, "retry_failed": True}), progress=False)
    assert summary["counts"] == {"accepted": 1, "rejected": 0, "failed": 0}
    assert not (tmp_path / "t" / "failed" / "000000.json").exists()
