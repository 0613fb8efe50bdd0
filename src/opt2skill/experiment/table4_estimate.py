"""What a table4 run is expected to cost on a 2-core CPU, from the per-item rates measured here
(docs/experiments.md), printed before it starts: the full setting is about 14 h. PPO's rate is
table3's on walks (128 worlds); the wipe's was not measured at that scale."""

from __future__ import annotations

import os

from opt2skill.experiment.table4_settings import TASK, Table4Settings

# Measured 2026-12-02 on 180 wipes of 11.4 s, 2 workers on the 2 cores (load 2): solve median 18.8 s,
# validation 1.0 s. The same solves took 96 s and 5 s when three other jobs shared the machine.
SOLVE_PER_MOTION_SECOND = 1.65  # s of wipe solve per s of motion
VALIDATION = 1.0  # s per reference (the expert's force replay included)
# The machine's environment steps/s of PPO, 128 worlds per policy, policies trained side by side (one per
# core, one thread each): 2 x 1177 on table3's walks, 2026-12-03 (1300 before the processes stopped
# oversubscribing the cores); not measured on the wipe at that scale.
TRAIN_STEPS_PER_S = 2350.0
MIXED_TRAIN_STEPS_PER_S = 6000.0  # the same with --mixed-precision (bf16 in the PPO update): 6.0k to 6.2k, 2026-12-03
# Environment steps/s distilling wipes, 64 worlds, two runs on the two cores (2026-12-02, before the
# thread fix, so pessimistic; not measured since).
DISTILL_STEPS_PER_S = 400.0
TRAIN_SETUP = 20.0  # s per policy: environment, references, checkpoints (29 to 69 s for 3,072 steps at load 6-7)
EVAL_STEP = 0.003  # s per policy step of one evaluation's batch of worlds: 153 s for 24 evaluations of 2,280 steps


def motion_seconds(s: Table4Settings) -> float:
    """Seconds of one wipe with the experiment's timing (its phase plan)."""
    from opt2skill.model import load_robot
    from opt2skill.tasks import get_task

    task = get_task(TASK, load_robot("digit"), s.task_config())
    return sum(phase.duration for phase in task.plan(task.param_space().sample(s.seed, 0)).phases)


def estimate(s: Table4Settings, references: int) -> dict[str, float]:
    """Hours of each stage for `references` references to generate (every set, not those on disk)."""
    workers = s.workers or os.cpu_count() or 1
    seconds = motion_seconds(s)
    frames = seconds * 200
    generate = references * (SOLVE_PER_MOTION_SECOND * seconds + VALIDATION) / min(workers, max(references, 1))
    rate = MIXED_TRAIN_STEPS_PER_S if s.mixed_precision else TRAIN_STEPS_PER_S
    train = len(s.ablations) * (TRAIN_SETUP + s.train_steps / rate + s.distill_steps / DISTILL_STEPS_PER_S)
    evaluate = (len(s.ablations) * len(s.forces) + len(s.transfer_desks)) * frames * EVAL_STEP  # one batch each
    return {"motion_s": seconds, "datasets_h": generate / 3600, "training_h": train / 3600, "evaluation_h": evaluate / 3600}


def describe(s: Table4Settings, references: int) -> str:
    e = estimate(s, references)
    total = e["datasets_h"] + e["training_h"] + e["evaluation_h"]
    return (f"expected on a 2-core CPU (rates measured on this project's; a machine loaded to 6-7 took twice as "
            f"long): {references} wipes of {e['motion_s']:.1f} s, {_time(e['datasets_h'])}; "
            f"{len(s.ablations)} policies x {_budget(s)}, {_time(e['training_h'])}; "
            f"evaluation {_time(e['evaluation_h'])}; "
            f"in all {_time(total)} (rerun the same command to resume)")


def _budget(s: Table4Settings) -> str:
    ppo = f"{s.train_steps:,} environment steps"
    return f"{s.distill_steps:,} distilled + {ppo} of PPO" if s.distill_steps else ppo


def _time(hours: float) -> str:
    return f"about {hours:.1f} h" if hours >= 1 else f"about {max(1, round(60 * hours))} min"
