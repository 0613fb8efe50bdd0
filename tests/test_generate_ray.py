"""Generation on a local Ray instance gives the same dataset as the process pool; crashes are recorded."""

from __future__ import annotations

import sys

import numpy as np
import ray
import ray.cloudpickle

from opt2skill.data.reader import Dataset
from opt2skill.data.record import FRAME_FIELDS
from opt2skill.data.store import ACCEPTED, FAILED
from opt2skill.data.validate import ValidationConfig
from opt2skill.trajopt.generate import GenerateRequest, generate
from opt2skill.trajopt.jobs import Job
from opt2skill.trajopt.ray_backend import ray_results


class _CrashInSolve:
    def __float__(self):
        import os

        os._exit(14)


def test_ray_generation_matches_the_process_pool(tmp_path):
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = generate(GenerateRequest(task="squat", n=2, seed=3, out=tmp_path / "ray", workers=2, ray=True), progress=False)
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray workers cannot import tests
        crash = Job("squat", "digit", {}, 7, 3, {"depth": _CrashInSolve()}, ValidationConfig().as_dict(), "test")
        crashed = [r.outcome for r in ray_results([crash], workers=1, address=None, timeout=None)]
        assert ray.is_initialized()  # the driver leaves an instance it did not start running
    finally:
        ray.shutdown()
    assert crashed[0].status == FAILED and crashed[0].reasons == ["worker_crash"], crashed[0].message
    assert on_ray["counts"][ACCEPTED] == 2
    on_pool = generate(GenerateRequest(task="squat", n=2, seed=3, out=tmp_path / "pool", workers=2), progress=False)
    a, b = Dataset.open(tmp_path / "ray"), Dataset.open(tmp_path / "pool")
    assert Dataset.open(tmp_path / "ray").header["runs"][0]["backend"] == "ray"
    for i in range(2):
        assert a[i].params == b[i].params
        for name in FRAME_FIELDS:
            assert np.array_equal(getattr(a[i], name), getattr(b[i], name)), name
    assert on_ray["figures"].keys() == on_pool["figures"].keys()
