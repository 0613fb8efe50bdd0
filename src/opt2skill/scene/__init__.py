"""Scenes: the terrain and props a motion is made on, as data (`Scene`), and built into MuJoCo
(`build_model`). The ground geometry (`terrain`, `ground`) is shared with the batched simulator.
Nothing here imports `sim`, `envs` or `trajopt`, so every stage (the deploy player included) can
build a record's scene."""

from opt2skill.scene.build import add_scene, build_model, prop_hinge, prop_qpos, show_ground
from opt2skill.scene.description import RoughGround, Scene
from opt2skill.scene.props import Box, Desk, Door, Shelf, Surface
from opt2skill.scene.terrain import Flat, Slope, Stairs

__all__ = [
    "Box",
    "Desk",
    "Door",
    "Flat",
    "RoughGround",
    "Scene",
    "Shelf",
    "Slope",
    "Stairs",
    "Surface",
    "add_scene",
    "build_model",
    "prop_hinge",
    "prop_qpos",
    "show_ground",
]
