"""Which physics backend a device name selects, and one clear error when it cannot run here.

`cpu`: C MuJoCo (`MujocoBatchedSim`). `cuda` (or `cuda:K`): MuJoCo Warp on that GPU
(`WarpBatchedSim`, the optional extra `pip install 'opt2skill[gpu]'`). `warp-cpu`: MuJoCo Warp on
Warp's CPU device, for tests and smoke runs only (a few hundred physics steps/s).
"""

from __future__ import annotations

from collections.abc import Sequence

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.props import Prop
from opt2skill.scene.terrain import Flat, Terrain
from opt2skill.sim.base import BatchedSim, SimConfig

DEVICES = ("cpu", "cuda", "warp-cpu")
INSTALL = "pip install 'opt2skill[gpu]' (mujoco-warp and warp-lang, docs/training.md)"


def import_warp():
    """(warp, mujoco_warp), or ConfigError naming the install step."""
    try:
        import warp
        import mujoco_warp
    except ImportError as exc:
        raise ConfigError(f"the GPU physics backend needs MuJoCo Warp ({exc.name} is not installed): {INSTALL}") from None
    warp.config.quiet = True  # no banner, no per-module compile lines
    warp.config.log_level = getattr(warp, "LOG_WARNING", 30)
    return warp, mujoco_warp


def check_device(device: str) -> None:
    """ConfigError unless `device` names a backend that can run on this machine."""
    name = str(device)
    if name == "cpu":
        return
    if name != "warp-cpu" and name != "cuda" and not (name.startswith("cuda:") and name[5:].isdigit()):
        raise ConfigError(f"--device must be cpu, cuda, cuda:K or warp-cpu, got '{device}'")
    wp, _ = import_warp()
    if name == "warp-cpu":
        return
    count = wp.get_cuda_device_count()
    index = int(name[5:]) if ":" in name else 0
    if count == 0:
        raise ConfigError("--device cuda needs an NVIDIA GPU with a working CUDA driver, and Warp finds none on "
                          "this machine; train with --device cpu")
    if index >= count:
        raise ConfigError(f"--device {name}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")


def learner_device(device: str, processes: int = 1) -> str:
    """The torch device PPO learns on beside physics on `device`: the same GPU for `cuda` / `cuda:K`
    (rsl_rl's networks, rollout storage and updates there, the observations copied to it once per
    step), the CPU for `cpu` and `warp-cpu`. A group of processes (`rl.processes`) averages its
    gradients over gloo, so its learners stay on the CPU whatever the physics device."""
    name = str(device)
    return name if processes == 1 and (name == "cuda" or name.startswith("cuda:")) else "cpu"


def make_sim(robot: Robot, nworld: int, config: SimConfig, terrains: Sequence[Terrain] = (Flat(),),
             device: str = "cpu", prop_sets: Sequence[Sequence[Prop]] = ((),)) -> BatchedSim:
    """The batched simulator of `device` (see the module docstring). Only C MuJoCo simulates props
    (`prop_sets`, scene/slots.py); the Warp backend refuses them."""
    props = sorted({p.name for s in prop_sets for p in s})
    if props and device != "cpu":
        raise ConfigError(f"--device {device}: the Warp backend does not simulate props yet, and these references' "
                          f"scenes have props {props}; use --device cpu (C MuJoCo) for them (docs/sim.md)")
    check_device(device)
    if device == "cpu":
        from opt2skill.sim.mujoco_sim import MujocoBatchedSim

        return MujocoBatchedSim(robot, nworld, config, terrains=terrains, prop_sets=prop_sets)
    from opt2skill.sim.warp_sim import WarpBatchedSim

    return WarpBatchedSim(robot, nworld, config, terrains=terrains, device="cpu" if device == "warp-cpu" else device)
