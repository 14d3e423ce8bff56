"""Exact-intersection primitives the simulated scenes are made of.

A scene is a terrain (:mod:`.terrain`) plus a list of :class:`Primitive` solids: boxes,
vertical or tilted elliptic cylinders, ellipsoids and gable prisms (a box whose top is cut
by two roof planes). Each solid carries its class label and a :class:`Surface` (colour,
reflectance, texture). A solid with ``density_per_m > 0`` is a porous volume (a tree crown,
a bush): a ray entering it travels an exponentially distributed free path before it hits a
leaf, so some rays pass through. A solid with a :class:`Motion` moves back and forth along a
segment while the scanner sweeps, which leaves smeared returns (scanning artefacts).

:func:`pack_primitives` turns the solids into the flat float64 table the numba kernels read.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from semantic3d.core import N_CLASSES
from semantic3d.datasets.simulator.errors import SimulationConfigError


class Shape(IntEnum):
    """The solid a primitive describes, in its local frame centred on the origin."""

    BOX = 0
    """``|x| <= hx, |y| <= hy, |z| <= hz``."""
    CYLINDER = 1
    """``(x/hx)² + (y/hy)² <= 1, |z| <= hz`` (the axis is local z)."""
    ELLIPSOID = 2
    """``(x/hx)² + (y/hy)² + (z/hz)² <= 1``."""
    GABLE = 3
    """A box whose top is cut by two roof planes meeting in a ridge along local x:
    ``z <= hz - 2 hz |y| / hy`` (eaves at ``z = -hz``, ridge at ``z = hz``)."""


@dataclass(frozen=True, slots=True)
class Surface:
    """How a surface looks to the scanner and the camera.

    Attributes:
        rgb: base colour, 0..255 per channel.
        reflectance: laser reflectance in 0..1 (drives intensity).
        texture_amplitude: relative colour variation of the procedural texture, 0..1.
        texture_scale_m: size of the texture's patches (tiles, bricks, grass tufts).
        colour_noise: standard deviation of per-point colour noise, in colour levels.
    """

    rgb: tuple[int, int, int]
    reflectance: float
    texture_amplitude: float = 0.1
    texture_scale_m: float = 0.5
    colour_noise: float = 6.0

    def __post_init__(self) -> None:
        if len(self.rgb) != 3 or not all(0 <= c <= 255 for c in self.rgb):
            raise SimulationConfigError(
                f"surface rgb: expected 3 values in 0..255, found {self.rgb}"
            )
        if not 0.0 <= self.reflectance <= 1.0:
            raise SimulationConfigError(
                f"surface reflectance: expected 0..1, found {self.reflectance}"
            )
        if self.texture_scale_m <= 0.0 or self.texture_amplitude < 0 or self.colour_noise < 0:
            raise SimulationConfigError(
                "surface texture: expected texture_scale_m > 0 and non-negative amplitude and "
                f"noise, found {self.texture_scale_m}, {self.texture_amplitude}, "
                f"{self.colour_noise}"
            )

    def tinted(self, factor: float) -> Surface:
        """The same surface with its colour scaled by ``factor`` (clipped to 0..255)."""
        r, g, b = (min(255, max(0, round(c * factor))) for c in self.rgb)
        return Surface(
            (r, g, b),
            self.reflectance,
            self.texture_amplitude,
            self.texture_scale_m,
            self.colour_noise,
        )


@dataclass(frozen=True, slots=True)
class Motion:
    """Back-and-forth motion along a straight segment during the sweep.

    At scene time ``t`` (seconds) the primitive is displaced by ``a * direction`` where
    ``a`` runs from 0 to ``length_m`` and back at ``speed_m_s``, starting ``phase_m`` along
    the way. Primitives of one moving object share one motion, so they move rigidly.
    """

    direction: tuple[float, float, float]
    speed_m_s: float
    length_m: float
    phase_m: float = 0.0

    def __post_init__(self) -> None:
        norm = math.sqrt(sum(c * c for c in self.direction))
        if not math.isfinite(norm) or norm == 0.0:
            raise SimulationConfigError(
                f"motion direction: expected a non-zero vector, found {self.direction}"
            )
        if self.speed_m_s <= 0.0 or self.length_m <= 0.0:
            raise SimulationConfigError(
                "motion: expected speed_m_s > 0 and length_m > 0, found "
                f"{self.speed_m_s}, {self.length_m}"
            )
        object.__setattr__(self, "direction", tuple(c / norm for c in self.direction))

    def offset_at(self, time_s: float) -> float:
        """Distance travelled along ``direction`` from the start of the segment at ``time_s``."""
        period = 2.0 * self.length_m
        u = (self.speed_m_s * time_s + self.phase_m) % period
        return u if u <= self.length_m else period - u


@dataclass(frozen=True, slots=True)
class Primitive:
    """One solid of a scene.

    Attributes:
        shape: which solid (see :class:`Shape`).
        center: centre in world coordinates (metres).
        half_size: half extents along the local axes (metres, all > 0).
        label: class label value 1..8.
        surface: colour and reflectance.
        yaw_rad, pitch_rad, roll_rad: orientation; local-to-world rotation
            ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
        density_per_m: 0 for a solid; > 0 makes a porous volume whose free path is
            exponential with this rate (1/m).
        motion: ``None`` for a static primitive.
    """

    shape: Shape
    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    label: int
    surface: Surface
    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0
    density_per_m: float = 0.0
    motion: Motion | None = None

    def __post_init__(self) -> None:
        if len(self.center) != 3 or not all(math.isfinite(c) for c in self.center):
            raise SimulationConfigError(
                f"primitive center: expected 3 finite values, found {self.center}"
            )
        if len(self.half_size) != 3 or not all(h > 0.0 for h in self.half_size):
            raise SimulationConfigError(
                f"primitive half_size: expected 3 values > 0, found {self.half_size}"
            )
        if not 1 <= self.label <= N_CLASSES:
            raise SimulationConfigError(
                f"primitive label: expected a class value 1..{N_CLASSES}, found {self.label}"
            )
        if self.density_per_m < 0.0:
            raise SimulationConfigError(
                f"primitive density_per_m: expected >= 0, found {self.density_per_m}"
            )

    def rotation(self) -> NDArray[np.float64]:
        """The 3×3 local-to-world rotation (columns are the local axes in world coordinates)."""
        return rotation_matrix(self.yaw_rad, self.pitch_rad, self.roll_rad)

    def bounds(
        self, rotation: NDArray[np.float64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World axis-aligned bounds ``(lo, hi)``, including the whole motion segment
        (``rotation``: :meth:`rotation`, when the caller has it already)."""
        turn = self.rotation() if rotation is None else rotation
        extent = np.abs(turn) @ np.asarray(self.half_size)
        center = np.asarray(self.center)
        lo, hi = center - extent, center + extent
        if self.motion is not None:
            end = np.asarray(self.motion.direction) * self.motion.length_m
            lo = np.minimum(lo, lo + end)
            hi = np.maximum(hi, hi + end)
        return lo, hi


def rotation_matrix(
    yaw_rad: float, pitch_rad: float = 0.0, roll_rad: float = 0.0
) -> NDArray[np.float64]:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    >>> np.round(rotation_matrix(math.pi / 2) @ [1.0, 0.0, 0.0], 12).tolist()
    [0.0, 1.0, 0.0]
    """
    return rotation_matrices([yaw_rad], [pitch_rad], [roll_rad])[0]


# Column layout of the packed primitive table read by the kernels.
P_CENTER = 0  # 3: centre (world)
P_WORLD_TO_LOCAL = 3  # 9: rows of the world-to-local rotation
P_HALF = 12  # 3: half extents
P_MOTION_DIR = 15  # 3: unit motion direction
P_SPEED = 18  # speed (m/s), 0 for static
P_PATH = 19  # motion segment length (m)
P_PHASE = 20  # motion phase (m)
P_DENSITY = 21  # porous free-path rate (1/m), 0 for solids
P_RGB = 22  # 3: base colour
P_REFLECTANCE = 25
P_TEXTURE_AMPLITUDE = 26
P_TEXTURE_SCALE = 27
P_COLOUR_NOISE = 28
N_PARAMS = 29


@dataclass(frozen=True, slots=True)
class PackedPrimitives:
    """The primitives as flat arrays for the kernels (row ``i`` is primitive ``i``)."""

    params: NDArray[np.float64]
    shapes: NDArray[np.int32]
    labels: NDArray[np.uint8]
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]

    @property
    def n_primitives(self) -> int:
        """Number of primitives."""
        return int(self.shapes.shape[0])


def pack_surface(surface: Surface, row: NDArray[np.float64], start: int) -> None:
    """Write ``surface`` into ``row[start : start + 7]`` (rgb, reflectance, texture, noise)."""
    row[start : start + 3] = surface.rgb
    row[start + 3] = surface.reflectance
    row[start + 4] = surface.texture_amplitude
    row[start + 5] = surface.texture_scale_m
    row[start + 6] = surface.colour_noise


def pack_primitives(primitives: Sequence[Primitive]) -> PackedPrimitives:
    """Flatten ``primitives`` into the table layout above (plus world bounds per row).

    Column by column over every primitive (a scene holds thousands: a loop building each
    one's matrices ran alone for ~30 ms before a many-thread sweep could start); the
    same numbers as :meth:`Primitive.rotation` and :meth:`Primitive.bounds`.
    """
    n = len(primitives)
    params = np.zeros((n, N_PARAMS), np.float64)
    if n == 0:
        empty = np.zeros((0, 3), np.float64)
        return PackedPrimitives(params, np.zeros(0, np.int32), np.zeros(0, np.uint8), empty, empty)
    rotation = rotation_matrices(
        [prim.yaw_rad for prim in primitives],
        [prim.pitch_rad for prim in primitives],
        [prim.roll_rad for prim in primitives],
    )
    center = np.array([prim.center for prim in primitives], np.float64)
    half = np.array([prim.half_size for prim in primitives], np.float64)
    params[:, P_CENTER : P_CENTER + 3] = center
    params[:, P_WORLD_TO_LOCAL : P_WORLD_TO_LOCAL + 9] = rotation.transpose(0, 2, 1).reshape(n, 9)
    params[:, P_HALF : P_HALF + 3] = half
    moving = [i for i, prim in enumerate(primitives) if prim.motion is not None]
    direction = np.zeros((n, 3), np.float64)
    length = np.zeros(n, np.float64)
    for i in moving:
        motion = primitives[i].motion
        assert motion is not None
        direction[i] = motion.direction
        length[i] = motion.length_m
        params[i, P_SPEED] = motion.speed_m_s
        params[i, P_PHASE] = motion.phase_m
    params[moving, P_MOTION_DIR : P_MOTION_DIR + 3] = direction[moving]
    params[moving, P_PATH] = length[moving]
    params[:, P_DENSITY] = [prim.density_per_m for prim in primitives]
    surfaces = [prim.surface for prim in primitives]
    params[:, P_RGB : P_RGB + 3] = [surface.rgb for surface in surfaces]
    params[:, P_REFLECTANCE] = [surface.reflectance for surface in surfaces]
    params[:, P_TEXTURE_AMPLITUDE] = [surface.texture_amplitude for surface in surfaces]
    params[:, P_TEXTURE_SCALE] = [surface.texture_scale_m for surface in surfaces]
    params[:, P_COLOUR_NOISE] = [surface.colour_noise for surface in surfaces]
    shapes = np.array([int(prim.shape) for prim in primitives], np.int32)
    labels = np.array([prim.label for prim in primitives], np.uint8)
    extent = (np.abs(rotation) @ half[:, :, None])[:, :, 0]
    lower, upper = center - extent, center + extent
    end = direction[moving] * length[moving, None]
    lower[moving] = np.minimum(lower[moving], lower[moving] + end)
    upper[moving] = np.maximum(upper[moving], upper[moving] + end)
    return PackedPrimitives(params, shapes, labels, lower, upper)


def rotation_matrices(
    yaw_rad: Sequence[float], pitch_rad: Sequence[float], roll_rad: Sequence[float]
) -> NDArray[np.float64]:
    """``(n, 3, 3)``: :func:`rotation_matrix` of each angle triple (the same numbers: the
    same sines and cosines, the same products)."""
    n = len(yaw_rad)
    turns = np.zeros((3, n, 3, 3), np.float64)
    for axis, angles, (c0, s0, s1, c1) in (
        (0, yaw_rad, ((0, 0), (0, 1), (1, 0), (1, 1))),  # Rz
        (1, pitch_rad, ((0, 0), (2, 0), (0, 2), (2, 2))),  # Ry
        (2, roll_rad, ((1, 1), (1, 2), (2, 1), (2, 2))),  # Rx
    ):
        cos = np.array([math.cos(angle) for angle in angles], np.float64)
        sin = np.array([math.sin(angle) for angle in angles], np.float64)
        turn = turns[axis]
        turn[:, c0[0], c0[1]] = cos
        turn[:, s0[0], s0[1]] = -sin
        turn[:, s1[0], s1[1]] = sin
        turn[:, c1[0], c1[1]] = cos
        fixed = 2 - axis  # the axis the rotation keeps: z, y, x
        turn[:, fixed, fixed] = 1.0
    return turns[0] @ turns[1] @ turns[2]
