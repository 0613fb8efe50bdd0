"""Keeping the best policy: held-out judgements on real rollouts order policies by success, then frames
tracked, then errors; the best checkpoint is the one eval and export take by default; a trainer
judges on its schedule and logs each judgement."""

from __future__ import annotations

import json

import numpy as np
import pytest
from envs_support import ROBOT, make_env, recorded_reference

from opt2skill.envs import tracking_config
from opt2skill.errors import ConfigError
from opt2skill.rl import checkpoint
from opt2skill.rl.best import JUDGEMENTS, HeldOutJudge, JudgeConfig, score
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.trainer import Schedule, Trainer

NOMINAL = JudgeConfig(every=2, n=2, randomize=False, noise=False)


@pytest.fixture(scope="module")
def recorded():
    return recorded_reference(steps=40)


class Replay:
    """Plays the targets that made the recorded reference, plus an offset: exact at offset 0."""

    def __init__(self, env_like, targets: np.ndarray, offset: float):
        self.targets, self.offset, self.step = targets, offset, 0
        self.default, self.scale = ROBOT.config.default_pose, env_like.actions.scale

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        target = self.targets[min(self.step, len(self.targets) - 1)] + self.offset
        self.step += 1
        return np.tile((target - self.default) / self.scale, (len(obs), 1))


def test_the_best_judgement_keeps_its_checkpoint(recorded, tmp_path):
    traj, targets = recorded
    config = tracking_config("recorded")
    judge = HeldOutJudge(tmp_path, ROBOT, [traj, traj], config, NOMINAL, threads=1)
    files = {}
    for name in ("slightly_off", "falls", "exact", "slightly_off_again"):
        files[name] = tmp_path / f"{name}.pt"
        files[name].write_bytes(name.encode())
    policies = [("slightly_off", 0.04), ("falls", 1.5), ("exact", 0.0), ("slightly_off_again", 0.04)]
    judged = [judge.judge(Replay(config, targets, offset), files[name], "ppo", i, 100 * i)
              for i, (name, offset) in enumerate(policies)]
    assert [j["best"] for j in judged] == [True, False, True, False]
    assert judged[1]["success"] == 0 and judged[2]["success"] == 1 and judged[0]["success"] == 1
    assert judged[2]["E_joint"] < judged[0]["E_joint"]
    assert checkpoint.best_path(tmp_path).read_bytes() == b"exact"
    assert json.loads((tmp_path / "best" / "best.json").read_text())["iteration"] == 2
    lines = (tmp_path / JUDGEMENTS).read_text().splitlines()
    assert [json.loads(line)["iteration"] for line in lines] == [0, 1, 2, 3]
    # a new judge of the same run starts from the kept best
    again = HeldOutJudge(tmp_path, ROBOT, [traj], config, NOMINAL, threads=1)
    assert again.best["iteration"] == 2
    assert checkpoint.policy_default(tmp_path) == checkpoint.best_path(tmp_path)


def test_the_order_is_success_then_frames_then_errors_relative_to_the_paper():
    base = {"success": 0.9, "tracked": 0.95, "E_ee_foot": 5.0, "E_joint": 0.03, "E_vel_x": 4.0, "E_pos_x": 1.0}
    assert score({**base, "success": 1.0, "E_joint": 0.3}) > score(base)
    assert score({**base, "tracked": 0.99, "E_joint": 0.3}) > score(base)
    assert score({**base, "E_joint": 0.02}) > score(base)
    assert score({**base, "E_pos_x": None}) > score({**base, "E_pos_x": 50.0})  # NaN (stored as null) is skipped
    with pytest.raises(ConfigError, match="interval"):
        JudgeConfig(every=0).check()


def test_a_trainer_judges_on_its_schedule_and_keeps_a_real_checkpoint(recorded, tmp_path):
    traj, _ = recorded
    env = make_env([traj], num_envs=4)
    trainer = Trainer(env, PPOConfig(rollout_seconds=0.05, hidden_dims=(16, 16)), tmp_path, seed=0)
    trainer.judge = HeldOutJudge(tmp_path, ROBOT, [traj], env.config, NOMINAL, threads=1)
    trainer.warm_up_normalizers()
    trainer.train(Schedule(total_steps=5 * trainer.batch, checkpoint_every=100), progress=False)
    lines = [json.loads(x) for x in (tmp_path / JUDGEMENTS).read_text().splitlines()]
    assert [x["iteration"] for x in lines] == [2, 4, 5]  # every 2 iterations and at the end
    best = max(lines, key=score)
    kept = checkpoint.load(checkpoint.best_path(tmp_path))
    assert kept["iteration"] == best["iteration"] and "alg" in kept


def test_eval_takes_the_best_then_the_newest_checkpoint_then_the_finished_actor(tmp_path):
    assert checkpoint.policy_default(tmp_path) is None
    final = checkpoint.final_path(tmp_path)
    final.parent.mkdir()
    final.write_bytes(b"actor")
    assert checkpoint.policy_default(tmp_path) == final  # a run carried without its checkpoints
    newest = checkpoint.save(tmp_path, 7, {"env_steps": 0})
    assert checkpoint.policy_default(tmp_path) == newest
    checkpoint.best_path(tmp_path).parent.mkdir()
    checkpoint.best_path(tmp_path).write_bytes(b"best")
    assert checkpoint.policy_default(tmp_path) == checkpoint.best_path(tmp_path)
