"""The config sections every task shares; a task's config subclasses `TaskConfig` and adds its own.

A subclass may give a shared section other defaults (walking keeps a larger minimum normal force)
by declaring the field again; `check()` checks the shared sections, then `check_own()` the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights, SolverSettings


@dataclass(frozen=True)
class TaskConfig:
    posture: Posture = field(default_factory=Posture)
    contact: ContactSettings = field(default_factory=ContactSettings)
    feasibility: FeasibilityWeights = field(default_factory=FeasibilityWeights)
    solver: SolverSettings = field(default_factory=SolverSettings)
    ranges: dict = field(default_factory=dict)  # parameter -> (low, high) sampling range

    def check(self) -> None:
        for section in (self.posture, self.contact, self.feasibility, self.solver):
            section.check()
        self.check_own()

    def check_own(self) -> None:
        """The task's own fields (sections it adds are checked here too)."""
