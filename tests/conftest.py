import os

# Crocoddyl is 25-100x slower per iteration with OpenMP threads on small machines (docs/dependencies.md).
os.environ.setdefault("OMP_NUM_THREADS", "1")

import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from opt2skill.robots import ROBOTS_DIR  # noqa: E402


@pytest.fixture(autouse=True)
def _scratch_working_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Run each test in its own directory: MuJoCo writes MUJOCO_LOG.TXT to the working directory
    when a test provokes an unstable simulation on purpose, and nothing may land in the checkout."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture
def digit_copy(tmp_path: Path) -> Path:
    """A writable copy of the Digit robot folder, for tests that break it on purpose."""
    target = tmp_path / "digit"
    shutil.copytree(ROBOTS_DIR / "digit", target)
    return target
