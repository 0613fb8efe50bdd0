"""`--init distill` runs both stages with one command and each stage resumes after a real kill."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from envs_support import shared_dataset

from opt2skill.errors import DataError
from opt2skill.expert.play import play_expert
from opt2skill.rl import checkpoint
from opt2skill.rl.distill_session import train
from opt2skill.rl.run import read_progress
from opt2skill.rl.session import TrainRequest

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
# 8 worlds: a distillation iteration is 8 x 24 steps, a PPO iteration 8 x 48 steps.
DRIVER = """
import json, sys
from pathlib import Path
from opt2skill.rl.distill_config import DistillConfig
from opt2skill.rl.distill_session import train
from opt2skill.rl.session import TrainRequest
request = TrainRequest(dataset=Path(sys.argv[1]), out=Path(sys.argv[2]), steps=8 * 48 * 6, num_envs=8, threads=1,
                       checkpoint_every=1, command="test")
config = DistillConfig(updates_per_iteration=2, batch_size=256, buffer_samples=5000, critic_warmup_iterations=2)
result = train(request, distill_steps=8 * 24 * 8, progress=False, distill=config)
print("RESULT " + json.dumps({"resumed_from": result["resumed_from"], "iteration": result["iteration"]}))
"""


@pytest.fixture(scope="module")
def squats_with_gains(tmp_path_factory) -> Path:
    return shared_dataset(tmp_path_factory, "squat", 3, keep_gains=True)


def start(dataset: Path, run: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", DRIVER, str(dataset), str(run)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)


def kill_when(proc: subprocess.Popen, directory: Path, iteration: int, timeout: float = 300) -> None:
    """SIGKILL `proc` once `directory` holds a checkpoint of `iteration` or later (no chance to save)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        # Whole checkpoints only: a write in progress has a temporary name (rl.checkpoint).
        done = [int(p.stem.split("_")[1]) for p in (directory / "checkpoints").glob("model_*.pt")]
        if done and max(done) >= iteration:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return
        if proc.poll() is not None:
            pytest.fail(f"the run ended before the kill: {proc.stderr.read()[-2000:]}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail("no checkpoint appeared in time")


def finish(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.split("RESULT ", 1)[1])


def test_each_stage_resumes_after_a_kill(squats_with_gains, tmp_path):
    run = tmp_path / "run"
    kill_when(start(squats_with_gains, run), run / "distill", 2)  # killed while distilling
    killed_at = checkpoint.load(checkpoint.latest(run / "distill"))["iteration"]
    before = read_progress(run / "distill")[:killed_at]
    assert checkpoint.latest(run) is None  # the PPO stage had not started

    proc = start(squats_with_gains, run)
    kill_when(proc, run, 3)  # resumed the distillation, finished it, killed during PPO (after the warm-up)
    ppo_killed_at = checkpoint.load(checkpoint.latest(run))["iteration"]
    distilled = read_progress(run / "distill")
    assert [r["iteration"] for r in distilled] == list(range(1, 9))
    assert distilled[:killed_at] == before  # went on from the checkpoint, not from scratch
    assert distilled[killed_at]["elapsed"] > before[-1]["elapsed"]

    result = finish(start(squats_with_gains, run))
    assert result["resumed_from"] == {"distill": None, "ppo": ppo_killed_at}
    assert result["iteration"] == 6
    ppo = read_progress(run)
    assert [r["iteration"] for r in ppo] == list(range(1, 7))
    # One time axis: the wall-clock time goes on from the distillation into PPO.
    assert ppo[0]["elapsed"] > distilled[-1]["elapsed"] and all(a["elapsed"] < b["elapsed"] for a, b in zip(ppo, ppo[1:]))
    # The critic warm-up kept the distilled actor: its first two PPO iterations left the action noise alone.
    assert ppo[0]["policy/action_std"] == pytest.approx(0.1) and ppo[1]["policy/action_std"] == pytest.approx(0.1)
    assert ppo[2]["policy/action_std"] != pytest.approx(0.1, abs=1e-7)

    # The distilled actor itself (the stage's last checkpoint) is evaluated like any of the run's
    # checkpoints: the same weights, named as the distillation's; a file outside the run is refused.
    from opt2skill.eval.evaluate import load_run_policy
    from opt2skill.rl.policy import Policy, build_actor
    from opt2skill.rl.run import read_spec

    stage_last = checkpoint.latest(run / "distill")
    distilled_policy = load_run_policy(run, stage_last)
    assert distilled_policy.info["name"] == "run (distillation iteration 8)"
    data = checkpoint.load(stage_last)
    spec = read_spec(run)
    actor = build_actor(spec.ppo, data["dims"]["actor"], data["dims"]["critic"], data["dims"]["actions"])
    actor.load_state_dict(data["actor_state_dict"])
    obs = torch.randn(5, data["dims"]["actor"], generator=torch.Generator().manual_seed(0)).numpy()
    np.testing.assert_allclose(distilled_policy.policy(obs), Policy(actor)(obs), atol=1e-6)
    last_ppo = load_run_policy(run).policy(obs)
    assert np.abs(last_ppo - distilled_policy.policy(obs)).max() > 1e-4  # PPO moved the actor: not the same file
    stray = tmp_path / "model_00000008.pt"
    stray.write_bytes(stage_last.read_bytes())
    with pytest.raises(DataError, match="is not one of run"):
        load_run_policy(run, stray)


def test_a_dataset_without_gains_gets_a_clear_error(tmp_path_factory, tmp_path):
    bare = shared_dataset(tmp_path_factory, "squat", 3)
    request = TrainRequest(dataset=bare, out=tmp_path / "run", steps=100, num_envs=2, threads=1)
    with pytest.raises(DataError, match="no feedback gains.*--keep-gains"):
        train(request, distill_steps=100, progress=False)
    shown = subprocess.run([str(Path(sys.executable).parent / "opt2skill"), "train", "--init", "distill", "--dataset",
                            str(bare), "--out", str(tmp_path / "run2"), "--quiet"], capture_output=True, text=True,
                           env=ENV, timeout=300)
    assert shown.returncode == 2 and len(shown.stderr.strip().splitlines()) == 1 and "--keep-gains" in shown.stderr


def test_the_expert_plays_on_its_own(squats_with_gains):
    result = play_expert(squats_with_gains, n=2, threads=1)
    assert [m.fell for m in result.motions] == [False, False]
    assert max(e["E_joint"] for e in result.errors) < 0.01  # measured 0.002 rad on squats
    shown = subprocess.run([str(Path(sys.executable).parent / "opt2skill"), "play", "--expert", "--dataset",
                            str(squats_with_gains), "--n", "1"], capture_output=True, text=True, env=ENV, timeout=300)
    assert shown.returncode == 0, shown.stderr
    assert "feedback" in shown.stdout and "321 / 321" in shown.stdout and "E_joint" in shown.stdout

