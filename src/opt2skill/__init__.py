"""Opt2Skill: whole-body trajectory optimization turned into robust humanoid skills."""

import os as _os
import sys as _sys

# Offscreen rendering without a display: MuJoCo reads MUJOCO_GL when it is first imported.
if _sys.platform.startswith("linux") and not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
