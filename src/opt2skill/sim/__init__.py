"""Batched physics: N worlds of the robot stepped together, PD at the physics rate, arrays out.

`BatchedSim` is the interface the tracking task uses; `MujocoBatchedSim` implements it with C
MuJoCo (`mujoco.rollout` on a thread pool). docs/sim.md is the contract.
"""

from opt2skill.scene.terrain import Flat, Rough, Slope, Stairs, Terrain, TerrainGrid, flat, rough
from opt2skill.sim.base import BatchedSim, SimConfig, SimStep
from opt2skill.sim.mujoco_sim import MujocoBatchedSim
from opt2skill.sim.params import WorldParams, sample_uniform

__all__ = [
    "BatchedSim",
    "Flat",
    "MujocoBatchedSim",
    "SimConfig",
    "SimStep",
    "Rough",
    "Slope",
    "Stairs",
    "Terrain",
    "TerrainGrid",
    "WorldParams",
    "flat",
    "rough",
    "sample_uniform",
]
