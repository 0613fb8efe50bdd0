"""Table III over replicates: the evaluations of Table III experiments that differ only in their
policies' training seed (`--train-seed`), pooled into one table per condition.

A replicate trains every policy again on the same references and evaluates it on the same held-out
ones, so a source's rollouts of all replicates are one sample (n = replicates x held-out references):
TO against IK is paired by (replicate, reference), TO against human unpaired, as in one experiment.
The paper trains one policy per source; a difference that holds over several training seeds is not
one seed's luck. The terrain sweeps are not pooled (each replicate's Fig. 3 stands on its own).
A replicate may train fewer history rows than the first run (`--histories 10`: the data rows alone);
the pooled table then holds the rows every replicate has.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.report import EvalReport
from opt2skill.experiment.runner import publish_table
from opt2skill.experiment.settings import IDENTITY_FILE, ExperimentSettings, with_defaults
from opt2skill.experiment.steps import DONE, Steps

# Identity keys that may differ between replicates: the policies' training seed, and the history rows
# (`histories`: a replicate of the data rows alone need not retrain every history; the pooled table
# holds the histories every replicate trained).
REPLICATE_KEYS = ("train_seed", "histories")
# A pooled rollout's index: the reference's generation index plus this times its replicate's position,
# so that TO and IK pair within a replicate (generation indices stay far below it).
REPLICATE_STRIDE = 1_000_000


def pool_table3(folders: list[Path], out: Path) -> dict[str, dict[str, str]]:
    """Write the pooled Table III (nominal and under Table II) of the replicates in `folders` into
    `out`; the written files of each. ConfigError unless they are replicates of one experiment."""
    if len(folders) < 2:
        raise ConfigError(f"pooling needs at least two replicate folders, got {len(folders)}")
    identities = [_identity(folder) for folder in folders]
    _check_replicates(folders, identities)
    settings = dataclasses.replace(_settings(identities[0]), histories=_shared_histories(identities))
    from opt2skill.experiment.table import NOMINAL, TABLE_II, build_table
    from opt2skill.experiment.table3 import TABLE_II_SUFFIX, policies

    seeds = [_training_seed(identity) for identity in identities]
    written = {}
    for suffix, condition in (("", NOMINAL), (TABLE_II_SUFFIX, TABLE_II)):
        reports, missing = {}, {}
        for key in policies(settings):
            found = [_report(folder, f"{key}{suffix}") for folder in folders]
            absent = [f"{folder}: {why}" for folder, (_, why) in zip(folders, found) if why]
            if absent:
                missing[key] = "; ".join(absent)
            else:
                reports[key] = pooled([report for report, _ in found])
        table = build_table(settings.setting, reports, missing, settings.histories, settings.history,
                            condition=condition, stem=f"table3-pooled{suffix}")
        table.notes.append(
            f"Pooled over {len(folders)} replicates (training seeds {', '.join(map(str, seeds))}; "
            f"{', '.join(map(str, folders))}): each row holds every replicate's rollouts on the same held-out "
            "references; TO and IK are paired by replicate and reference. The replicates' own tables are in "
            "their folders; the terrain sweeps are not pooled.")
        dropped = sorted({h for identity in identities for h in identity["histories"]} - set(settings.histories))
        if dropped:
            table.notes.append(f"History rows {', '.join(map(str, dropped))} are left out: not every replicate "
                               "trained them.")
        written[condition] = publish_table(table, out)
    return written


def pooled(reports: list[EvalReport]) -> EvalReport:
    """One report holding the rollouts of `reports` (replicates of one policy), each rollout's index
    offset by its replicate's position times `REPLICATE_STRIDE`."""
    first = reports[0]
    results = [dataclasses.replace(r, index=r.index + k * REPLICATE_STRIDE)
               for k, report in enumerate(reports) for r in report.results]
    policy = {**first.policy, "description": f"{len(reports)} replicates of {first.policy.get('description', 'a policy')}"}
    return dataclasses.replace(first, policy=policy, results=results,
                               elapsed=sum(report.elapsed for report in reports))


def _identity(folder: Path) -> dict[str, Any]:
    path = Path(folder) / IDENTITY_FILE
    if not path.is_file():
        raise DataError(f"{folder} is not an experiment folder (no {IDENTITY_FILE})")
    try:
        identity = json.loads(path.read_text())
    except ValueError as exc:
        raise DataError(f"{path} is unreadable ({exc})") from None
    if identity.get("experiment") != "table3":
        raise ConfigError(f"{folder} holds a '{identity.get('experiment')}' experiment; pooling reads table3 folders")
    return with_defaults(identity, ExperimentSettings)  # settings added since at their defaults, as a resume reads them


def _check_replicates(folders: list[Path], identities: list[dict[str, Any]]) -> None:
    """ConfigError naming the settings in which a folder differs from the first (other than the
    training seed), or a training seed used twice."""
    first = identities[0]
    for folder, identity in zip(folders[1:], identities[1:]):
        keys = sorted(k for k in set(first) | set(identity)
                      if k not in REPLICATE_KEYS and first.get(k) != identity.get(k))
        if keys:
            shown = ", ".join(f"{k}: {first.get(k)!r} in {folders[0]}, {identity.get(k)!r} in {folder}" for k in keys)
            raise ConfigError(f"{folder} is not a replicate of {folders[0]} (they differ in {shown}); replicates "
                              "differ only in --train-seed and --histories")
    seeds = [_training_seed(identity) for identity in identities]
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"two folders trained with the same seed ({seeds}); a replicate needs its own --train-seed")


def _shared_histories(identities: list[dict[str, Any]]) -> tuple[int, ...]:
    """The histories every replicate trained, in the first one's order."""
    return tuple(h for h in identities[0]["histories"] if all(h in identity["histories"] for identity in identities))


def _training_seed(identity: dict[str, Any]) -> int:
    return identity["train_seed"] if identity.get("train_seed") is not None else identity["seed"]


def _settings(identity: dict[str, Any]) -> ExperimentSettings:
    """The experiment's settings from its identity (lists back to tuples; settings added since at
    their defaults)."""
    names = {f.name for f in dataclasses.fields(ExperimentSettings)}
    values = {k: _tuples(v) for k, v in identity.items() if k in names}
    return ExperimentSettings(**values)


def _tuples(value):
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _report(folder: Path, name: str) -> tuple[EvalReport | None, str]:
    """(evaluation `name`'s report, '') or (None, why not): its file in the folder (which may have
    moved since), else where its step recorded it."""
    from opt2skill.eval.report import read_report
    from opt2skill.experiment.table3 import eval_dir

    record = Steps(folder, 0).record(f"eval-{name}")
    if record is None or record["status"] != DONE:
        return None, (record or {}).get("result", {}).get("reason", "not run")
    here = eval_dir(Path(folder), name) / "eval.json"
    return read_report(here if here.is_file() else Path(record["result"]["report"])), ""
