"""An evaluation's results: per-trajectory metrics, their mean ± SE, success and episode length;
written as JSON (the record) and Markdown (tables to paste), with the paper's Table III row as a
marked reference line.

The same report serves `opt2skill eval` (the training simulator), `opt2skill deploy-sim` (the
standalone 2 kHz player) and `opt2skill compare`, so their numbers line up column for column.
"""

from __future__ import annotations

import datetime
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.data.atomic import write_report_files
from opt2skill.data.record import FRAME_DT
from opt2skill.errors import DataError
from opt2skill.eval.metrics import METRICS, TrackingErrors
from opt2skill.eval.stats import Summary, success_rate, summarize

FORMAT = "opt2skill-eval"
FORMAT_VERSION = 1
TABLE_III = ("E_joint", "E_vel_x", "E_vel_yaw", "E_ee_hand", "E_ee_foot", "E_pos_x", "E_pos_y", "E_yaw")
TABLE_IV = ("E_force", "E_torque")
# The paper's Table III (mean ± SE over 20 references, policies evaluated in Agility's simulator).
# A reference line only: other simulator, other robot model, E_pos-y/E_yaw per the paper's "step".
PAPER_ROWS = {
    "Opt2Skill (paper, Table III)": {
        "E_joint": (0.03, 0.01), "E_vel_x": (4.86, 4.18), "E_vel_yaw": (0.06, 0.04), "E_ee_hand": (2.00, 0.76),
        "E_ee_foot": (5.23, 1.75), "E_pos_x": (1.14, 0.61), "E_pos_y": (0.06, 0.03), "E_yaw": (0.02, 0.01),
    },
}


def label(metric: str) -> str:
    """The paper's name of a metric: E_vel_x -> E_vel-x."""
    head, _, rest = metric.partition("_")
    return f"{head}_{rest.replace('_', '-')}"


def header(metric: str) -> str:
    return f"{label(metric)} ({METRICS[metric][0]})"


def mean_se(s: Summary | tuple[float, float] | None) -> str:
    if s is None:
        return "-"
    if not isinstance(s, Summary):  # a printed figure of the paper, as printed
        return f"{s[0]:.2f} ± {s[1]:.2f}"
    mean, se = s.mean, s.se
    if not np.isfinite(mean):
        return "-"
    return f"{mean:.3g} ± {se:.2g}" if np.isfinite(se) else f"{mean:.3g}"


@dataclass
class TrajectoryResult:
    index: int  # generation index of the reference
    params: dict[str, Any]
    seen: bool | None  # the policy trained on this reference
    cause: str  # why the rollout ended: "time_out" when it reached the reference's end
    frames: int  # frames tracked (the start frame included)
    reference_frames: int
    errors: TrackingErrors
    task_metrics: dict[str, tuple[float, str]] = field(default_factory=dict)  # the task's own: name -> (value, unit)

    @property
    def fell(self) -> bool:
        return self.errors.fell

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "params": self.params, "seen_in_training": self.seen, "cause": self.cause,
                "frames": self.frames, "reference_frames": self.reference_frames, **self.errors.as_dict(),
                "task_metrics": {k: {"value": v, "unit": u} for k, (v, u) in self.task_metrics.items()}}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrajectoryResult:
        missing = [k for k in (*METRICS, "index", "params", "cause", "frames", "fell", "reference_frames") if k not in d]
        if missing:
            raise DataError(f"an evaluation report's trajectory lacks {missing}")
        values = {k: (float("nan") if d[k] is None else float(d[k])) for k in METRICS}
        # absent from reports written before they existed
        pace, turn, lead = (float("nan") if d.get(k) is None else float(d[k]) for k in ("pace", "turn", "lead"))
        errors = TrackingErrors(**values, frames=int(d["frames"]), fell=bool(d["fell"]), pace=pace, turn=turn,
                                lead=lead)
        try:
            task = {k: (float(v["value"]), str(v["unit"])) for k, v in d.get("task_metrics", {}).items()}
        except (TypeError, KeyError, ValueError, AttributeError):
            raise DataError("an evaluation report's task metrics are not {name: {value, unit}}") from None
        return cls(int(d["index"]), d["params"], d["seen_in_training"], d["cause"], int(d["frames"]),
                   int(d["reference_frames"]), errors, task)


@dataclass
class EvalReport:
    kind: str  # "eval" (training simulator) or "deploy-sim" (standalone player)
    policy: dict[str, Any]  # what was evaluated (run, checkpoint, iteration / ONNX file, training provenance)
    references: dict[str, Any]  # eval.references.ReferenceSet.to_dict()
    options: dict[str, Any]  # randomization, noise, seed; the player's rates, latency, noise
    results: list[TrajectoryResult]
    elapsed: float = 0.0  # s, wall
    provenance: dict[str, Any] = field(default_factory=dict)
    created: str = field(default_factory=lambda: datetime.datetime.now().isoformat(timespec="seconds"))

    # ------------------------------------------------------------ figures

    def summary(self) -> dict[str, Summary]:
        return summarize([r.errors for r in self.results])

    def task_summary(self) -> dict[str, tuple[float, float, int, str]]:
        """Each task metric over the references: (mean, SE, n, unit)."""
        names = dict.fromkeys(k for r in self.results for k in r.task_metrics)
        out = {}
        for name in names:
            values = np.array([r.task_metrics[name][0] for r in self.results if name in r.task_metrics])
            unit = next(r.task_metrics[name][1] for r in self.results if name in r.task_metrics)
            se = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else float("nan")
            out[name] = (float(values.mean()), se, len(values), unit)
        return out

    @property
    def success_rate(self) -> float:
        return success_rate([r.errors for r in self.results])

    def pace_summary(self) -> dict[str, float] | None:
        """Median, min, max and n of the references' signed paces (`metrics.TrackingErrors.pace`);
        None when no reference has one (stepping in place, or a report older than the pace)."""
        return _median_range([r.errors.pace for r in self.results])

    def turn_summary(self) -> dict[str, float] | None:
        """Median of the references' signed final yaw errors (`metrics.TrackingErrors.turn`, rad) and
        how many turned left (> 0) and right; None for a report older than the turn."""
        turns = np.array([r.errors.turn for r in self.results])
        turns = turns[np.isfinite(turns)]
        if not len(turns):
            return None
        return {"median": float(np.median(turns)), "left": int((turns > 0).sum()), "right": int((turns < 0).sum()),
                "n": len(turns)}

    def lead_summary(self) -> dict[str, float] | None:
        """Median, min, max and n of the references' leads (`metrics.TrackingErrors.lead`, m/s ahead of
        the reference); None for a report older than the lead."""
        return _median_range([r.errors.lead for r in self.results])

    @property
    def mean_episode_length(self) -> float:
        """Mean seconds tracked before the episode ended (a reference's full length when it succeeded)."""
        return float(np.mean([(r.frames - 1) * FRAME_DT for r in self.results]))

    @property
    def mean_episode_fraction(self) -> float:
        return float(np.mean([(r.frames - 1) / max(r.reference_frames - 1, 1) for r in self.results]))

    def key(self) -> dict[str, Any]:
        """What decides the numbers: the same key means a cached report can be reused."""
        return {"kind": self.kind, "policy": self.policy.get("key"), "options": self.options,
                "references": {k: self.references[k] for k in ("dataset", "indices", "fingerprints")}}

    # ------------------------------------------------------------ files

    def to_dict(self) -> dict[str, Any]:
        summary = self.summary()
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION, "kind": self.kind, "created": self.created,
            "policy": self.policy, "references": self.references, "options": self.options,
            "summary": {name: {"mean": s.mean, "se": s.se, "n": s.n, "unit": METRICS[name][0]} for name, s in summary.items()},
            "success_rate": self.success_rate, "mean_episode_length_s": self.mean_episode_length,
            "mean_episode_fraction": self.mean_episode_fraction, "pace": self.pace_summary(),
            "turn": self.turn_summary(), "lead": self.lead_summary(),
            "trajectories": [r.to_dict() for r in self.results],
            "task_summary": {k: {"mean": m, "se": se, "n": n, "unit": u} for k, (m, se, n, u) in self.task_summary().items()},
            "paper": {row: {k: {"mean": m, "se": s} for k, (m, s) in values.items()} for row, values in PAPER_ROWS.items()},
            "elapsed_s": self.elapsed, "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EvalReport:
        return cls(d["kind"], d["policy"], d["references"], d["options"],
                   [TrajectoryResult.from_dict(t) for t in d["trajectories"]], d.get("elapsed_s", 0.0),
                   d.get("provenance", {}), d.get("created", ""))

    def write(self, out_dir: Path, stem: str = "eval") -> tuple[Path, Path]:
        """OUT_DIR/STEM.json and OUT_DIR/STEM.md, each written atomically."""
        return write_report_files(out_dir, stem, self.to_dict(), self.markdown())

    # ------------------------------------------------------------ tables

    def title(self) -> str:
        return self.policy.get("name", "policy")

    def table_iii_rows(self, paper: bool = True) -> list[list[str]]:
        s = self.summary()
        rows = [[self.title(), *(mean_se(s[m]) for m in TABLE_III)]]
        if paper:
            rows += [[name, *(mean_se(values[m]) for m in TABLE_III)] for name, values in PAPER_ROWS.items()]
        return rows

    def extra_rows(self) -> list[list[str]]:
        s = self.summary()
        n = len(self.results)
        fallen = sum(r.fell for r in self.results)
        return [[self.title(), *(mean_se(s[m]) for m in TABLE_IV), f"{self.success_rate:.0%} ({n - fallen}/{n})",
                 f"{self.mean_episode_length:.2f} s ({self.mean_episode_fraction:.0%})"]]

    def ends_text(self) -> str:
        """Why the rollouts ended, most common first ("time_out": at the reference's end): a low
        success rate reads differently when the policy falls than when it drifts off the reference."""
        ends = Counter(r.cause for r in self.results).most_common()
        return ", ".join(f"{cause} {count}" for cause, count in ends)

    def trajectory_rows(self) -> list[list[str]]:
        rows = []
        for r in self.results:
            e = r.errors.as_dict()
            seen = {True: "yes", False: "no", None: "?"}[r.seen]
            rows.append([str(r.index), seen, r.cause, f"{(r.frames - 1) * FRAME_DT:.2f}",
                         *(_num(e[m]) for m in (*TABLE_III, *TABLE_IV)), _num(r.errors.pace), _num(r.errors.turn),
                         _num(r.errors.lead)])
        return rows

    def markdown(self) -> str:
        p, o = self.policy, self.options
        lines = [f"# {'Evaluation' if self.kind == 'eval' else 'Sim-to-sim evaluation (standalone player)'}: {self.title()}", ""]
        lines += [f"- policy: {p.get('description', '')}", f"- references: {self.references['note']}",
                  f"- options: {', '.join(f'{k}={v}' for k, v in o.items())}",
                  f"- created {self.created}, {self.elapsed:.0f} s, code {self.provenance.get('code_version', '?')}", ""]
        lines += ["## Tracking (Table III; mean ± SE over references)", ""]
        lines += _markdown_table(["policy", *(header(m) for m in TABLE_III)], self.table_iii_rows())
        lines += ["", "The paper's row is a reference line (Agility's simulator, their Digit model), not a result of "
                  "this code. E_pos-y and E_yaw are per 200 Hz step here (docs/eval.md).", ""]
        pace = self.pace_summary()
        if pace is not None:
            lines += [f"Pace (distance covered along the reference's heading over its path length; E_pos-x with its "
                      f"sign, 1 on pace): median {pace['median']:.2f}, {pace['min']:.2f} to {pace['max']:.2f} over "
                      f"{pace['n']} references.", ""]
        turn = self.turn_summary()
        if turn is not None:
            lines += [f"Turn (the final yaw error with its sign, tracked - reference; E_yaw with its sign, > 0 left): "
                      f"median {turn['median']:+.3f} rad; left in {turn['left']}, right in {turn['right']} of "
                      f"{turn['n']} references.", ""]
        lead = self.lead_summary()
        if lead is not None:
            lines += [f"Lead (the final along-heading error over the time tracked, m/s ahead of the reference; E_pos-x "
                      f"without the division by the path length): median {lead['median']:+.3f} m/s, "
                      f"{lead['min']:+.3f} to {lead['max']:+.3f} over {lead['n']} references.", ""]
        lines += ["## Contact force, torque, success (Table IV quantities)", ""]
        lines += _markdown_table(["policy", *(header(m) for m in TABLE_IV), "success (falls counted)", "mean episode length"],
                                 self.extra_rows())
        lines += ["", f"Episode ends: {self.ends_text()}."]
        task = self.task_summary()
        if task:
            lines += ["", "## Task metrics (the task's own; mean ± SE over references)", ""]
            lines += _markdown_table(["policy", *(f"{k} ({u})" if u else k for k, (_, _, _, u) in task.items())],
                                     [[self.title(), *(mean_se(Summary(m, se, n)) for m, se, n, _ in task.values())]])
        lines += ["", "## Per reference", ""]
        lines += _markdown_table(["index", "trained on", "end", "tracked (s)", *(label(m) for m in (*TABLE_III, *TABLE_IV)), "pace",
                                  "turn (rad)", "lead (m/s)"],
                                 self.trajectory_rows())
        return "\n".join(lines) + "\n"


def read_report(path: Path) -> EvalReport:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{path} is not a readable evaluation report: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("format_version") != FORMAT_VERSION:
        raise DataError(f"{path} is not an opt2skill evaluation report of format version {FORMAT_VERSION}")
    return EvalReport.from_dict(data)


def _num(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.3g}"


def _markdown_table(head: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return out


def _median_range(values: list[float]) -> dict[str, float] | None:
    """Median, min, max and n of the finite values; None when there are none."""
    finite = np.array(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if not len(finite):
        return None
    return {"median": float(np.median(finite)), "min": float(finite.min()), "max": float(finite.max()), "n": len(finite)}
