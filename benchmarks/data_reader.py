"""Reader benchmark: a dataset of the paper's size (2000 trajectories x 2800 frames) on disk.

Writes N copies of a real trajectory (the first of --template DIR, or a solved squat tiled to
--frames) as a dataset, then measures: write time and size per file, `Dataset.open`, random
access `ds[i]` and `ds.frames`, and `frame_table` load time and memory for the fields an RL
environment reads (float32), without and with the frame-table cache, and the peak memory.

    .venv/bin/python benchmarks/data_reader.py [--n 2000] [--frames 2800] [--template data/walk]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from opt2skill.data.reader import Dataset  # noqa: E402
from opt2skill.data.record import FRAME_DT, FRAME_FIELDS  # noqa: E402
from opt2skill.data.store import ACCEPTED, DatasetStore, Outcome  # noqa: E402

RL_FIELDS = ("qpos", "qvel", "joint_torque", "contact_wrench", "contact_active", "ee_pos_base", "base_lin_vel", "base_ang_vel")


def template(path: str | None, frames: int):
    if path:
        return Dataset.open(path)[0]
    from opt2skill.model import load_robot
    from opt2skill.tasks import get_task

    traj = get_task("squat", load_robot("digit")).solve({"depth": 0.1}, 0)
    reps = -(-frames // traj.num_frames)
    tiled = {f: np.concatenate([getattr(traj, f)] * reps)[:frames] for f in FRAME_FIELDS}
    tiled["time"] = np.arange(frames) * FRAME_DT
    return replace(traj, **tiled)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=2800)
    parser.add_argument("--template", default=None, help="dataset whose first trajectory is copied")
    parser.add_argument("--dir", default=None, help="where to write (default: a temporary directory)")
    args = parser.parse_args()

    traj = template(args.template, args.frames)
    print(f"template: {traj.task}, {traj.num_frames} frames; machine: {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        store = DatasetStore(Path(tmp) / "ds")
        rng = np.random.default_rng(0)
        start = time.perf_counter()
        with store.lock():
            store.prepare({"task": traj.task}, {})
            for i in range(args.n):
                noisy = replace(traj, qpos=traj.qpos + 1e-6 * rng.standard_normal(traj.qpos.shape))
                store.write_trajectory(Outcome(i, ACCEPTED, traj.params), noisy)
        write = (time.perf_counter() - start) / args.n
        size = sum(p.stat().st_size for p in store.files()) / args.n
        raw = sum(np.asarray(getattr(traj, f)).nbytes for f in FRAME_FIELDS)
        print(f"write: {1e3 * write:.1f} ms per trajectory; {size / 1e6:.2f} MB per file ({raw / 1e6:.2f} MB raw arrays)")

        os.sync()
        start = time.perf_counter()
        ds = Dataset.open(store.root)
        print(f"Dataset.open: {1e3 * (time.perf_counter() - start):.1f} ms for {len(ds)} trajectories")
        picks = rng.integers(0, len(ds), 50)
        start = time.perf_counter()
        for i in picks:
            ds[int(i)]
        print(f"ds[i] (whole trajectory): {1e3 * (time.perf_counter() - start) / len(picks):.1f} ms")
        start = time.perf_counter()
        for i in picks:
            ds.frames(int(i), ("qpos", "qvel"), 1000, 1100)
        print(f"ds.frames(i, (qpos, qvel), 100 frames): {1e3 * (time.perf_counter() - start) / len(picks):.2f} ms")

        before = peak_rss_mb()
        start = time.perf_counter()
        table = ds.frame_table(RL_FIELDS, dtype=np.float32)
        seconds = time.perf_counter() - start
        print(
            f"frame_table({len(RL_FIELDS)} fields, float32): {table.num_rows} rows, {table.nbytes / 1e9:.2f} GB, "
            f"{seconds:.1f} s ({table.num_rows / seconds / 1e6:.2f} M frames/s); peak RSS {before:.0f} -> {peak_rss_mb():.0f} MB"
        )
        del table
        start = time.perf_counter()
        ds.frame_table(RL_FIELDS, dtype=np.float32, use_cache=True)
        print(f"frame_table with use_cache, first time (build and save the cache): {time.perf_counter() - start:.1f} s")
        start = time.perf_counter()
        table = ds.frame_table(RL_FIELDS, dtype=np.float32, use_cache=True)
        mapped = time.perf_counter() - start
        total = sum(float(np.asarray(a).sum()) for a in table.fields.values())  # touch every page
        print(f"frame_table from the cache: {mapped:.2f} s mapped, {time.perf_counter() - start:.1f} s with every page read (checksum {total:.3g})")
        rows = table.row(rng.integers(0, len(ds), 4096), rng.integers(0, 2000, 4096))
        start = time.perf_counter()
        for _ in range(100):
            {name: arr[rows] for name, arr in table.fields.items()}
        print(f"gather 4096 random frames, all fields: {1e3 * (time.perf_counter() - start) / 100:.2f} ms")


if __name__ == "__main__":
    main()
