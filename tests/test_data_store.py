"""The trajectory file, the dataset directory and the reader, on a real solved squat."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from opt2skill.data.record import FRAME_FIELDS
from opt2skill.data.reader import Dataset
from opt2skill.data.store import ACCEPTED, FAILED, REJECTED, DatasetStore, Outcome
from opt2skill.data.trajfile import read_frames, read_meta, read_trajectory, write_trajectory
from opt2skill.errors import DataError
from opt2skill.model import load_robot
from opt2skill.tasks import get_task


@pytest.fixture(scope="module")
def squat():
    robot = load_robot("digit")
    task = get_task("squat", robot, {"solver.keep_gains": True})
    return task.solve({"depth": 0.1}, 0)


def _arrays_equal(a, b) -> None:
    for name in FRAME_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name


def test_trajectory_file_round_trip_keeps_values_and_dtypes(tmp_path, squat):
    path = tmp_path / "000007.h5"
    write_trajectory(path, squat, 7)
    back = read_trajectory(path)
    _arrays_equal(squat, back)
    assert back.knots["gains"].dtype == np.float32 and back.knots["x"].dtype == np.float64
    assert set(back.knots) == set(squat.knots)
    assert back.params == squat.params and back.solver == squat.solver and back.contact_names == squat.contact_names
    meta = read_meta(path)
    assert meta.index == 7 and meta.num_frames == squat.num_frames and "gains" in meta.knot_names
    part = read_frames(path, ("qpos", "contact_active"), frames=slice(10, 20))
    assert np.array_equal(part["qpos"], squat.qpos[10:20]) and part["contact_active"].dtype == bool
    # The store drops the gains unless asked to keep them.
    write_trajectory(tmp_path / "b.h5", squat, 7, drop_knots=("gains",))
    assert "gains" not in read_trajectory(tmp_path / "b.h5").knots
    assert not list(tmp_path.glob("*.tmp"))


def test_corrupt_and_foreign_files_get_clear_errors(tmp_path, squat):
    good = tmp_path / "good.h5"
    write_trajectory(good, squat, 0)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 3])
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an hdf5 file\n" * 50)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("qpos", data=np.zeros((3, 27)))
    for path, words in [(truncated, "truncated"), (garbage, "signature"), (foreign, "no opt2skill trajectory")]:
        with pytest.raises(DataError, match=words) as info:
            read_trajectory(path)
        assert str(path) in str(info.value)
    bad_attr = tmp_path / "bad_attr.h5"
    write_trajectory(bad_attr, squat, 0)
    with h5py.File(bad_attr, "a") as f:
        f["traj_000000"].attrs["params"] = "{not json"
        del f["traj_000000"]["qvel"]
    with pytest.raises(DataError, match="'params' is not valid JSON"):
        read_meta(bad_attr)
    with h5py.File(bad_attr, "a") as f:
        f["traj_000000"].attrs["params"] = "{}"
    with pytest.raises(DataError, match="missing the array 'qvel'"):
        read_trajectory(bad_attr)


def _identity(seed: int = 0) -> dict:
    return {"task": "squat", "robot": "digit", "seed": seed, "ranges": {"depth": [0.0, 0.15]}}


def test_store_resumes_checks_identity_and_resolves_interrupted_retries(tmp_path, squat):
    store = DatasetStore(tmp_path / "ds")
    with store.lock():
        header, outcomes = store.prepare(_identity(), {"command": "first"})
        assert outcomes == {}
        store.write_trajectory(Outcome(0, ACCEPTED, squat.params), squat)
        rejected = replace(squat, validation={"accepted": False, "reasons": ["foot_slip"], "figures": {"foot_slip": 9.0}})
        store.write_trajectory(Outcome(1, REJECTED, squat.params, ["foot_slip"]), rejected)
        store.write_failure(Outcome(2, FAILED, {"depth": 0.05}, ["solver_error"], "diverged"))
        with pytest.raises(DataError, match="another process is writing"):
            with DatasetStore(tmp_path / "ds").lock():
                pass
    # A retry killed after writing its new result but before deleting the old record.
    write_trajectory(store.path(ACCEPTED, 2), squat, 2)
    (store.root / "trajectories" / "000005.h5.tmp").write_bytes(b"half a file")
    with store.lock():
        header, outcomes = store.prepare(_identity(), {"command": "second"})
    assert [h["command"] for h in header["runs"]] == ["first", "second"]
    assert {i: o.status for i, o in outcomes.items()} == {0: ACCEPTED, 1: REJECTED, 2: ACCEPTED}
    assert not store.path(FAILED, 2).exists() and not list(store.root.rglob("*.tmp"))
    assert outcomes[1].reasons == ["foot_slip"]
    with store.lock(), pytest.raises(DataError, match=r"seed: dataset has 0, this command 1"):
        store.prepare(_identity(seed=1), {})
    with store.lock(), pytest.raises(DataError, match=r"ranges\.depth: dataset has \[0.0, 0.15\]"):
        store.prepare({**_identity(), "ranges": {"depth": [0.0, 0.1]}}, {})
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with DatasetStore(other).lock(), pytest.raises(DataError, match="not empty and not an opt2skill dataset"):
        DatasetStore(other).prepare(_identity(), {})


def test_reader_random_access_and_frame_table(tmp_path, squat):
    store = DatasetStore(tmp_path)
    lengths = {}
    with store.lock():
        store.prepare(_identity(), {})
        for index, frames in ((4, 100), (0, squat.num_frames), (9, 57)):
            part = replace(squat, **{f: getattr(squat, f)[:frames] for f in FRAME_FIELDS})
            store.write_trajectory(Outcome(index, ACCEPTED, squat.params), part)
            lengths[index] = frames
        store.write_trajectory(Outcome(5, REJECTED, squat.params), squat)
    ds = Dataset.open(tmp_path)
    assert len(ds) == 3 and list(ds.indices) == [0, 4, 9]
    assert ds[1].num_frames == 100 and ds.position(9) == 2 and ds.meta(2).num_frames == 57
    assert np.array_equal(ds.frames(0, ["qvel"], 5, 8)["qvel"], squat.qvel[5:8])
    assert len(Dataset.open(tmp_path, REJECTED)) == 1
    with pytest.raises(IndexError):
        ds[3]

    table = ds.frame_table(("qpos", "joint_torque", "contact_active"), dtype=np.float32, subset=[2, 0])
    assert table["qpos"].dtype == np.float32 and table["contact_active"].dtype == bool
    assert table.num_rows == 57 + squat.num_frames and list(table.trajectories) == [2, 0]
    rows = table.row(np.array([0, 1, 1]), np.array([56, 0, 200]))
    assert list(rows) == [56, 57, 257]
    traj, frame = table.locate(rows)
    assert list(traj) == [0, 1, 1] and list(frame) == [56, 0, 200]
    assert np.allclose(table["joint_torque"][257], squat.joint_torque[200], atol=1e-4)
    with pytest.raises(IndexError):
        table.row(0, 57)

    # The cache maps the same table from uncompressed arrays; a changed dataset gets a new entry.
    first = ds.frame_table(("qpos", "contact_active"), dtype=np.float32, use_cache=True)
    again = ds.frame_table(("qpos", "contact_active"), dtype=np.float32, use_cache=True)
    assert isinstance(again["qpos"], np.memmap) and not isinstance(first["qpos"], np.memmap)
    assert np.array_equal(first["qpos"], again["qpos"]) and np.array_equal(first.start, again.start)
    assert again["contact_active"].dtype == bool and len(list((tmp_path / "cache").iterdir())) == 1
    with store.lock():
        store.write_trajectory(Outcome(4, ACCEPTED, squat.params), squat)  # index 4 now has every frame
    changed = Dataset.open(tmp_path).frame_table(("qpos", "contact_active"), dtype=np.float32, use_cache=True)
    assert changed.num_rows == first.num_rows - 100 + squat.num_frames
    assert len(list((tmp_path / "cache").iterdir())) == 2


def test_dataset_errors_name_the_problem(tmp_path):
    with pytest.raises(DataError, match="not found"):
        Dataset.open(tmp_path / "missing")
    with pytest.raises(DataError, match="not an opt2skill dataset"):
        Dataset.open(tmp_path)
    (tmp_path / "dataset.json").write_text("{ truncated")
    with pytest.raises(DataError, match=r"dataset.json is not valid JSON"):
        Dataset.open(tmp_path)
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(DataError, match="not an opt2skill dataset header"):
        Dataset.open(tmp_path)
    with DatasetStore(tmp_path / "ok").lock():
        DatasetStore(tmp_path / "ok").prepare(_identity(), {})
    (tmp_path / "ok" / "summary.json").write_text('{"counts": ')
    with pytest.raises(DataError, match=r"ok/summary.json is not valid JSON .*the dataset summary is corrupt"):
        Dataset.open(tmp_path / "ok").summary()
    (tmp_path / "ok" / "trajectories" / "000000.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    with pytest.raises(DataError, match=r"000000.h5 is not a readable HDF5 file"):
        Dataset.open(tmp_path / "ok")[0]


def test_atomic_writes_leave_no_partial_file(tmp_path, squat):
    """A write that fails half way leaves neither a file nor a temporary behind."""
    path = tmp_path / "000001.h5"
    broken = replace(squat, knots={"bad": np.array([object()], dtype=object)})
    with pytest.raises(TypeError):
        write_trajectory(path, broken, 1)
    assert not path.exists() and not list(Path(tmp_path).iterdir())
