"""Procedural articulated objects: hand tools modelled on the Progress Tools objects of NARF22, and
objects with several joints (a desk lamp, a parallel gripper, a cabinet).

``build_tool(name, out_dir, seed)`` writes a URDF and one textured mesh per link::

    out_dir/object.urdf
    out_dir/meshes/<link>.obj   <link>.mtl   <link>.png

Every link is a handful of solid prisms (2-D outlines extruded along z, each a closed mesh) and has
one texture atlas: its top faces, its bottom faces and its side walls, painted by mapping each
texel back to the 3-D point it covers (:mod:`.textures`). The OBJ files hold a single shape and a
single material (``mtllib`` + ``map_Kd``) with ``vt`` coordinates, which is what pybullet needs to
show the texture; yourdfpy/trimesh load them as ``TextureVisuals``.

Frames (metres, radians): each tool lies in the xy plane of its root link with +z up, so a tool
lying flat on a table has its root +z pointing up; the root frame sits

- at the pivot for the pliers (jaws towards +x, revolute joint ``pivot`` about +z, 0 = closed);
- at the fixed jaw's pad face for the clamp (bar along +x, jaws towards -y, prismatic joint
  ``jaw_opening`` along +x whose value is the gap between the two pads).

Tools (links root first):

- ``clamp``: ``bar`` (0.32 m steel bar with ruler marks, fixed jaw, pistol grip; 0.325 m overall) and
  ``moving_jaw``; prismatic ``jaw_opening``, 0.02 - 0.20 m. Yellow ribbed grip, orange dotted pads.
- ``lineman-a``: ``lower_half`` and ``upper_half`` (the one on top at the pivot); revolute
  ``pivot``, 0 - 0.5 rad. 0.20 m long, square nose, blue ribbed grips.
- ``lineman-b``: the same links and joint; 0.22 m, rounded nose, red grips with black dots.
- ``longnose``: the same links, ``pivot`` 0 - 0.6 rad; 0.20 m, long thin jaws, yellow knurled grips.

Objects with several joints (joint origins place each link's frame; see each design's docstring):

- ``lamp``: ``base`` (round foot, +z up), ``lower_arm``, ``upper_arm``, ``head``; a chain of revolute
  joints ``shoulder`` (-0.5 - 0.5 rad), ``elbow`` (-0.2 - 0.8), ``head_tilt`` (-0.5 - 0.9) about
  parallel horizontal axes. Thin arms (16 x 12 mm), 0.45 m tall at most.
- ``gripper``: ``palm``, ``finger_left``, ``finger_right``; prismatic ``finger_left`` along +y and
  ``finger_right`` along -y, 0 - 0.04 m each. 0.19 x 0.18 m, lying flat like the tools.
- ``cabinet``: ``body`` (+z up, fronts facing +x), ``drawer_lower``, ``drawer_upper``, ``door``;
  prismatic drawers along +x (0 - 0.16 m) and a revolute ``door`` on a vertical hinge (0 - 1.75 rad).
  0.22 x 0.32 x 0.25 m closed.

The two pliers halves differ in grip tone and printed marks; the links of the other objects in
colour and marks. Inertial frames coincide with the link frames (mass and inertia about the link
origin), so that pybullet's base pose *is* the URDF root pose. The seed changes the texture noise
only; shapes, sizes and limits are fixed per object.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
import shapely
import trimesh
from numpy.typing import NDArray
from PIL import Image, ImageDraw
from shapely.affinity import scale as _scale_geometry
from shapely.geometry import LineString, MultiPolygon, Point, Polygon, box
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

from narf_core.data.synth.textures import (
    Box,
    Disk,
    Dots,
    FloatArray,
    Mark,
    Paint,
    Rgb,
    Ribs,
    Surface,
    Ticks,
    ValueNoise,
    rotated_mask,
    text_mask,
    to_uint8,
)

TOOLS: tuple[str, ...] = ("clamp", "lineman-a", "lineman-b", "longnose", "lamp", "gripper", "cabinet")

_TEXELS_PER_M = 2500.0  # 0.4 mm texels: finer than a 640x480 pixel on a tool 0.3 m from the camera
_PAD = 2  # texels of margin around every atlas island, so bilinear filtering never bleeds across
_MIN_WIDTH = 256  # atlas width in texels at least (small links would otherwise get tall, thin atlases)
_MAX_EDGE = 0.01  # outlines are split into edges no longer than this (metres)
_SMOOTH_COS = np.cos(np.radians(35.0))  # side walls meeting at a shallower angle share a normal


# ---------------------------------------------------------------------------------------------
# Public API


@dataclass(frozen=True)
class ToolSpec:
    """The configurations a synthetic dataset of tool ``name`` uses (docs/design.md §3, the paper's Table I).

    ``train_configurations`` are the few configurations seen in training (also used by the ``test``
    split); ``novel_configurations`` are absent from training. Each is ``{joint_name: value}``.
    ``views`` are the fields of :class:`~narf_core.data.synth.generate.ViewSampling` this object sets
    apart from the rig's (each a ``(low, high)`` range): ``distance`` (metres) for an object too
    large for the rig's, so that it stays in view like the tools do; ``azimuth_deg`` and
    ``elevation_deg`` for one that stands against a wall and is seen from in front of it.
    """

    name: str
    train_configurations: list[dict[str, float]]
    novel_configurations: list[dict[str, float]]
    views: dict[str, tuple[float, float]] = field(default_factory=dict)


# joint name, train values, novel values (paper: 4 + 3 clamp, 1 + 3 lineman's, 1 + 1 longnose)
_SPECS: dict[str, tuple[str, tuple[float, ...], tuple[float, ...]]] = {
    "clamp": ("jaw_opening", (0.05, 0.09, 0.13, 0.17), (0.07, 0.12, 0.19)),
    "lineman-a": ("pivot", (0.02,), (0.15, 0.30, 0.45)),
    "lineman-b": ("pivot", (0.03,), (0.12, 0.25, 0.40)),
    "longnose": ("pivot", (0.02,), (0.35,)),
}

# Objects with several joints: configurations as fractions of each joint's range, in the order of
# the design's joints. Train: a maximin Latin hypercube of 8 (each joint takes 8 distinct values
# from 5% to 95% of its range, so that joints vary together); novel: 4 configurations in the gaps
# between them, each joint at a value no train configuration has.
_SPLITS_BY_JOINTS: dict[int, tuple[tuple[tuple[float, ...], ...], tuple[tuple[float, ...], ...]]] = {
    2: (
        ((0.05, 0.56), (0.18, 0.18), (0.31, 0.82), (0.44, 0.44), (0.56, 0.05), (0.69, 0.95), (0.82, 0.31), (0.95, 0.69)),
        ((0.625, 0.625), (0.25, 0.625), (0.625, 0.25), (0.25, 0.375)),
    ),
    3: (
        (
            (0.05, 0.82, 0.44), (0.18, 0.31, 0.31), (0.31, 0.44, 0.82), (0.44, 0.95, 0.95),
            (0.56, 0.69, 0.18), (0.69, 0.18, 0.05), (0.82, 0.05, 0.69), (0.95, 0.56, 0.56),
        ),
        ((0.5, 0.75, 0.625), (0.625, 0.375, 0.5), (0.25, 0.625, 0.25), (0.5, 0.25, 0.25)),
    ),
}

# Objects seen otherwise than the rig sees the tools. The cabinet overflows the frame at the rig's
# nearest distance (0.4 m: it is 0.32 m wide, 0.45 m with its door open), so it is seen from farther
# away; and it stands against a wall, its front (+x) to the room, so a robot sees its drawers and
# door from in front of it and from about their height, never from behind or from straight above.
_VIEWS: dict[str, dict[str, tuple[float, float]]] = {
    "cabinet": {"distance": (0.6, 1.3), "azimuth_deg": (-75.0, 75.0), "elevation_deg": (10.0, 50.0)},
}


def tool_spec(name: str) -> ToolSpec:
    """The train and novel configurations of object ``name`` (one of :data:`TOOLS`), and its camera
    distances if it has its own."""
    _check_name(name)
    if name in _SPECS:
        joint, train, novel = _SPECS[name]
        return ToolSpec(name, [{joint: v} for v in train], [{joint: v} for v in novel])
    joints = _DESIGNS[name]().joints
    train, novel = _SPLITS_BY_JOINTS[len(joints)]

    def configuration(fractions: tuple[float, ...]) -> dict[str, float]:
        return {j.name: round(j.lower + f * (j.upper - j.lower), 4) for j, f in zip(joints, fractions)}

    return ToolSpec(
        name, [configuration(f) for f in train], [configuration(f) for f in novel], dict(_VIEWS.get(name, {}))
    )


def build_tool(name: str, out_dir: Path, seed: int = 0) -> Path:
    """Write tool ``name``'s URDF, meshes and textures under ``out_dir``; returns the URDF's path.

    The same ``(name, seed)`` gives byte-identical files. Mesh paths in the URDF are relative
    (``meshes/<link>.obj``), so the folder can be moved as a whole.
    """
    _check_name(name)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"out_dir {str(out_dir)!r} exists and is not a directory")
    design = _DESIGNS[name]()
    mesh_dir = out_dir / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    inertials = []
    for index, link in enumerate(design.links):
        mesh, atlas = _link_mesh(link, design.texels_per_m)
        texture = _paint_atlas(link, atlas, ValueNoise((int(seed), index)))
        Image.fromarray(texture).save(mesh_dir / f"{link.name}.png", format="PNG", compress_level=6)
        (mesh_dir / f"{link.name}.mtl").write_text(_mtl_text(link.name))
        (mesh_dir / f"{link.name}.obj").write_text(_obj_text(link.name, mesh, atlas))
        inertials.append(_inertial(link))
    urdf_path = out_dir / "object.urdf"
    urdf_path.write_text(_urdf_text(name, design, inertials))
    return urdf_path


def _check_name(name: str) -> None:
    if name not in TOOLS:
        raise ValueError(f"unknown tool {name!r}; known tools: {', '.join(TOOLS)}")


# ---------------------------------------------------------------------------------------------
# Tool descriptions


@dataclass(frozen=True)
class _Prism:
    """A solid: ``outline`` (xy polygon, metres) extruded over ``z = (bottom, top)``."""

    outline: Polygon
    z: tuple[float, float]
    surface: Surface
    density: float  # kg / m^3


@dataclass(frozen=True)
class _Link:
    name: str
    prisms: tuple[_Prism, ...]
    marks: tuple[Mark, ...] = ()


@dataclass(frozen=True)
class _Joint:
    """A URDF joint; ``xyz``/``rpy`` is its origin ``T_parent_joint`` and ``axis`` lies in the joint frame."""

    name: str
    kind: Literal["revolute", "prismatic"]
    parent: str
    child: str
    axis: tuple[float, float, float]
    lower: float
    upper: float
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class _Design:
    """An object: its links (the root first) and joints; ``texels_per_m`` sets its textures' resolution."""

    links: tuple[_Link, ...]
    joints: tuple[_Joint, ...]
    texels_per_m: float = _TEXELS_PER_M


_STEEL, _COATED_STEEL, _PLASTIC, _RUBBER, _WOOD, _PLYWOOD = 7850.0, 5000.0, 1150.0, 1200.0, 700.0, 600.0


def _prisms(outline: shapely.Geometry, z: tuple[float, float], surface: Surface, density: float) -> tuple[_Prism, ...]:
    """One prism per polygon of ``outline`` (slivers dropped), with edges split to at most ``_MAX_EDGE``."""
    out = []
    for polygon in shapely.get_parts(outline):
        if not isinstance(polygon, Polygon) or polygon.area < 1e-8:
            continue
        clean = orient(shapely.segmentize(polygon.simplify(1e-5), _MAX_EDGE), 1.0)
        out.append(_Prism(clean, z, surface, density))
    return tuple(out)


def _rounded(polygon: Polygon | MultiPolygon, radius: float) -> Polygon | MultiPolygon:
    """``polygon`` with its convex corners rounded to ``radius`` (a morphological opening)."""
    return polygon.buffer(-radius, quad_segs=3).buffer(radius, quad_segs=3)


def _catmull_rom(points: Sequence[Sequence[float]], per_segment: int = 8) -> FloatArray:
    """A smooth curve ``[m, k]`` through control ``points [n, k]`` (uniform Catmull-Rom)."""
    p = np.asarray(points, dtype=np.float64)
    padded = np.concatenate([p[:1], p, p[-1:]])
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)[:, None]
    pieces = []
    for i in range(len(p) - 1):
        p0, p1, p2, p3 = padded[i : i + 4]
        a, b, c = -p0 + p2, 2 * p0 - 5 * p1 + 4 * p2 - p3, -p0 + 3 * p1 - 3 * p2 + p3
        pieces.append(p1 + 0.5 * (a * t + b * t**2 + c * t**3))
    return np.concatenate([*pieces, p[-1:]])


# --- pliers -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _PliersLook:
    """Colours and marks of one pair of pliers; ``*_upper`` / ``*_lower`` tell the halves apart."""

    steel: Surface
    jaw_steel: Surface
    grip_upper: Surface
    grip_lower: Surface
    marks_upper: tuple[Mark, ...]
    marks_lower: tuple[Mark, ...]


@dataclass(frozen=True)
class _PliersShape:
    """Pliers geometry in the pivot frame (metres); the upper half's jaw lies on +y.

    ``jaw``: ``(x, half width)`` from the pivot (x = 0) to the tip; ``handle``: ``(x, inner
    offset from the centre line, width)`` from the pivot back to the handle's end (x < 0).
    """

    jaw: tuple[tuple[float, float], ...]
    handle: tuple[tuple[float, float, float], ...]
    pivot_radius: float
    head_thickness: float
    grip_start: float  # x where the dipped grip begins
    grip_thickness: float
    upper: float  # joint limit (rad)
    corner_radius: float = 0.0012
    gap: float = 0.0003  # half the clearance between the closed jaws


def _upper_half_outline(shape: _PliersShape) -> Polygon | MultiPolygon:
    """The upper half's jaw (+y side) and handle (-y side), rounded, without the pivot disc."""
    jaw = _catmull_rom(shape.jaw)
    jaw_poly = Polygon(np.concatenate([np.column_stack([jaw[:, 0], np.full(len(jaw), shape.gap)]), jaw[::-1]]))
    handle = _catmull_rom(shape.handle)
    x, inner, width = handle.T
    handle_poly = Polygon(np.concatenate([np.column_stack([x, -inner]), np.column_stack([x, -(inner + width)])[::-1]]))
    end_cap = Point(x[-1], -(inner[-1] + width[-1] / 2)).buffer(width[-1] / 2, quad_segs=6)
    return _rounded(jaw_poly.union(handle_poly).union(end_cap), shape.corner_radius)


def _pliers(shape: _PliersShape, look: _PliersLook) -> _Design:
    """Two halves crossing at a lap joint: each is full thickness except on the pivot disc, where
    the lower half fills ``z < 0`` and the upper half ``z > 0``."""
    disc = Point(0.0, 0.0).buffer(shape.pivot_radius, quad_segs=12)
    upper_outline = _upper_half_outline(shape).difference(disc)
    t, g = shape.head_thickness / 2, shape.grip_thickness / 2
    grip_box = box(-1.0, -1.0, shape.grip_start, 1.0)

    def half(
        name: str, outline: shapely.Geometry, disc_z: tuple[float, float], grip: Surface, marks: tuple[Mark, ...]
    ) -> _Link:
        prisms = (
            _prisms(outline.intersection(box(0.0, -1.0, 1.0, 1.0)), (-t, t), look.jaw_steel, _STEEL)
            + _prisms(disc, disc_z, look.steel, _STEEL)
            + _prisms(outline.intersection(box(shape.grip_start, -1.0, 0.0, 1.0)), (-t, t), look.steel, _STEEL)
            + _prisms(outline.intersection(grip_box), (-g, g), grip, _COATED_STEEL)
        )
        return _Link(name, prisms, marks)

    mirrored = _scale_geometry(upper_outline, 1.0, -1.0, origin=(0.0, 0.0))
    lower = half("lower_half", mirrored, (-t, 0.0), look.grip_lower, look.marks_lower)
    upper = half("upper_half", upper_outline, (0.0, t), look.grip_upper, look.marks_upper)
    joint = _Joint("pivot", "revolute", "lower_half", "upper_half", (0.0, 0.0, 1.0), 0.0, shape.upper)
    return _Design((lower, upper), (joint,))


def _pliers_steel(colour: Rgb, grain: float, shape: _PliersShape, serration_from: float) -> tuple[Surface, Surface]:
    """Forged-steel surfaces: the body, and the jaws with serrations and a ground cutting edge."""
    rivet = (
        Paint((0.22, 0.22, 0.24), Disk((0.0, 0.0), 0.0062)),
        Paint(tuple(min(1.0, c * 1.35) for c in colour), Disk((0.0, 0.0), 0.0048)),
        Paint((0.25, 0.25, 0.27), Disk((0.0, 0.0), 0.0012)),
    )
    tip = shape.jaw[-1][0]
    jaw = Surface(
        colour,
        mottle=0.08,
        speckle=0.05,
        grain=grain,
        details=(
            Ribs(0.0011, (1.0, 0.0, 0.0), 0.55, 0.45, Box((serration_from, -0.0045, -1.0), (tip + 0.01, 0.0045, 1.0))),
            Paint((0.80, 0.80, 0.82), Box((shape.pivot_radius, -0.0011, -1.0), (serration_from - 0.002, 0.0011, 1.0))),
        ),
    )
    return Surface(colour, mottle=0.12, speckle=0.05, grain=grain, details=rivet), jaw


_LINEMAN_A = _PliersShape(
    jaw=((0.0, 0.0128), (0.02, 0.0126), (0.036, 0.0117), (0.045, 0.0104), (0.048, 0.0094)),
    handle=(
        (0.0, 0.0003, 0.0118), (-0.02, 0.0012, 0.0112), (-0.045, 0.0040, 0.0112),
        (-0.08, 0.0068, 0.0125), (-0.12, 0.0088, 0.0138), (-0.148, 0.0098, 0.0140),
    ),
    pivot_radius=0.0145,
    head_thickness=0.011,
    grip_start=-0.040,
    grip_thickness=0.0145,
    upper=0.5,
)

_LINEMAN_B = _PliersShape(
    jaw=((0.0, 0.0135), (0.018, 0.0136), (0.034, 0.0124), (0.044, 0.0098), (0.049, 0.0060), (0.0505, 0.0035)),
    handle=(
        (0.0, 0.0003, 0.0125), (-0.018, 0.0010, 0.0118), (-0.04, 0.0030, 0.0110),
        (-0.075, 0.0052, 0.0130), (-0.12, 0.0072, 0.0148), (-0.158, 0.0090, 0.0150),
    ),
    pivot_radius=0.0155,
    head_thickness=0.0115,
    grip_start=-0.034,
    grip_thickness=0.0155,
    upper=0.5,
)

_LONGNOSE = _PliersShape(
    jaw=((0.0, 0.0100), (0.012, 0.0088), (0.03, 0.0056), (0.055, 0.0033), (0.074, 0.0019), (0.078, 0.0015)),
    handle=(
        (0.0, 0.0003, 0.0098), (-0.018, 0.0012, 0.0092), (-0.04, 0.0042, 0.0096),
        (-0.075, 0.0070, 0.0112), (-0.105, 0.0085, 0.0120), (-0.118, 0.0090, 0.0120),
    ),
    pivot_radius=0.0115,
    head_thickness=0.009,
    grip_start=-0.032,
    grip_thickness=0.0125,
    upper=0.6,
    corner_radius=0.0004,
)


def _pliers_design(
    shape: _PliersShape,
    steel: tuple[Rgb, float, float],
    grip: Callable[[Rgb], Surface],
    grip_colours: tuple[Rgb, Rgb],
    marks_upper: tuple[Mark, ...],
    marks_lower: tuple[Mark, ...],
) -> _Design:
    """Pliers of ``shape`` with ``steel = (colour, grain, serrations from x)`` and ``grip(colour)``
    surfaces in the upper and lower ``grip_colours``."""
    body, jaw = _pliers_steel(steel[0], steel[1], shape, steel[2])
    return _pliers(shape, _PliersLook(body, jaw, grip(grip_colours[0]), grip(grip_colours[1]), marks_upper, marks_lower))


def _lineman_a() -> _Design:
    yellow, white = (0.96, 0.78, 0.10), (0.95, 0.95, 0.93)
    grip = partial(Surface, mottle=0.05, speckle=0.05, details=(
        Ribs(0.004, (1.0, 0.0, 0.0), 0.40, 0.35, Box((-0.128, -1.0, -1.0), (-0.052, 1.0, 1.0))),
        Paint(yellow, Box((-0.145, -1.0, -1.0), (-0.135, 1.0, 1.0))),
        Paint(yellow, Box((-1.0, -1.0, -1.0), (-0.155, 1.0, 1.0))),
    ))
    return _pliers_design(
        _LINEMAN_A, ((0.43, 0.44, 0.46), 0.16, 0.024), grip, ((0.11, 0.28, 0.60), (0.20, 0.42, 0.78)),
        (Mark("NARF", (-0.090, -0.0133), 0.06, 0.0055, white), Mark("9 IN", (-0.090, -0.0133), -0.06, 0.005, white, -1)),
        (Mark("LINEMAN", (-0.090, 0.0133), -0.06, 0.0045, white), Mark("A-7", (-0.090, 0.0133), 0.06, 0.005, white, -1)),
    )


def _lineman_b() -> _Design:
    black, white = (0.07, 0.07, 0.08), (0.96, 0.96, 0.96)
    grip = partial(Surface, mottle=0.06, speckle=0.04, details=(
        Dots(0.0048, 0.0013, black, Box((-0.140, -1.0, -1.0), (-0.048, 1.0, 1.0))),
        Paint(black, Box((-1.0, -1.0, -1.0), (-0.150, 1.0, 1.0))),
        Paint(black, Box((-0.040, -1.0, -1.0), (-0.034, 1.0, 1.0))),
    ))
    return _pliers_design(
        _LINEMAN_B, ((0.30, 0.32, 0.37), 0.12, 0.026), grip, ((0.70, 0.09, 0.07), (0.84, 0.22, 0.14)),
        (Mark("PROGRESS", (-0.097, -0.0130), 0.05, 0.0045, white), Mark("B-220", (-0.097, -0.0130), -0.05, 0.005, white, -1)),
        (Mark("NARF", (-0.097, 0.0130), -0.05, 0.0055, white), Mark("HD", (-0.097, 0.0130), 0.05, 0.006, white, -1)),
    )


def _longnose() -> _Design:
    black, ink = (0.06, 0.06, 0.07), (0.05, 0.05, 0.05)
    knurl = Box((-0.112, -1.0, -1.0), (-0.050, 1.0, 1.0))
    grip = partial(Surface, mottle=0.05, speckle=0.04, details=(
        Ribs(0.0032, (0.7071, 0.7071, 0.0), 0.35, 0.3, knurl),
        Ribs(0.0032, (0.7071, -0.7071, 0.0), 0.35, 0.3, knurl),
        Paint(black, Box((-0.046, -1.0, -1.0), (-0.040, 1.0, 1.0))),
        Paint(black, Box((-1.0, -1.0, -1.0), (-0.118, 1.0, 1.0))),
    ))
    return _pliers_design(
        _LONGNOSE, ((0.60, 0.61, 0.64), 0.22, 0.030), grip, ((0.93, 0.73, 0.07), (0.96, 0.58, 0.10)),
        (Mark("LONG NOSE", (-0.078, -0.0125), 0.10, 0.0040, ink), Mark("NARF", (-0.078, -0.0125), -0.10, 0.005, ink, -1)),
        (Mark("6 IN", (-0.078, 0.0125), -0.10, 0.0050, ink), Mark("L-6", (-0.078, 0.0125), 0.10, 0.005, ink, -1)),
    )


# --- clamp ------------------------------------------------------------------------------------


def _clamp() -> _Design:
    """A one-handed bar clamp: steel bar along +x, jaws hanging towards -y, pads facing each other."""
    black, dark, yellow = (0.10, 0.10, 0.11), (0.17, 0.17, 0.18), (0.96, 0.76, 0.08)
    white = (0.95, 0.95, 0.93)
    steel = Surface(
        (0.68, 0.69, 0.71),
        mottle=0.06,
        speckle=0.03,
        grain=0.25,
        details=(Ticks(0.005, (0.05, 0.05, 0.05), Box((-0.01, 0.0025, -1.0), (0.236, 0.0092, 1.0))),),
    )
    plastic = Surface(black, mottle=0.10, speckle=0.08)
    jaw = Surface(
        (0.22, 0.22, 0.23),
        mottle=0.10,
        speckle=0.08,
        details=(
            Ribs(0.005, (0.0, 1.0, 0.0), 0.45, 0.3, Box((-1.0, -0.080, -1.0), (1.0, -0.026, 1.0))),
            Paint(yellow, Box((-1.0, -1.0, -1.0), (1.0, -0.086, 1.0))),
        ),
    )
    stripe = Paint(yellow, Box((-0.072, 0.009, -1.0), (-0.022, 0.020, 1.0)))
    housing = Surface(dark, mottle=0.10, speckle=0.08, details=(stripe,))
    grip_ribs = Ribs(0.006, (0.0, 1.0, 0.0), 0.75, 0.35, Box((-1.0, -0.128, -1.0), (1.0, -0.045, 1.0)))
    grip = Surface(yellow, mottle=0.05, speckle=0.05, details=(grip_ribs,))
    pad = Surface((0.95, 0.45, 0.08), mottle=0.05, speckle=0.05, details=(Dots(0.004, 0.0011, (0.55, 0.22, 0.04)),))
    lever = Surface(yellow, mottle=0.05, speckle=0.05, details=(Ribs(0.0025, (1.0, 0.0, 0.0), 0.5, 0.4),))

    bar_z, jaw_z, pad_z = (-0.003, 0.003), (-0.0095, 0.0095), (-0.0115, 0.0115)
    pad_outline = _rounded(box(-0.006, -0.088, 0.0, -0.022), 0.0015)
    grip_outline = Polygon([(-0.068, -0.030), (-0.030, -0.030), (-0.044, -0.130), (-0.082, -0.130)])
    bar = _Link(
        "bar",
        _prisms(box(-0.006, -0.0095, 0.236, 0.0095), bar_z, steel, _STEEL)
        + _prisms(box(-0.080, -0.0095, -0.072, 0.0095), bar_z, steel, _STEEL)
        + _prisms(_rounded(box(0.236, -0.012, 0.244, 0.012), 0.002), (-0.0055, 0.0055), plastic, _PLASTIC)
        + _prisms(pad_outline, pad_z, pad, _RUBBER)
        + _prisms(_rounded(box(-0.024, -0.092, -0.006, 0.016), 0.003), jaw_z, jaw, _PLASTIC)
        + _prisms(_rounded(box(-0.072, -0.030, -0.024, 0.020), 0.004), (-0.013, 0.013), housing, _PLASTIC)
        + _prisms(_rounded(grip_outline.difference(box(-1, -0.030, 1, 1)), 0.005), (-0.014, 0.014), grip, _RUBBER),
        (
            Mark("NARF QUICK-CLAMP", (0.120, -0.003), 0.0, 0.0042, (0.08, 0.08, 0.08)),
            Mark("300 MM", (0.120, -0.003), 0.0, 0.0045, (0.08, 0.08, 0.08), -1),
            Mark("NARF", (-0.048, -0.008), 0.0, 0.008, white),
            Mark("PROGRESS", (-0.048, -0.008), 0.0, 0.005, white, -1),
        ),
    )
    moving_jaw = _Link(
        "moving_jaw",
        _prisms(_rounded(box(0.0, -0.088, 0.006, -0.022), 0.0015), pad_z, pad, _RUBBER)
        + _prisms(_rounded(box(0.006, -0.092, 0.024, 0.018), 0.003), jaw_z, jaw, _PLASTIC)
        + _prisms(_rounded(box(0.024, -0.014, 0.034, 0.016), 0.002), (-0.006, 0.006), lever, _PLASTIC),
        (
            Mark("OPEN", (0.015, -0.055), np.pi / 2, 0.0055, white),
            Mark("12", (0.015, -0.055), np.pi / 2, 0.007, white, -1),
        ),
    )
    joint = _Joint("jaw_opening", "prismatic", "bar", "moving_jaw", (1.0, 0.0, 0.0), 0.02, 0.20)
    return _Design((bar, moving_jaw), (joint,))


# --- multi-joint objects ------------------------------------------------------------------------


def _stadium(length: float, radius: float) -> Polygon:
    """A bar of half-width ``radius`` with round ends, from the origin along +y for ``length``."""
    return LineString([(0.0, 0.0), (0.0, length)]).buffer(radius, quad_segs=6)


def _lamp() -> _Design:
    """A desk lamp: a round foot, two thin arms and a shade on three parallel revolute joints.

    The base frame sits on the floor under the foot's centre (+z up, arm swinging in the xz plane,
    reaching towards +x). Each moving link lies in its own xy plane with the joint axis along its z,
    so ``shoulder`` turns its frame by ``rpy = (pi/2, 0, 0)`` (axis along world -y). At zero the lower
    arm stands up, the upper arm reaches forward and the shade hangs down; positive values tilt the
    lower arm back, raise the upper arm and swing the shade forward. The upper arm runs beside the
    lower arm (a lap at the elbow) and the shade's neck beside the upper arm, so no two links meet
    anywhere in the joint box.
    """
    dark, brass, white = (0.13, 0.14, 0.17), (0.80, 0.63, 0.27), (0.95, 0.95, 0.93)
    lower_len, upper_len, shoulder_z = 0.18, 0.15, 0.05
    foot = Surface(
        dark,
        mottle=0.10,
        speckle=0.06,
        details=(
            Ribs(0.003, (0.0, 0.0, 1.0), 0.5, 0.4, Box((-1.0, -1.0, 0.003), (1.0, 1.0, 0.013))),
            Paint(brass, Disk((0.0, 0.0), 0.070)),
            Paint(dark, Disk((0.0, 0.0), 0.064)),
            Dots(0.008, 0.0012, (0.35, 0.36, 0.40), Box((-1.0, -1.0, 0.0155), (1.0, 1.0, 1.0))),
        ),
    )
    brass_surface = Surface(brass, mottle=0.08, speckle=0.05, grain=0.2, grain_axis=(0.0, 0.0, 1.0))
    steel = Surface((0.62, 0.63, 0.66), mottle=0.06, speckle=0.04, grain=0.25)
    cheek = box(-0.014, 0.0085, 0.014, 0.0125)
    base = _Link(
        "base",
        _prisms(Point(0.0, 0.0).buffer(0.075, quad_segs=12), (0.0, 0.016), foot, _STEEL)
        + _prisms(Point(0.0, 0.0).buffer(0.022, quad_segs=8), (0.016, 0.030), brass_surface, _STEEL)
        + _prisms(cheek.union(_scale_geometry(cheek, 1.0, -1.0, origin=(0.0, 0.0))), (0.030, 0.062), steel, _STEEL),
        (
            Mark("NARF", (0.045, 0.0), np.pi / 2, 0.010, white),
            Mark("LAMP-3", (0.0, 0.040), 0.0, 0.008, white),
            Mark("230V 40W", (0.0, 0.0), 0.0, 0.008, white, -1),
        ),
    )

    def arm(name: str, length: float, z: tuple[float, float], colour: Rgb, stripe: Rgb, text: str) -> _Link:
        """A thin bar along +y with sprung ends (ribs) and a painted band at mid-length."""
        surface = Surface(
            colour,
            mottle=0.06,
            speckle=0.05,
            details=(
                Ribs(0.0025, (0.0, 1.0, 0.0), 0.5, 0.45, Box((-1.0, 0.012, -1.0), (1.0, 0.040, 1.0))),
                Ribs(0.0025, (0.0, 1.0, 0.0), 0.5, 0.45, Box((-1.0, length - 0.040, -1.0), (1.0, length - 0.012, 1.0))),
                Paint(stripe, Box((-1.0, 0.46 * length, -1.0), (1.0, 0.50 * length, 1.0))),
            ),
        )
        centre = (0.0, 0.7 * length)
        marks = (Mark(text, centre, np.pi / 2, 0.008, white), Mark(text, centre, np.pi / 2, 0.008, white, -1))
        return _Link(name, _prisms(_stadium(length, 0.008), z, surface, _STEEL), marks)

    lower_arm = arm("lower_arm", lower_len, (-0.006, 0.006), (0.70, 0.10, 0.08), white, "NARF")
    upper_arm = arm("upper_arm", upper_len, (0.0065, 0.0165), (0.08, 0.40, 0.46), (0.95, 0.80, 0.10), "A-2")
    knob = Surface((0.10, 0.10, 0.11), mottle=0.08, speckle=0.08, details=(Ribs(0.002, (1.0, 0.0, 0.0), 0.5, 0.4),))
    elbow_knob = _prisms(Point(0.0, 0.0).buffer(0.010, quad_segs=8), (0.0165, 0.0225), knob, _PLASTIC)
    upper_arm = _Link(upper_arm.name, upper_arm.prisms + elbow_knob, upper_arm.marks)
    shade_outline = Polygon([(-0.013, 0.022), (0.013, 0.022), (0.045, 0.080), (-0.045, 0.080)])
    shade = Surface(
        (0.95, 0.74, 0.10),
        mottle=0.05,
        speckle=0.05,
        details=(
            Paint(dark, Box((-1.0, 0.022, -1.0), (1.0, 0.030, 1.0))),
            Paint((1.0, 0.96, 0.82), Box((-0.040, 0.0795, -0.023), (0.040, 1.0, 0.023))),  # the bulb's opening
            Dots(0.009, 0.0015, (0.80, 0.45, 0.05), Box((-1.0, 0.034, -1.0), (1.0, 0.074, 1.0))),
        ),
    )
    head = _Link(
        "head",
        _prisms(_stadium(0.024, 0.006), (-0.005, 0.005), steel, _STEEL)
        + _prisms(shade_outline, (-0.028, 0.028), shade, _STEEL),
        (Mark("NARF", (0.0, 0.055), 0.0, 0.008, dark), Mark("E27", (0.0, 0.055), 0.0, 0.008, dark, -1)),
    )
    up, fwd = (0.0, 0.0, 1.0), (0.0, 0.0, -np.pi / 2)
    joints = (
        _Joint("shoulder", "revolute", "base", "lower_arm", up, -0.5, 0.5, (0.0, 0.0, shoulder_z), (np.pi / 2, 0.0, 0.0)),
        _Joint("elbow", "revolute", "lower_arm", "upper_arm", up, -0.2, 0.8, (0.0, lower_len, 0.0), fwd),
        _Joint("head_tilt", "revolute", "upper_arm", "head", up, -0.5, 0.9, (0.0, upper_len, 0.0), fwd),
    )
    return _Design((base, lower_arm, upper_arm, head), joints)


def _gripper() -> _Design:
    """A two-finger parallel gripper lying flat: palm at the origin, fingers towards +x.

    Each finger slides on the palm's front rail on its own prismatic joint, ``finger_left`` along
    +y and ``finger_right`` along -y; the value is how far that finger's pad has moved out from the
    closed position (pads 4 mm apart at zero). The halves differ in carriage colour and marks.
    """
    light, black, white = (0.84, 0.85, 0.87), (0.08, 0.08, 0.09), (0.95, 0.95, 0.93)
    body = Surface(
        light,
        mottle=0.05,
        speckle=0.04,
        details=(
            Paint(black, Box((-0.052, -1.0, -1.0), (-0.046, 1.0, 1.0))),
            Paint((0.95, 0.70, 0.08), Box((-0.040, 0.080, -1.0), (-0.010, 1.0, 1.0))),  # status light, +y side
            Dots(0.006, 0.0012, (0.55, 0.56, 0.60), Box((-0.044, -0.088, -1.0), (-0.004, -0.050, 1.0))),
        ),
    )
    flange = Surface(black, mottle=0.10, speckle=0.08, details=(Ribs(0.003, (0.0, 1.0, 0.0), 0.5, 0.4),))
    steel = Surface((0.66, 0.67, 0.70), mottle=0.05, speckle=0.04, grain=0.3, grain_axis=(0.0, 1.0, 0.0))
    palm_outline = Polygon(
        [(-0.070, -0.080), (-0.060, -0.090), (0.0, -0.090), (0.0, 0.090), (-0.060, 0.090), (-0.070, 0.080)]
    )
    palm = _Link(
        "palm",
        _prisms(box(-0.086, -0.040, -0.070, 0.040), (-0.030, 0.030), flange, _STEEL)
        + _prisms(_rounded(palm_outline, 0.004), (-0.022, 0.022), body, _PLASTIC)
        + _prisms(box(0.0, -0.085, 0.008, 0.085), (-0.012, 0.012), steel, _STEEL),
        (
            Mark("NARF", (-0.030, -0.030), 0.0, 0.012, black),
            Mark("PG-2", (-0.030, 0.045), 0.0, 0.009, black),
            Mark("SN 0042", (-0.030, 0.0), 0.0, 0.008, black, -1),
        ),
    )
    aluminium = Surface((0.76, 0.77, 0.79), mottle=0.05, speckle=0.05, grain=0.3)
    pad = Surface((0.16, 0.16, 0.17), mottle=0.08, speckle=0.06, details=(Ribs(0.002, (1.0, 0.0, 0.0), 0.5, 0.45),))
    carriage_outline = box(0.0, 0.003, 0.018, 0.030)
    finger_outline = Polygon([(0.018, 0.003), (0.095, 0.003), (0.095, 0.011), (0.060, 0.016), (0.018, 0.024)])
    pad_outline = box(0.050, 0.0, 0.093, 0.003)

    def finger(name: str, side: float, anodised: Rgb, text: str) -> _Link:
        def place(outline: Polygon) -> Polygon:
            return outline if side > 0 else _scale_geometry(outline, 1.0, -1.0, origin=(0.0, 0.0))

        front_band = Paint(black, Box((0.014, -1.0, -1.0), (1.0, 1.0, 1.0)))
        carriage = Surface(anodised, mottle=0.06, speckle=0.05, details=(front_band,))
        return _Link(
            name,
            _prisms(place(carriage_outline), (-0.018, 0.018), carriage, _STEEL)
            + _prisms(place(finger_outline), (-0.011, 0.011), aluminium, _STEEL)
            + _prisms(place(pad_outline), (-0.009, 0.009), pad, _RUBBER),
            (
                Mark(text, (0.007, side * 0.0165), 0.0, 0.010, white),
                Mark(text, (0.007, side * 0.0165), 0.0, 0.010, white, -1),
                Mark("NARF", (0.045, side * 0.011), 0.0, 0.0045, black),
            ),
        )

    left = finger("finger_left", 1.0, (0.12, 0.30, 0.72), "L")
    right = finger("finger_right", -1.0, (0.72, 0.14, 0.10), "R")
    joints = (
        _Joint("finger_left", "prismatic", "palm", "finger_left", (0.0, 1.0, 0.0), 0.0, 0.04, (0.008, 0.002, 0.0)),
        _Joint("finger_right", "prismatic", "palm", "finger_right", (0.0, -1.0, 0.0), 0.0, 0.04, (0.008, -0.002, 0.0)),
    )
    return _Design((palm, left, right), joints)


def _cabinet() -> _Design:
    """A small wooden cabinet: two drawers on the left (-y) over each other, a door on the right.

    The body frame sits on the floor under the body's centre, +z up, fronts facing +x. Drawers
    ``drawer_lower`` and ``drawer_upper`` slide out along +x (value: how far, metres); ``door``
    turns about a vertical hinge at the front right edge (value: the opening angle, 0 = closed).
    Each moving link's frame is the centre of its front at zero; fronts overlay the body's front.
    Textures are coarser than the tools' (1 mm texels) to keep the atlases of the larger panels small.
    """
    depth, half_width, t = 0.22, 0.16, 0.012
    front_x = depth / 2
    plinth_z, floor_z, top_z, shelf_z = 0.020, 0.032, 0.238, (0.129, 0.141)
    white, black = (0.95, 0.95, 0.93), (0.07, 0.07, 0.08)
    oak = partial(Surface, (0.74, 0.57, 0.37), mottle=0.10, speckle=0.04, grain=0.30)
    across, upright = oak(grain_axis=(0.0, 1.0, 0.0)), oak(grain_axis=(0.0, 0.0, 1.0))
    plate = Paint((0.82, 0.80, 0.74), Box((-0.060, -1.0, 0.170), (-0.020, -0.159, 0.200)))  # maker's plate, -y side
    walls = box(-front_x, -half_width, front_x, -half_width + t).union(
        box(-front_x, half_width - t, front_x, half_width)
    ).union(box(-front_x, -half_width + t, -front_x + t, half_width - t))
    body = _Link(
        "body",
        _prisms(box(-0.095, -0.150, 0.095, 0.150), (0.0, plinth_z), Surface(black, mottle=0.1, speckle=0.08), _PLASTIC)
        + _prisms(box(-front_x, -half_width, front_x, half_width), (plinth_z, floor_z), across, _WOOD)
        + _prisms(walls, (floor_z, top_z), oak(grain_axis=(0.0, 0.0, 1.0), details=(plate,)), _WOOD)
        + _prisms(box(-front_x + t, -t / 2, front_x, t / 2), (floor_z, shelf_z[0]), upright, _WOOD)
        + _prisms(box(-front_x + t, -t / 2, front_x, t / 2), (shelf_z[1], top_z), upright, _WOOD)
        + _prisms(box(-front_x + t, -half_width + t, front_x, half_width - t), shelf_z, across, _WOOD)
        + _prisms(box(-front_x, -half_width, front_x, half_width), (top_z, top_z + t), across, _WOOD),
    )
    handle = Surface((0.70, 0.71, 0.73), mottle=0.04, speckle=0.04, grain=0.3, grain_axis=(0.0, 1.0, 0.0))
    ply = Surface((0.88, 0.76, 0.56), mottle=0.08, speckle=0.04, grain=0.2)

    def drawer(name: str, card: Rgb, letter: str) -> _Link:
        """Front (overlay, 16 mm), a bar handle, and a tray 0.196 m deep behind the front."""
        front = Surface(
            (0.42, 0.56, 0.47),
            mottle=0.06,
            speckle=0.04,
            details=(  # a label card in a holder, black at its left edge
                Paint(card, Box((0.015, -0.028, 0.022), (1.0, 0.028, 0.040))),
                Paint(black, Box((0.015, -0.030, 0.020), (1.0, -0.028, 0.042))),
            ),
        )
        tray = box(-0.196, -0.064, 0.0, 0.064).difference(box(-0.188, -0.056, 0.0, 0.056))
        posts = box(0.016, -0.040, 0.030, -0.032).union(box(0.016, 0.032, 0.030, 0.040))
        pull = unary_union([posts, box(0.024, -0.040, 0.032, 0.040)])
        return _Link(
            name,
            _prisms(box(0.0, -0.0785, 0.016, 0.0785), (-0.0565, 0.0565), front, _WOOD)
            + _prisms(box(-0.196, -0.064, 0.0, 0.064), (-0.042, -0.034), ply, _PLYWOOD)
            + _prisms(tray, (-0.034, 0.040), ply, _PLYWOOD)
            + _prisms(pull, (-0.006, 0.006), handle, _STEEL),
            (
                Mark(letter, (-0.100, 0.0), 0.0, 0.040, (0.30, 0.22, 0.12)),
                Mark("NARF", (-0.100, 0.0), 0.0, 0.012, black, -1),
            ),
        )

    door_surface = Surface(
        (0.90, 0.87, 0.78),
        mottle=0.05,
        speckle=0.04,
        details=(
            Paint((0.70, 0.66, 0.56), Box((0.015, -0.146, -0.102), (1.0, -0.012, 0.102))),
            Paint((0.90, 0.87, 0.78), Box((0.015, -0.142, -0.098), (1.0, -0.016, 0.098))),
            Dots(0.012, 0.0015, (0.78, 0.74, 0.64), Box((0.015, -0.138, -0.094), (1.0, -0.020, 0.094))),
        ),
    )
    door = _Link(
        "door",
        _prisms(box(0.0, -0.158, 0.016, -0.001), (-0.114, 0.114), door_surface, _WOOD)
        + _prisms(box(0.016, -0.150, 0.030, -0.142), (-0.040, 0.040), handle, _STEEL),
    )
    lower = drawer("drawer_lower", white, "A")
    upper = drawer("drawer_upper", (0.96, 0.82, 0.20), "B")
    x = (1.0, 0.0, 0.0)
    joints = (
        _Joint("drawer_lower", "prismatic", "body", "drawer_lower", x, 0.0, 0.16, (front_x, -0.0805, 0.0775)),
        _Joint("drawer_upper", "prismatic", "body", "drawer_upper", x, 0.0, 0.16, (front_x, -0.0805, 0.1925)),
        _Joint("door", "revolute", "body", "door", (0.0, 0.0, 1.0), 0.0, 1.75, (front_x, half_width, 0.135)),
    )
    return _Design((body, lower, upper, door), joints, texels_per_m=1000.0)


_DESIGNS: dict[str, Callable[[], _Design]] = {
    "clamp": _clamp,
    "lineman-a": _lineman_a,
    "lineman-b": _lineman_b,
    "longnose": _longnose,
    "lamp": _lamp,
    "gripper": _gripper,
    "cabinet": _cabinet,
}


# ---------------------------------------------------------------------------------------------
# Meshes and texture atlases


@dataclass(frozen=True)
class _SideIsland:
    """A run of consecutive side-wall edges of one ring, laid out as a rectangle in the atlas."""

    prism: int
    ring: FloatArray  # [m, 2] the ring's vertices, oriented (outward normal on the right)
    first_edge: int
    n_edges: int
    col: int  # top-left texel of the rectangle
    row: int
    width: int
    height: int


@dataclass(frozen=True)
class _Atlas:
    """Where each face lands in a link's texture: two cap bands, then shelves of side islands.

    Cap bands map ``(x, y)`` isotropically at ``texels_per_m`` (image up = +y); a side island maps
    arc length along its ring to columns and ``z`` (top first) to rows.
    """

    width: int
    height: int
    x_min: float
    y_max: float
    top_row: int
    bottom_row: int
    sides: tuple[_SideIsland, ...]
    texels_per_m: float


@dataclass
class _Mesh:
    positions: list[FloatArray] = field(default_factory=list)  # [n, 3] per piece
    normals: list[FloatArray] = field(default_factory=list)
    uvs: list[FloatArray] = field(default_factory=list)  # [n, 2] as texel coordinates (col, row)
    faces: list[NDArray[np.int64]] = field(default_factory=list)
    count: int = 0

    def add(self, positions: FloatArray, normals: FloatArray, uv: FloatArray, faces: NDArray[np.int64]) -> None:
        self.positions.append(positions)
        self.normals.append(normals)
        self.uvs.append(uv)
        self.faces.append(faces + self.count)
        self.count += len(positions)


def _rings(outline: Polygon) -> list[FloatArray]:
    """The boundary rings ``[m, 2]`` of an oriented polygon, without the repeated closing vertex."""
    return [np.asarray(r.coords)[:-1] for r in [outline.exterior, *outline.interiors]]


def _ring_lengths(ring: FloatArray) -> FloatArray:
    """Edge lengths ``[m]`` of a closed ring ``[m, 2]`` (edge i joins vertex i to i + 1)."""
    return np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)


def _layout(link: _Link, texels_per_m: float) -> _Atlas:
    bounds = np.array([p.outline.bounds for p in link.prisms])
    x_min, y_min = bounds[:, 0].min(), bounds[:, 1].min()
    x_max, y_max = bounds[:, 2].max(), bounds[:, 3].max()
    width = int(np.ceil((x_max - x_min) * texels_per_m)) + 2 * _PAD
    width = max(_MIN_WIDTH, -(-width // 8) * 8)
    band = int(np.ceil((y_max - y_min) * texels_per_m)) + 2 * _PAD
    row_limit = (width - 2 * _PAD) / texels_per_m  # longest run of edges one island can hold
    sides: list[_SideIsland] = []
    shelf_row, shelf_height, col = 2 * band, 0, 0
    for k, prism in enumerate(link.prisms):
        height = int(np.ceil((prism.z[1] - prism.z[0]) * texels_per_m)) + 2 * _PAD
        for ring in _rings(prism.outline):
            lengths = _ring_lengths(ring)
            first = 0
            while first < len(ring):
                n, run = 0, 0.0
                while first + n < len(ring) and run + lengths[first + n] <= row_limit:
                    run += lengths[first + n]
                    n += 1
                if n == 0:
                    raise ValueError(f"edge longer than the atlas row in link {link.name!r}")
                island_width = int(np.ceil(run * texels_per_m)) + 2 * _PAD
                if col + island_width > width:
                    shelf_row, shelf_height, col = shelf_row + shelf_height, 0, 0
                sides.append(_SideIsland(k, ring, first, n, col, shelf_row, island_width, height))
                col += island_width
                shelf_height = max(shelf_height, height)
                first += n
    total = -(-(shelf_row + shelf_height) // 8) * 8
    return _Atlas(width, total, x_min, y_max, 0, band, tuple(sides), texels_per_m)


def _cap_texel(atlas: _Atlas, xy: FloatArray, band_row: int) -> FloatArray:
    """Continuous texel coordinates ``[n, 2]`` (col, row) of points ``xy [n, 2]`` in a cap band."""
    col = _PAD + (xy[:, 0] - atlas.x_min) * atlas.texels_per_m
    row = band_row + _PAD + (atlas.y_max - xy[:, 1]) * atlas.texels_per_m
    return np.column_stack([col, row])


def _link_mesh(link: _Link, texels_per_m: float) -> tuple[_Mesh, _Atlas]:
    """The link's triangles with flat caps, side walls shaded smooth where they curve gently."""
    atlas = _layout(link, texels_per_m)
    mesh = _Mesh()
    for k, prism in enumerate(link.prisms):
        z0, z1 = prism.z
        verts, tris = trimesh.creation.triangulate_polygon(prism.outline, engine="earcut")
        a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
        clockwise = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0] < 0
        tris = np.where(clockwise[:, None], tris[:, ::-1], tris)
        n = len(verts)
        for z, sign, band_row in ((z1, 1.0, atlas.top_row), (z0, -1.0, atlas.bottom_row)):
            positions = np.column_stack([verts, np.full(n, z)])
            normals = np.tile([0.0, 0.0, sign], (n, 1))
            mesh.add(positions, normals, _cap_texel(atlas, verts, band_row), tris if sign > 0 else tris[:, ::-1])
        for island in atlas.sides:
            if island.prism == k:
                _add_side_island(mesh, island, prism.z, texels_per_m)
    return mesh, atlas


def _add_side_island(mesh: _Mesh, island: _SideIsland, z: tuple[float, float], texels_per_m: float) -> None:
    ring = island.ring
    m = len(ring)
    edge = np.roll(ring, -1, axis=0) - ring
    edge_normal = np.column_stack([edge[:, 1], -edge[:, 0]]) / np.linalg.norm(edge, axis=1)[:, None]
    previous = np.roll(edge_normal, 1, axis=0)  # normal of the edge ending at vertex i
    smooth = (edge_normal * previous).sum(1) > _SMOOTH_COS
    blended = edge_normal + previous
    blended /= np.linalg.norm(blended, axis=1)[:, None]
    lengths = _ring_lengths(ring)
    z0, z1 = z
    scale_z = (island.height - 2 * _PAD) / (z1 - z0)
    s = 0.0
    for e in range(island.first_edge, island.first_edge + island.n_edges):
        i, j = e, (e + 1) % m
        n_i = blended[i] if smooth[i] else edge_normal[e]
        n_j = blended[j] if smooth[j] else edge_normal[e]
        xy = np.stack([ring[i], ring[j], ring[j], ring[i]])
        zs = np.array([z0, z0, z1, z1])
        normals = np.column_stack([np.stack([n_i, n_j, n_j, n_i]), np.zeros(4)])
        cols = island.col + _PAD + np.array([s, s + lengths[e], s + lengths[e], s]) * texels_per_m
        rows = island.row + _PAD + (z1 - zs) * scale_z
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        mesh.add(np.column_stack([xy, zs]), normals, np.column_stack([cols, rows]), faces)
        s += lengths[e]


def _paint_atlas(link: _Link, atlas: _Atlas, noise: ValueNoise) -> NDArray[np.uint8]:
    """The link's texture ``[height, width, 3]`` (sRGB ``uint8``)."""
    image = np.zeros((atlas.height, atlas.width, 3))
    band_height = atlas.bottom_row - atlas.top_row
    for band_row, z_index, face in ((atlas.top_row, 1, 1), (atlas.bottom_row, 0, -1)):
        owner = _cap_owners(link, atlas, band_height)
        rows, cols = np.nonzero(owner >= 0)
        xy = np.column_stack(
            [
                atlas.x_min + (cols + 0.5 - _PAD) / atlas.texels_per_m,
                atlas.y_max - (rows + 0.5 - _PAD) / atlas.texels_per_m,
            ]
        )
        for k, prism in enumerate(link.prisms):
            mine = owner[rows, cols] == k
            points = np.column_stack([xy[mine], np.full(mine.sum(), prism.z[z_index])])
            image[band_row + rows[mine], cols[mine]] = prism.surface.paint(points, noise)
        inside = owner >= 0
        for mark in link.marks:
            if mark.face == face:
                _draw_mark(image[band_row : band_row + band_height], inside, atlas, mark)
    for island in atlas.sides:
        prism = link.prisms[island.prism]
        image[island.row : island.row + island.height, island.col : island.col + island.width] = _paint_island(
            island, prism, noise, atlas.texels_per_m
        )
    return to_uint8(image)


def _cap_owners(link: _Link, atlas: _Atlas, band_height: int) -> NDArray[np.int64]:
    """``[band_height, width]``: the prism each cap texel shows (-1: none). Texels inside a prism's
    outline belong to it; texels just outside every outline go to a neighbour, so that filtering at
    the silhouette picks up the right colour."""
    owner = np.full((band_height, atlas.width), -1, dtype=np.int64)
    margin = (_PAD + 1) / atlas.texels_per_m
    for grown in (True, False):
        for k, prism in enumerate(link.prisms):
            outline = prism.outline.buffer(margin, quad_segs=2) if grown else prism.outline
            mask = Image.new("L", (atlas.width, band_height))
            draw = ImageDraw.Draw(mask)
            for polygon in outline.geoms if isinstance(outline, MultiPolygon) else [outline]:
                texels = _cap_texel(atlas, np.asarray(polygon.exterior.coords), 0) - 0.5
                draw.polygon([tuple(p) for p in texels], fill=255)
                for hole in polygon.interiors:
                    draw.polygon([tuple(p) for p in _cap_texel(atlas, np.asarray(hole.coords), 0) - 0.5], fill=0)
            owner[np.asarray(mask) > 0] = k
    return owner


def _draw_mark(band: FloatArray, inside: NDArray[np.bool_], atlas: _Atlas, mark: Mark) -> None:
    """Blend ``mark`` into a cap band ``[h, w, 3]`` in place, only over texels ``inside`` the link."""
    coverage = rotated_mask(text_mask(mark.text, round(mark.height * atlas.texels_per_m)), mark.angle, mark.face < 0)
    col, row = _cap_texel(atlas, np.array([mark.centre]), 0)[0]
    h, w = coverage.shape
    top, left = int(round(row - h / 2)), int(round(col - w / 2))
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + h, band.shape[0]), min(left + w, band.shape[1])
    if r0 >= r1 or c0 >= c1:
        raise ValueError(f"mark {mark.text!r} lies outside its link")
    alpha = coverage[r0 - top : r1 - top, c0 - left : c1 - left] * inside[r0:r1, c0:c1]
    region = band[r0:r1, c0:c1]
    region[:] = region * (1 - alpha[..., None]) + np.asarray(mark.colour) * alpha[..., None]


def _paint_island(island: _SideIsland, prism: _Prism, noise: ValueNoise, texels_per_m: float) -> FloatArray:
    """Colours ``[height, width, 3]`` of one side island; margins continue along the ring."""
    ring = np.concatenate([island.ring, island.ring[:1]])
    cumulative = np.concatenate([[0.0], np.cumsum(_ring_lengths(island.ring))])
    perimeter = cumulative[-1]
    start = cumulative[island.first_edge]
    s = (start + (np.arange(island.width) + 0.5 - _PAD) / texels_per_m) % perimeter
    x, y = np.interp(s, cumulative, ring[:, 0]), np.interp(s, cumulative, ring[:, 1])
    z0, z1 = prism.z
    scale_z = (island.height - 2 * _PAD) / (z1 - z0)
    z = z1 - (np.arange(island.height) + 0.5 - _PAD) / scale_z
    points = np.column_stack(
        [np.tile(x, island.height), np.tile(y, island.height), np.repeat(z, island.width)]
    )
    return prism.surface.paint(points, noise).reshape(island.height, island.width, 3)


# ---------------------------------------------------------------------------------------------
# Files


def _obj_text(name: str, mesh: _Mesh, atlas: _Atlas) -> str:
    """A single-shape, single-material OBJ; ``vt`` has v = 0 at the image's bottom row."""
    positions = np.concatenate(mesh.positions)
    normals = np.concatenate(mesh.normals)
    texels = np.concatenate(mesh.uvs)
    texels = np.column_stack([texels[:, 0] / atlas.width, 1.0 - texels[:, 1] / atlas.height])
    faces = np.concatenate(mesh.faces) + 1
    return "".join(
        [
            f"# {name}: generated by narf_core.data.synth.tools\n",
            f"mtllib {name}.mtl\n",
            "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in positions),
            "".join(f"vt {u:.6f} {v:.6f}\n" for u, v in texels),
            "".join(f"vn {x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in normals),
            f"usemtl {name}\n",
            "".join(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}\n" for a, b, c in faces),
        ]
    )


def _mtl_text(name: str) -> str:
    return f"newmtl {name}\nKa 1 1 1\nKd 1 1 1\nKs 0.1 0.1 0.1\nNs 20\nd 1\nillum 2\nmap_Kd {name}.png\n"


def _inertial(link: _Link) -> tuple[float, FloatArray]:
    """Mass (kg) and inertia tensor ``[3, 3]`` about the link origin, summed over the prisms."""
    mass, inertia = 0.0, np.zeros((3, 3))
    for prism in link.prisms:
        solid = trimesh.creation.extrude_polygon(prism.outline, prism.z[1] - prism.z[0], engine="earcut")
        solid.apply_translation([0.0, 0.0, prism.z[0]])
        solid.density = prism.density
        mass += solid.mass
        inertia += solid.moment_inertia_frame(np.eye(4))
    return mass, np.where(np.abs(inertia) < 1e-12, 0.0, inertia) + 0.0  # no round-off dust, no -0


def _fmt(values: Sequence[float]) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def _fmt_exact(values: Sequence[float]) -> str:
    """The shortest text that reads back as the same floats (``pi / 2`` keeps all its digits)."""
    return " ".join(np.format_float_positional(v, trim="-") for v in values)


def _urdf_text(name: str, design: _Design, inertials: Sequence[tuple[float, FloatArray]]) -> str:
    robot = ET.Element("robot", name=name)
    zero = {"xyz": "0 0 0", "rpy": "0 0 0"}
    for link, (mass, inertia) in zip(design.links, inertials):
        node = ET.SubElement(robot, "link", name=link.name)
        inertial = ET.SubElement(node, "inertial")
        ET.SubElement(inertial, "origin", zero)
        ET.SubElement(inertial, "mass", value=f"{mass:.6g}")
        (ixx, ixy, ixz), (_, iyy, iyz), (_, _, izz) = inertia
        ET.SubElement(
            inertial,
            "inertia",
            ixx=f"{ixx:.6g}", ixy=f"{ixy:.6g}", ixz=f"{ixz:.6g}", iyy=f"{iyy:.6g}", iyz=f"{iyz:.6g}", izz=f"{izz:.6g}",
        )
        for kind in ("visual", "collision"):
            element = ET.SubElement(node, kind)
            ET.SubElement(element, "origin", zero)
            ET.SubElement(ET.SubElement(element, "geometry"), "mesh", filename=f"meshes/{link.name}.obj")
    for joint in design.joints:
        node = ET.SubElement(robot, "joint", name=joint.name, type=joint.kind)
        ET.SubElement(node, "parent", link=joint.parent)
        ET.SubElement(node, "child", link=joint.child)
        ET.SubElement(node, "origin", xyz=_fmt_exact(joint.xyz), rpy=_fmt_exact(joint.rpy))
        ET.SubElement(node, "axis", xyz=_fmt(joint.axis))
        ET.SubElement(node, "limit", lower=f"{joint.lower:.6g}", upper=f"{joint.upper:.6g}", effort="50", velocity="1")
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
