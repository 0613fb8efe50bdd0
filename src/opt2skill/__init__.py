"""Opt2Skill: whole-body trajectory optimization turned into robust humanoid skills."""

__version__ = "0.1.0"
