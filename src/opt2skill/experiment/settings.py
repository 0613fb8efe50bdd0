"""The sizes of an experiment (`opt2skill experiment table3`, `table4`): named settings (quick,
full) and per-option overrides, one dataclass per experiment (`ExperimentSettings` is table3's,
`experiment.table4_settings.Table4Settings` table4's), each naming its experiment and presets.

The resolved settings are the experiment's identity, written to OUT/experiment.json on the first
run; a rerun with other settings into the same folder is refused with the differing keys named,
since its steps would mix two experiments.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from opt2skill.errors import ConfigError, DataError

SOURCES = ("to", "ik", "human")  # Table III's data rows, in the paper's order of comparison
SOURCE_LABELS = {"to": "Opt2Skill (TO)", "ik": "IK-data", "human": "human-data"}
SOURCE_TASKS = {"to": "walk", "ik": "walk_ik", "human": "walk_human"}
IDENTITY_FILE = "experiment.json"


class Settings:
    """What every experiment's settings share: a name, presets, a check and an identity."""

    experiment: ClassVar[str]
    presets: ClassVar[dict[str, dict[str, Any]]]
    setting: str

    def check(self) -> None:
        raise NotImplementedError

    def identity(self) -> dict[str, Any]:
        """What the experiment's outputs depend on (not `workers`: it changes speed, not results)."""
        d = dataclasses.asdict(self)  # type: ignore[call-overload]
        d.pop("workers", None)
        return json.loads(json.dumps(d))  # tuples as lists, as they read back


S = TypeVar("S", bound=Settings)


PAPER_HISTORY = 10  # the history length of the paper's Opt2Skill rows (Table III)


@dataclass(frozen=True)
class ExperimentSettings(Settings):
    experiment: ClassVar[str] = "table3"
    setting: str
    n_train: int  # training references per source
    n_test: int  # held-out references per source (another seed)
    duration: float  # s, each TO and IK walk (the paper's: 14 s)
    human_duration: float  # s, each constructed human clip (the paper's human clips: 5-6 s)
    speed: tuple[float, float]  # m/s, the matched range of every source
    clearance: tuple[float, float]  # m, the matched range of every source
    train_steps: int  # environment steps per policy, all worlds together (the same budget for every source)
    num_envs: int
    histories: tuple[int, ...] = (0, 5, 10, 15)  # the ablation rows, on the TO data
    history: int = PAPER_HISTORY  # the data rows' history length
    to_ablation: str = "pos_f_t"  # the TO policy's inputs; kinematic sources can only have `pos`
    stairs: tuple[float, ...] = ()  # m, step heights of the sweep
    slopes: tuple[float, ...] = ()  # degrees
    sweep_trials: int = 10
    sweep_start: float = 1.0  # m from the start to the terrain
    yaw_range: float = 25.0  # degrees
    seed: int = 0  # training references' seed; held-out ones use seed + 1
    train_seed: int | None = None  # every policy's training seed (None: `seed`): a replicate on the same references
    workers: int = 0  # generation processes, and policies trained at once on a CPU (0: every core)
    human: str | None = None  # folder of AMASS .npz / BVH clips; None: constructed clips
    device: str = "cpu"  # training physics: cpu (C MuJoCo) or cuda (MuJoCo Warp), as `train --device`
    mixed_precision: bool = False  # bf16 autocast in every policy's PPO update, as `train --mixed-precision`
    base_position: str = "task"  # every policy's base-position reward, as `train --base-position`
    noise_min: float = 1.0  # each world's least share of Table II's observation noise, as `train --noise-min`
    # Reward terms changed from Table I for every policy, (name, weight, scale or None), as `train --reward`
    rewards: tuple[tuple[str, float, float | None], ...] = ()

    def check(self) -> None:
        problems = []
        from opt2skill.envs.config import BASE_POSITION, RewardConfig, with_rewards

        if self.base_position not in BASE_POSITION:
            problems.append(f"--base-position must be one of {', '.join(BASE_POSITION)}, got '{self.base_position}'")
        if not 0 <= self.noise_min <= 1:
            problems.append(f"--noise-min must be a share in [0, 1] of Table II's observation noise, got {self.noise_min}")
        try:  # the kinematic sources train with Pos inputs only: no force or torque term may pay
            with_rewards(RewardConfig(), tuple(tuple(change) for change in self.rewards), force=False, torque=False)
        except ConfigError as exc:
            problems.append(str(exc))
        if self.n_train < 1 or self.n_test < 1:
            problems.append(f"--n-train and --n-test must be >= 1, got {self.n_train} and {self.n_test}")
        if self.train_steps < 1 or not 1 <= self.num_envs <= 4096:
            problems.append(f"--train-steps must be >= 1 and --num-envs in [1, 4096], got {self.train_steps}, {self.num_envs}")
        if not 1.0 <= self.duration <= 60.0 or not 1.0 <= self.human_duration <= 60.0:
            problems.append(f"--duration and --human-duration must be in [1, 60] s, got {self.duration}, {self.human_duration}")
        if self.train_seed is not None and self.train_seed < 0:
            problems.append(f"--train-seed must be >= 0, got {self.train_seed}")
        if self.sweep_trials < 1:
            problems.append(f"--sweep-trials must be >= 1, got {self.sweep_trials}")
        if self.history not in self.histories:
            problems.append(f"the data rows' history {self.history} (--history) must be one of --histories "
                            f"{list(self.histories)}")
        if any(not 0 <= h <= 50 for h in self.histories):
            problems.append(f"--histories must be in [0, 50], got {list(self.histories)}")
        for name, (lo, hi) in (("speed", self.speed), ("clearance", self.clearance)):
            if not lo <= hi:
                problems.append(f"--{name} must be lo:hi with lo <= hi, got {lo}:{hi}")
        from opt2skill.envs import ABLATIONS

        if self.to_ablation not in ABLATIONS:
            problems.append(f"--to-ablation must be one of {', '.join(ABLATIONS)}, got '{self.to_ablation}'")
        if self.human is not None and not Path(self.human).is_dir():
            problems.append(f"--human {self.human} is not a folder of .npz or .bvh clips")
        if problems:
            raise ConfigError("; ".join(problems))
        from opt2skill.sim.devices import check_device

        check_device(self.device)  # e.g. cuda without a GPU: said before hours of data generation


SETTINGS: dict[str, dict[str, Any]] = {
    # Minutes on a 2-core CPU: the plumbing of every step, not the paper's comparison.
    # Moderate speeds and clearances, where the IK walks and the constructed human clips pass most often.
    "quick": dict(n_train=3, n_test=2, duration=6.0, human_duration=4.0, speed=(0.5, 1.0), clearance=(0.12, 0.16),
                  train_steps=3072, num_envs=32, stairs=(0.0, 0.08, 0.16), slopes=(0.0, 10.0, 20.0), sweep_trials=2,
                  sweep_start=0.6),
    # The paper's set-up (Sec. IV-B) at the scale the issue asks for; training at a CPU budget (docs/experiments.md).
    "full": dict(n_train=100, n_test=20, duration=14.0, human_duration=6.0, speed=(0.0, 1.5), clearance=(0.10, 0.20),
                 train_steps=20_000_000, num_envs=128, stairs=tuple(round(0.02 * i, 2) for i in range(9)),
                 slopes=tuple(2.5 * i for i in range(9)), sweep_trials=10, sweep_start=1.0),
}


ExperimentSettings.presets = SETTINGS


def resolve(setting: str, overrides: dict[str, Any] | None = None, kind: type[S] = ExperimentSettings) -> S:  # type: ignore[assignment]
    """`kind`'s named setting with the given options (those not None) replacing its sizes; checked."""
    if setting not in kind.presets:
        raise ConfigError(f"unknown setting '{setting}'; settings: {', '.join(kind.presets)}")
    values = {**kind.presets[setting], **{k: v for k, v in (overrides or {}).items() if v is not None}}
    names = {f.name for f in dataclasses.fields(kind)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"unknown experiment options {unknown}; known: {sorted(names - {'setting'})}")
    settings = kind(setting=setting, **values)
    settings.check()
    return settings


def with_defaults(identity: dict[str, Any], kind: type, only: dict[str, Any] | None = None) -> dict[str, Any]:
    """A folder's recorded identity with every setting added after it was made (of `kind`, and in
    `only` if given) at its default, as JSON reads it back (tuples as lists)."""
    defaults = json.loads(json.dumps({f.name: f.default for f in dataclasses.fields(kind)
                                      if f.default is not dataclasses.MISSING}))
    return {**{k: v for k, v in defaults.items() if k not in identity and (only is None or k in only)}, **identity}


def claim_folder(out: Path, settings: Settings) -> None:
    """Write OUT/experiment.json, or check that the one there is this experiment's."""
    path = Path(out) / IDENTITY_FILE
    mine = {"experiment": settings.experiment, **settings.identity()}
    if path.is_file():
        try:
            theirs = json.loads(path.read_text())
        except ValueError as exc:
            raise DataError(f"{path} is unreadable ({exc}); it is not an experiment folder this command made") from None
        theirs = with_defaults(theirs, type(settings), only=mine)
        if theirs != mine:
            keys = sorted(k for k in set(theirs) | set(mine) if theirs.get(k) != mine.get(k))
            shown = ", ".join(f"{k}: {theirs.get(k)!r} there, {mine.get(k)!r} now" for k in keys)
            raise ConfigError(f"{out} holds another experiment ({shown}); rerun with its settings to resume it, "
                              "or choose another --out")
        return
    # A `data` folder may be there: datasets copied in to be reused (each checks its own identity).
    if Path(out).is_dir() and any(p.name not in (".lock", "data") for p in Path(out).iterdir()):
        raise DataError(f"{out} is not empty and is not an experiment folder (no {IDENTITY_FILE}); choose another --out "
                        "(a new folder may hold only data/, datasets to reuse)")
    from opt2skill.data.atomic import write_json

    Path(out).mkdir(parents=True, exist_ok=True)
    write_json(path, mine)
