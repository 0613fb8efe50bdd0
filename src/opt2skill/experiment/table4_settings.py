"""The sizes of `opt2skill experiment table4` (the force ablation of the paper's Sec. IV-F): named
settings (quick, full) and per-option overrides, checked against the wiping task's parameters."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from opt2skill.errors import ConfigError
from opt2skill.experiment.settings import Settings

TASK = "wipe"  # the experiment's task: a hand pressing a prescribed normal force on a desk
ABLATION_LABELS = {"pos": "Pos", "pos_f": "Pos+F", "pos_t": "Pos+T", "pos_f_t": "Pos+F+T"}  # the paper's names
BEST = "pos_f_t"  # the paper's method: every other row is tested against it


@dataclass(frozen=True)
class Table4Settings(Settings):
    experiment: ClassVar[str] = "table4"
    setting: str
    n_train: int  # training references, force and desk height sampled in their ranges
    n_test: int  # held-out references per force level (another seed)
    train_steps: int  # environment steps per policy, all worlds together (the same for every ablation)
    num_envs: int
    # Environment steps of distilling the optimizer's feedback expert into each policy before its PPO
    # steps (`train --init distill`, docs/distill.md; the training references keep their gains); 0: PPO
    # from scratch, the paper's way.
    distill_steps: int = 0
    forces: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)  # N, the evaluation levels (Table IV's)
    train_force: tuple[float, float] = (0.0, 20.0)  # N, the training references' range (the paper's)
    desk_height: tuple[float, float] = (0.85, 0.95)  # m, every reference's desk top range (the paper's)
    ablations: tuple[str, ...] = ("pos", "pos_f", "pos_t", "pos_f_t")  # Table IV's rows
    history: int = 10
    transfer_force: float = 15.0  # N, the desk-height transfer's reference (the paper's 15 N at 0.95 m)
    transfer_height: float = 0.95  # m
    transfer_desks: tuple[float, ...] = (0.90, 1.00)  # m, desk tops it is tracked at (empty: no transfer test)
    n_transfer: int = 10  # references of the transfer test (reach sampled)
    timing: dict[str, float] = field(default_factory=dict)  # s per wipe phase replacing the task's (tasks/wipe.py Timing)
    seed: int = 0  # training references' seed and training's; held-out ones use seed + 1
    workers: int = 0  # generation processes, and policies trained at once on a CPU (0: every core)
    device: str = "cpu"
    mixed_precision: bool = False  # bf16 autocast in every policy's PPO update, as `train --mixed-precision`

    def check(self) -> None:
        problems = []
        if self.n_train < 1 or self.n_test < 1 or self.n_transfer < 1:
            problems.append(f"--n-train, --n-test and --n-transfer must be >= 1, got {self.n_train}, {self.n_test}, "
                            f"{self.n_transfer}")
        if self.distill_steps < 0:
            problems.append(f"--distill-steps must be >= 0 (0: PPO from scratch), got {self.distill_steps}")
        if self.train_steps < 1 or not 1 <= self.num_envs <= 4096:
            problems.append(f"--train-steps must be >= 1 and --num-envs in [1, 4096], got {self.train_steps}, {self.num_envs}")
        if not self.forces or len(set(self.forces)) != len(self.forces):
            problems.append(f"--forces must be distinct force levels, got {list(self.forces)}")
        if not 0 <= self.history <= 50:
            problems.append(f"--history must be in [0, 50], got {self.history}")
        from opt2skill.envs import ABLATIONS

        wrong = [a for a in self.ablations if a not in ABLATIONS]
        if wrong or BEST not in self.ablations or len(set(self.ablations)) != len(self.ablations):
            problems.append(f"--ablations must be distinct names from {', '.join(ABLATIONS)} including {BEST} (the row the "
                            f"others are tested against), got {list(self.ablations)}")
        problems += self._parameter_problems()
        if any(not 0.5 <= h <= 1.5 for h in self.transfer_desks):
            problems.append(f"--transfer-desks must be desk tops in [0.5, 1.5] m, got {list(self.transfer_desks)}")
        if problems:
            raise ConfigError("; ".join(problems))
        from opt2skill.sim.devices import check_device

        check_device(self.device)

    def _parameter_problems(self) -> list[str]:
        """The forces, desk heights and timing against the task's own ranges and config."""
        from opt2skill.model import load_robot
        from opt2skill.tasks import get_task

        problems = []
        try:
            task = get_task(TASK, load_robot("digit"), self.task_config())
        except ConfigError as exc:
            return [f"--timing: {exc}"]
        space = task.param_space()
        pinned = [("--forces", "force", (f, f)) for f in self.forces]
        pinned += [("--train-force", "force", self.train_force), ("--desk-height", "desk_height", self.desk_height),
                   ("--transfer-force", "force", (self.transfer_force,) * 2),
                   ("--transfer-height", "desk_height", (self.transfer_height,) * 2)]
        for option, name, bounds in pinned:
            try:
                space.set_range(name, bounds)
            except ConfigError as exc:
                problems.append(f"{option}: {exc}")
        return problems

    def task_config(self) -> dict[str, Any]:
        """The wipe task's config overrides (only the timing; none at the task's own)."""
        return {"timing": dict(self.timing)} if self.timing else {}


# The quick setting's wipe: every phase shorter (6.8 s of motion instead of 11.4 s; a solve about
# 55 s instead of 96 s on the loaded 2-core machine), the force ramps as long as the task's.
QUICK_TIMING = dict(stand=0.1, rise=0.3, reach=0.5, lower=0.2, stroke=0.5, lift=0.2, back=0.5, rest=0.1)

PRESETS: dict[str, dict[str, Any]] = {
    # Minutes on a 2-core CPU: every step's plumbing at the paper's six levels, not its comparison.
    "quick": dict(n_train=2, n_test=2, train_steps=3072, num_envs=32, n_transfer=2, timing=QUICK_TIMING),
    # The paper's set-up (Sec. IV-F): 1400 training references, 10 per level and for the transfer.
    "full": dict(n_train=1400, n_test=10, train_steps=20_000_000, num_envs=128, n_transfer=10),
}
Table4Settings.presets = PRESETS
