"""How fast evaluation, the 2 kHz player and rendering are, on this machine.

    python benchmarks/eval_speed.py [--run RUN --dataset DIR] [--seconds 14]

Without a run, it makes its own: a 14-s squatting reference recorded from the simulator (so a
replayed action sequence tracks it for its whole length, with the contact load of a standing
robot), a dataset of it, and a run trained for one PPO iteration (a real, untrained-looking policy).
Figures:

- eval rollouts (`eval.rollout`, the tracking environment at 1 kHz physics): world-steps per second
  for 1, 10 and 20 references tracked at once, and the time of a 20-reference evaluation of 14-s
  references (the paper's set-up);
- the standalone player (2 kHz, one world): policy steps per second and the real-time factor, with
  the time split between physics, observation building and onnxruntime;
- rendering: video frames per second (640x480, ghost on).

Terminations are off where the policy would end an episode early, so every figure is for full-length
references.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import opt2skill  # noqa: F401  (before mujoco: selects offscreen EGL rendering)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def make_run(root: Path, seconds: float) -> tuple[Path, Path]:
    from eval_support import write_dataset

    from opt2skill.envs.recorded import record_reference, squat_targets
    from opt2skill.model import load_robot
    from opt2skill.rl.session import TrainRequest, train

    robot = load_robot("digit")
    targets = squat_targets(robot, int(round(seconds / 0.005)))
    reference = record_reference(robot, targets, task="squat")
    dataset = write_dataset(root / "data", [reference])
    run = root / "run"
    train(TrainRequest(dataset=dataset, out=run, steps=4 * 48, num_envs=4, threads=1), progress=False)
    np.save(root / "targets.npy", targets)
    return run, dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path)
    parser.add_argument("--dataset", type=Path)
    parser.add_argument("--seconds", type=float, default=14.0, help="length of the self-made reference")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import mujoco

    from opt2skill.data.reader import Dataset
    from opt2skill.deploy.export import export_policy
    from opt2skill.deploy.player import Player
    from opt2skill.envs import evaluation_config
    from opt2skill.envs.config import TerminationConfig
    from opt2skill.eval.evaluate import load_run_policy
    from opt2skill.eval.render import render_video
    from opt2skill.eval.rollout import rollout

    tmp = tempfile.TemporaryDirectory()
    root = Path(tmp.name)
    if args.run:
        run, dataset, replay = args.run, args.dataset or None, None
    else:
        print(f"making a run on a {args.seconds:g}-s recorded reference ...", flush=True)
        run, dataset = make_run(root, args.seconds)
        replay = np.load(root / "targets.npy")
    source = load_run_policy(run)
    ds = Dataset.open(dataset or source.spec.dataset)
    reference = ds[0]
    steps = reference.num_frames - 1
    config = dataclasses.replace(evaluation_config(source.spec.tracking), terminations=TerminationConfig(
        max_height_error=0, max_orientation_error=0, max_xy_error=0, min_height=0))

    def policy_for(n):
        if replay is None:
            return source.policy
        actions = iter((replay - source.robot.config.default_pose) / config.actions.scale)
        return lambda obs: np.tile(next(actions), (n, 1))

    print(f"\nreference: {reference.duration:.1f} s ({steps} policy steps); "
          f"{'replayed recorded actions' if replay is not None else 'the run policy'}")
    print("eval rollouts (tracking environment, 1 kHz physics, 2 threads):")
    for n in (1, 10, 20):
        start = time.perf_counter()
        rollout(source.robot, [reference] * n, policy_for(n), config)
        elapsed = time.perf_counter() - start
        print(f"  {n:3d} references: {n * steps / elapsed:8.0f} world-steps/s, {elapsed:6.1f} s "
              f"(20 x 14 s references at this rate: {20 * 2800 / (n * steps / elapsed):.0f} s)")

    onnx_path, _ = export_policy(run, root / "policy.onnx")
    player = Player(onnx_path)
    player.terminations = {}  # play the whole reference
    start = time.perf_counter()
    played = player.run(reference)
    elapsed = time.perf_counter() - start
    done = played.tracked.num_frames - 1
    # The parts on their own: the physics steps (holding the start pose) and the network calls.
    m, d = player.model, player.data
    mujoco.mj_resetData(m, d)
    d.qpos[:], d.ctrl[:] = reference.qpos[0], reference.qpos[0, 7:]
    t = time.perf_counter()
    for _ in range(done * player.substeps):
        mujoco.mj_step(m, d)
    physics = time.perf_counter() - t
    obs = np.zeros(player.meta.obs_dim, dtype=np.float32)
    t = time.perf_counter()
    for _ in range(done):
        player.act(obs)
    network = time.perf_counter() - t
    print(f"2 kHz player (one world, own loop): {done / elapsed:6.0f} policy steps/s = {done * 0.005 / elapsed:.2f} x "
          f"real time; of its time about {physics / elapsed:.0%} physics ({player.substeps} mj_step per policy step), "
          f"{network / elapsed:.0%} onnxruntime, the rest sensors, observation and bookkeeping")

    qpos = reference.qpos[: int(5 / 0.005)]
    start = time.perf_counter()
    render_video(source.robot, qpos, root / "v.mp4", ghost_qpos=qpos, fps=30)
    elapsed = time.perf_counter() - start
    frames = int((len(qpos) - 1) * 0.005 * 30) + 1
    print(f"render: {frames / elapsed:.1f} video frames/s (640x480, ghost), a 14-s video at 30 fps in "
          f"{14 * 30 / (frames / elapsed):.0f} s")
    tmp.cleanup()


if __name__ == "__main__":
    main()
