"""Props: what the robot touches besides the ground (a box, a shelf, a desk, a door), as data.

A prop is a frozen description in SI units, world frame, posed by a position and a yaw. It gives its
MuJoCo geoms (`geoms()`: boxes at the prop's initial pose) and its contact surfaces (`surfaces()`:
the rectangles that hands, feet or other props touch, where trajectory optimization puts contacts).
A `Box` is a free body: only contacts move or hold it, it is never welded to a hand. Shelves and
desks are fixed: geoms of the world body. A `Door` is a panel on a vertical hinge whose spring and
damper close it: its pose moves with one hinge angle.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.mujoco_model import FLOOR_FRICTION

POST = 0.03  # m, side of the square posts under boards
NAME = re.compile(r"[A-Za-z0-9_]+\Z")  # prop names prefix MuJoCo names: no '/' or spaces


@dataclass(frozen=True, eq=False)
class Surface:
    """A rectangle a contact can sit on: `centre` on it, outward unit `normal`, in-plane unit `axes`
    (2, 3) and `half_size` along them (m), all in the world at the prop's initial pose. `moves` is
    true on a free body (the surface follows it)."""

    prop: str
    name: str
    centre: np.ndarray
    normal: np.ndarray
    axes: np.ndarray
    half_size: np.ndarray
    friction: float
    moves: bool

    def contains(self, point: np.ndarray, tol: float = 1e-6) -> bool:
        """Whether `point` (3,) lies on the rectangle (within `tol` m of its plane and its edges)."""
        d = np.asarray(point, dtype=float) - self.centre
        return bool(abs(d @ self.normal) <= tol and np.all(np.abs(self.axes @ d) <= self.half_size + tol))


@dataclass(frozen=True, eq=False)
class Geom:
    """A box geom: `name` (unique within its prop), centre, half sizes and orientation (w, x, y, z)."""

    name: str
    centre: np.ndarray
    half: np.ndarray
    quat: np.ndarray


@dataclass(frozen=True)
class Box:
    """A box on a free joint: `size` its full extents along its own x, y, z (m), `pos` its centre."""

    kind: ClassVar[str] = "box"
    fixed: ClassVar[bool] = False  # geoms of the world body
    free: ClassVar[bool] = True  # a body on a free joint (a door moves too, on its hinge)
    size: tuple[float, float, float] = (0.3, 0.3, 0.3)
    mass: float = 1.0  # kg, uniform density
    pos: tuple[float, float, float] = (0.5, 0.0, 0.8)
    yaw: float = 0.0  # rad, about z
    friction: float = 1.0
    # Torsional friction of the box's contacts (m, a contact patch's size; MuJoCo condim 4; 0 gives
    # point contacts). Hands pressing on two opposite faces hold the box's position, not its turn
    # about the line between them: without torsion a box held above its centre swings like an
    # undamped pendulum, and with much of it the box turns with the palms, whose rotation the
    # optimizer does not plan. 5 mm damps the swing (docs/trajopt.md has the measurements).
    torsion: float = 0.005
    name: str = "box"

    def __post_init__(self) -> None:
        where = f"box '{self.name}'"
        _name(self.name)
        _vector(where, "size", self.size, 3, 0.02, 1.5, "m")
        _number(where, "mass", self.mass, 0.01, 50.0, "kg")
        _vector(where, "pos", self.pos, 3, -100.0, 100.0, "m")
        _common(where, self.yaw, self.friction)
        _number(where, "torsion", self.torsion, 0.0, 0.1, "m")
        if self.pos[2] < self.size[2] / 2 - 1e-9:
            raise ConfigError(f"{where}: its bottom is below z = 0 (pos z {self.pos[2]:g} m < half its height "
                              f"{self.size[2] / 2:g} m)")

    @property
    def contact(self) -> tuple[int, tuple[float, float, float]]:
        """MuJoCo condim and friction (sliding, torsional, rolling) of the box's geom."""
        if self.torsion == 0.0:
            return 3, (self.friction, *FLOOR_FRICTION[1:])
        return 4, (self.friction, self.torsion, FLOOR_FRICTION[2])

    def geoms(self) -> list[Geom]:
        return [Geom(self.name, np.array(self.pos, float), np.array(self.size, float) / 2, _yaw_quat(self.yaw))]

    @property
    def inertia(self) -> np.ndarray:
        """Principal moments (3,) about the centre, uniform density, along the box's own axes."""
        a, b, c = self.size
        return self.mass / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])

    def surfaces(self) -> list[Surface]:
        """The six faces, named by the box's own axes: front (+x), back, left (+y), right, top, bottom."""
        rot, half, centre = _yaw_matrix(self.yaw), np.array(self.size, float) / 2, np.array(self.pos, float)
        out = []
        for name, axis, sign in (("front", 0, 1), ("back", 0, -1), ("left", 1, 1), ("right", 1, -1),
                                 ("top", 2, 1), ("bottom", 2, -1)):
            normal = sign * rot[:, axis]
            others = [a for a in range(3) if a != axis]
            out.append(Surface(self.name, name, centre + half[axis] * normal, normal, rot[:, others].T,
                               half[others], self.friction, moves=True))
        return out


@dataclass(frozen=True)
class Shelf:
    """Horizontal boards on four corner posts, standing on the floor. `pos` is the footprint's centre
    (x, y), `depth` its extent along its own x (the side facing the robot at yaw 0 is -x), `width`
    along its y; `boards` are the heights of the boards' top surfaces, lowest first."""

    kind: ClassVar[str] = "shelf"
    fixed: ClassVar[bool] = True
    free: ClassVar[bool] = False
    pos: tuple[float, float] = (0.7, 0.0)
    yaw: float = 0.0
    width: float = 0.8
    depth: float = 0.4
    boards: tuple[float, ...] = (0.8,)
    thickness: float = 0.03
    friction: float = 1.0
    name: str = "shelf"

    def __post_init__(self) -> None:
        where = _check_furniture(self)
        if not (isinstance(self.boards, tuple) and self.boards):
            raise ConfigError(f"{where}: boards must be a non-empty list of heights (m), got {self.boards!r}")
        _vector(where, "boards", self.boards, len(self.boards), self.thickness, 2.5, "m")
        gaps = np.diff(self.boards)
        if np.any(gaps <= self.thickness):
            raise ConfigError(f"{where}: board heights must increase by more than the thickness "
                              f"({self.thickness:g} m), got {list(self.boards)}")

    @property
    def contact(self) -> tuple[int, tuple[float, float, float]]:
        return _sliding(self.friction)

    def geoms(self) -> list[Geom]:
        return _boards_on_posts(self, [f"board_{i}" for i in range(len(self.boards))])

    def surfaces(self) -> list[Surface]:
        return _tops(self, [f"board_{i}" for i in range(len(self.boards))])


@dataclass(frozen=True)
class Desk:
    """A table top at `height` (its top surface) on four legs; `pos`, `yaw`, `width`, `depth` as for
    `Shelf`."""

    kind: ClassVar[str] = "desk"
    fixed: ClassVar[bool] = True
    free: ClassVar[bool] = False
    pos: tuple[float, float] = (0.7, 0.0)
    yaw: float = 0.0
    height: float = 0.9
    width: float = 1.2
    depth: float = 0.6
    thickness: float = 0.04
    friction: float = 1.0
    name: str = "desk"

    def __post_init__(self) -> None:
        where = _check_furniture(self)
        _number(where, "height", self.height, self.thickness + 0.05, 2.0, "m")

    @property
    def boards(self) -> tuple[float, ...]:
        return (self.height,)

    @property
    def contact(self) -> tuple[int, tuple[float, float, float]]:
        return _sliding(self.friction)

    def geoms(self) -> list[Geom]:
        return _boards_on_posts(self, ["top"])

    def surfaces(self) -> list[Surface]:
        return _tops(self, ["top"])


@dataclass(frozen=True)
class Door:
    """A door panel on a vertical hinge at `hinge` (x, y), closed by a spring and a damper.

    Closed, the panel stands in the plane through the hinge facing along `yaw` (at yaw 0 its faces
    look along x, the robot's side being -x) and reaches `width` m from the hinge towards -y (turned
    by yaw); it opens by turning about +z (the free edge towards +x at yaw 0), from 0 to `max_angle`,
    and a stop holds it at 0 (the frame). Hinge torque resisting an opening: stiffness * angle +
    damping * rate (MuJoCo's joint spring and damper, `springref` 0) plus the panel's inertia about
    the hinge. Its pose is the hinge frame's: (hinge x, y, 0) and the yaw plus the angle about z."""

    kind: ClassVar[str] = "door"
    fixed: ClassVar[bool] = False
    free: ClassVar[bool] = False
    hinge: tuple[float, float] = (0.6, 0.45)
    yaw: float = 0.0
    width: float = 0.8  # m, hinge to free edge
    height: float = 2.0  # m, the panel's extent from its bottom
    thickness: float = 0.04  # m
    bottom: float = 0.01  # m of gap under the panel
    mass: float = 8.0  # kg, uniform panel
    stiffness: float = 4.0  # N m / rad, the closing spring
    damping: float = 2.0  # N m s / rad
    max_angle: float = 1.9  # rad, the opening stop
    friction: float = 0.5  # of the panel's faces
    name: str = "door"

    def __post_init__(self) -> None:
        where = f"door '{self.name}'"
        _name(self.name)
        _vector(where, "hinge", self.hinge, 2, -100.0, 100.0, "m")
        _common(where, self.yaw, self.friction)
        _number(where, "width", self.width, 0.3, 2.0, "m")
        _number(where, "height", self.height, 0.5, 3.0, "m")
        _number(where, "thickness", self.thickness, 0.01, 0.15, "m")
        _number(where, "bottom", self.bottom, 0.0, 0.5, "m")
        _number(where, "mass", self.mass, 0.5, 100.0, "kg")
        _number(where, "stiffness", self.stiffness, 0.0, 200.0, "N m/rad")
        _number(where, "damping", self.damping, 0.0, 200.0, "N m s/rad")
        _number(where, "max_angle", self.max_angle, 0.2, 3.0, "rad")

    @property
    def contact(self) -> tuple[int, tuple[float, float, float]]:
        return _sliding(self.friction)

    @property
    def panel_centre(self) -> np.ndarray:
        """The panel's centre in the hinge frame (closed)."""
        return np.array([0.0, -self.width / 2, self.bottom + self.height / 2])

    @property
    def inertia(self) -> np.ndarray:
        """Principal moments (3,) about the panel's centre, along the hinge frame's axes."""
        a, b, c = self.thickness, self.width, self.height
        return self.mass / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])

    @property
    def hinge_inertia(self) -> float:
        """kg m^2 about the hinge axis: the panel's own about its centre plus m d^2 (its centre's distance)."""
        return float(self.inertia[2] + self.mass * (self.width / 2) ** 2)

    def hinge_torque(self, angle, rate, acceleration) -> np.ndarray:
        """N m the hands must apply about the hinge to move the door along (angle, rate, acceleration)."""
        return self.stiffness * np.asarray(angle) + self.damping * np.asarray(rate) + self.hinge_inertia * np.asarray(acceleration)

    def pose(self, angle) -> np.ndarray:
        """(..., 7) the hinge frame's pose (x y z qw qx qy qz) at hinge angles `angle` (rad)."""
        angle = np.asarray(angle, dtype=float)
        half = (self.yaw + angle) / 2
        out = np.zeros((*angle.shape, 7))
        out[..., :2] = self.hinge
        out[..., 3], out[..., 6] = np.cos(half), np.sin(half)
        return out

    def angle_of(self, pose: np.ndarray) -> np.ndarray:
        """The hinge angles (rad) of poses (..., 7) `pose` gives."""
        pose = np.asarray(pose, dtype=float)
        return np.angle(np.exp(1j * (2 * np.arctan2(pose[..., 6], pose[..., 3]) - self.yaw)))

    def panel_point(self, angle, along: float, height: float, side: float = -1.0) -> np.ndarray:
        """(..., 3) the world point `along` m from the hinge on the panel's face at `height` m above
        the floor, on the robot's side (`side` -1, the face towards -x at yaw 0) or the other (+1)."""
        angle = np.asarray(angle, dtype=float)
        heading = self.yaw + angle
        u = np.stack([np.sin(heading), -np.cos(heading), np.zeros_like(heading)], axis=-1)  # hinge to free edge
        n = self.face_normal(angle, side)
        return np.array([*self.hinge, height]) + along * u + (self.thickness / 2) * n

    def face_normal(self, angle, side: float = -1.0) -> np.ndarray:
        """(..., 3) the outward unit normal of the panel's face on `side` at hinge angles `angle`."""
        heading = self.yaw + np.asarray(angle, dtype=float)
        return -side * np.stack([-np.cos(heading), -np.sin(heading), np.zeros_like(heading)], axis=-1)

    def geoms(self) -> list[Geom]:
        """The closed panel, in the world."""
        rot = _yaw_matrix(self.yaw)
        centre = np.array([*self.hinge, 0.0]) + rot @ self.panel_centre
        half = np.array([self.thickness, self.width, self.height]) / 2
        return [Geom(self.name, centre, half, _yaw_quat(self.yaw))]

    def surfaces(self) -> list[Surface]:
        """The closed panel's two faces: `front` (the robot's side, -x at yaw 0) and `back`."""
        rot, (g,) = _yaw_matrix(self.yaw), self.geoms()
        return [Surface(self.name, name, g.centre + g.half[0] * sign * rot[:, 0], sign * rot[:, 0], rot[:, 1:].T,
                        g.half[1:], self.friction, moves=True) for name, sign in (("front", -1.0), ("back", 1.0))]


Prop = Box | Shelf | Desk | Door
PROP_KINDS: dict[str, type] = {cls.kind: cls for cls in (Box, Shelf, Desk, Door)}


def _sliding(friction: float) -> tuple[int, tuple[float, float, float]]:
    """MuJoCo condim and friction of a prop's geoms with sliding friction only (condim 3)."""
    return 3, (friction, *FLOOR_FRICTION[1:])


def _check_furniture(prop: Shelf | Desk) -> str:
    """Check what shelves and desks share (name, footprint, boards' thickness); returns the prop's
    name for messages."""
    where = f"{prop.kind} '{prop.name}'"
    _name(prop.name)
    _vector(where, "pos", prop.pos, 2, -100.0, 100.0, "m")
    _common(where, prop.yaw, prop.friction)
    _number(where, "width", prop.width, 0.2, 3.0, "m")
    _number(where, "depth", prop.depth, 0.1, 1.5, "m")
    _number(where, "thickness", prop.thickness, 0.005, 0.2, "m")
    return where


def _boards_on_posts(prop: Shelf | Desk, names: list[str]) -> list[Geom]:
    """Boards (tops at `prop.boards`) and four corner posts from the floor to the top board."""
    rot, quat = _yaw_matrix(prop.yaw), _yaw_quat(prop.yaw)
    origin = np.array([*prop.pos, 0.0])
    out = [Geom(name, origin + [0.0, 0.0, top - prop.thickness / 2],
                np.array([prop.depth / 2, prop.width / 2, prop.thickness / 2]), quat)
           for name, top in zip(names, prop.boards)]
    post_top = prop.boards[-1] - prop.thickness
    for i, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        local = np.array([sx * (prop.depth - POST) / 2, sy * (prop.width - POST) / 2, post_top / 2])
        out.append(Geom(f"post_{i}", origin + rot @ local, np.array([POST / 2, POST / 2, post_top / 2]), quat))
    return out


def _tops(prop: Shelf | Desk, names: list[str]) -> list[Surface]:
    rot = _yaw_matrix(prop.yaw)
    return [Surface(prop.name, name, np.array([*prop.pos, top]), np.array([0.0, 0.0, 1.0]), rot[:, :2].T,
                    np.array([prop.depth / 2, prop.width / 2]), prop.friction, moves=False)
            for name, top in zip(names, prop.boards)]


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _name(name: str) -> None:
    if not (isinstance(name, str) and NAME.match(name)):
        raise ConfigError(f"a prop name must be letters, digits or '_', got {name!r}")


def _common(where: str, yaw: float, friction: float) -> None:
    _number(where, "yaw", yaw, -np.pi, np.pi, "rad")
    _number(where, "friction", friction, 0.05, 3.0, "")


def _number(where: str, what: str, value, lo: float, hi: float, unit: str) -> None:
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not (ok and np.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{where}: {what} must be in [{lo:g}, {hi:g}] {unit}".rstrip() + f", got {value!r}")


def _vector(where: str, what: str, value, n: int, lo: float, hi: float, unit: str) -> None:
    if not (isinstance(value, tuple) and len(value) == n):
        raise ConfigError(f"{where}: {what} must be {n} numbers, got {value!r}")
    for v in value:
        _number(where, what, v, lo, hi, unit)
