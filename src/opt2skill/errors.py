"""User-facing errors.

Anything a user can cause (bad parameter, unknown robot or task, corrupt file, diverging solver)
raises an `Opt2SkillError` whose message names the problem and what is allowed. The CLI prints
that message on one line and exits with status 2; it never shows a traceback for these.
"""


class Opt2SkillError(Exception):
    """Base class of errors caused by input, configuration or data, not by a bug."""


class ConfigError(Opt2SkillError):
    """A configuration file or parameter is missing, malformed or out of range."""


class ModelError(Opt2SkillError):
    """A robot model file is missing, malformed or disagrees with its configuration."""


class DataError(Opt2SkillError):
    """A dataset, checkpoint or exported file is missing, corrupt or of the wrong kind."""


class SolverError(Opt2SkillError):
    """An optimizer or simulation diverged or failed to produce a usable result."""


class DataWarning(UserWarning):
    """Something in the input was skipped or repaired; the work goes on (the CLI prints one line)."""
