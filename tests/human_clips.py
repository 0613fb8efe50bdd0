"""Small constructed human walking clips (no real clip ships in a PyPI or Debian package; docs/baselines.md).
They live in the library (`opt2skill.retarget.synthetic`), which the experiment command also uses."""

from opt2skill.retarget.synthetic import walking_joints

__all__ = ["walking_joints"]
