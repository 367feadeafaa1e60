"""Procedural object families: mugs and YCB-like boxes, cans, bottles, bowls and irregular objects.

Every shape is a watertight solid built with manifold3d (revolved profiles, extrusions, convex hulls and
boolean operations) and handed out as a :class:`trimesh.Trimesh` in the *object frame*:

* sizes in metres;
* the base (lowest point) at z = 0, z is "up";
* the body's vertical axis at x = y = 0 (revolved bodies: the axis of revolution; boxes: the box centre;
  irregular objects: the centre of their axis-aligned bounds);
* mugs: the handle points along +x.

Size limit: the observation grid is 0.20 m wide, so every object fits a 0.18 m cube in any orientation:
the diagonal of its axis-aligned bounds is at most :data:`MAX_DIAGONAL`. The YCB-like families use the
*proportions* of YCB objects (cracker/sugar/pudding/gelatin boxes, soup/coffee/tuna cans, mustard/bleach
bottles, the YCB bowl); objects whose real size would break the limit (a cracker box, the bowl, a coffee
can) are scaled down uniformly to fit, and ``attributes["scale_to_fit"]`` records the factor (1.0 when the
real-size object already fits). Mugs keep their wall and handle thickness and shrink only their height,
radius and handle reach when needed.

Identity and splits: a shape is fully determined by its :class:`ShapeId` ``(family, seed)``;
:func:`make_shape` is deterministic. :func:`split_seeds` hands out seeds from disjoint ranges per split, so
train, validation and test objects are disjoint by construction.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import manifold3d as mf
import numpy as np
import trimesh

FAMILIES: tuple[str, ...] = ("mug", "box", "can", "bottle", "bowl", "irregular",
                             "mug_broad", "box_broad", "can_broad", "bottle_broad", "box_edged")
"""Every procedural family. The ``*_broad`` families break the base families' priors and ``box_edged`` softens the
boxes' edges (training only, see :data:`BROAD_FAMILIES` and :data:`EDGED_FAMILIES`)."""

YCB_FAMILIES: tuple[str, ...] = ("box", "can", "bottle", "bowl", "irregular")
"""The YCB-like families (used by the slit-occlusion experiment)."""

BROAD_FAMILIES: tuple[str, ...] = ("mug_broad", "box_broad", "can_broad", "bottle_broad")
"""Families whose proportions are drawn independently per axis, as far as the size limit allows: mugs with wider
ranges of body size, handle reach, span, thickness and tilt and a slightly elliptic body; boxes whose width,
depth and height are independent (a box's hidden depth says nothing about its visible face); cans and bottles
stretched independently along each axis. A model trained on the base families alone learns their
correlations (a cereal box is ~7 cm deep) and completes every hidden side to them."""

EDGED_FAMILIES: tuple[str, ...] = ("box_edged",)
"""Boxes of independent sides (as ``box_broad``) whose edges are sharp, bevelled or rounded, by boolean unions and
differences of prisms, cylinders and spheres: real packaging rarely has the knife edges of ``Manifold.cube``
(training only, the ``boxes`` scale; ``results/edged_boxes/`` measures what training on them changes)."""

MAX_DIAGONAL: float = 0.18
"""Largest allowed diagonal of an object's axis-aligned bounds (m): it then fits a 0.18 m cube in any pose."""

# Objects are fitted to a slightly smaller diagonal so polygonisation never pushes them over the limit.
_FIT_DIAGONAL = 0.176

SPLIT_RANGES: Mapping[str, tuple[int, int]] = MappingProxyType({
    "train": (0, 1_000_000),
    "val": (1_000_000, 2_000_000),
    "test": (2_000_000, 3_000_000),
})
"""Half-open seed range of each split. Ranges do not overlap, so splits are disjoint by identity."""

# Chord error at a 5 cm radius: 0.2 mm, far below a 64^3 voxel (~3 mm); boolean cost grows with triangles.
_REVOLVE_SEGMENTS = 36


class ShapeError(ValueError):
    """A shape request is invalid (unknown family, bad seed, bad split); the message says which."""


@dataclass(frozen=True)
class ShapeId:
    """Stable identity of an object: its family and seed. ``str(ShapeId("mug", 42)) == "mug-00042"``."""

    family: str
    seed: int

    def __post_init__(self) -> None:
        if not isinstance(self.family, str) or not self.family or "-" in self.family:
            raise ShapeError(f"family must be a non-empty string without '-', got {self.family!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ShapeError(f"seed must be a non-negative integer, got {self.seed!r}")

    def __str__(self) -> str:
        return f"{self.family}-{int(self.seed):05d}"

    @classmethod
    def parse(cls, text: str) -> ShapeId:
        """Inverse of ``str()``: ``"mug-00042"`` -> ``ShapeId("mug", 42)``."""
        family, sep, seed = str(text).rpartition("-")
        if not sep or not seed.isdigit():
            raise ShapeError(f"not a shape identity (expected '<family>-<seed>'): {text!r}")
        return cls(family, int(seed))


@dataclass
class Shape:
    """One object: a watertight solid in the object frame (metres, base at z = 0, vertical axis at x = y = 0).

    Attributes:
        identity: the object's stable identity.
        mesh: the solid.
        handle: for mugs with a handle, the part of the handle outside the body (a solid in the same frame);
            the data module renders it alone to decide whether a view shows the handle. None otherwise.
        attributes: generation parameters and summary values (family-specific; always ``height``,
            ``diagonal`` and ``scale_to_fit`` for procedural shapes).
    """

    identity: ShapeId
    mesh: trimesh.Trimesh
    handle: trimesh.Trimesh | None = None
    attributes: dict[str, float | str | bool] = field(default_factory=dict)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds ``[min, max]`` of the mesh in the object frame (metres)."""
        return np.asarray(self.mesh.bounds, dtype=np.float64)

    def box_corners(self) -> np.ndarray:
        """(8, 3) corners of :attr:`bounds` in the object frame.

        Fixed order: corner ``i`` takes x from ``bounds[i & 1]``, y from ``bounds[(i >> 1) & 1]`` and z from
        ``bounds[(i >> 2) & 1]`` (binary counting, x fastest): (min,min,min), (max,min,min), (min,max,min),
        (max,max,min), (min,min,max), (max,min,max), (min,max,max), (max,max,max).
        """
        b = self.bounds
        index = np.arange(8)
        return np.stack([b[index & 1, 0], b[(index >> 1) & 1, 1], b[(index >> 2) & 1, 2]], axis=1)


def split_seeds(split: str, count: int) -> list[int]:
    """The first ``count`` seeds of a split.

    Seeds come from the split's range in :data:`SPLIT_RANGES` (train ``[0, 1e6)``, val ``[1e6, 2e6)``,
    test ``[2e6, 3e6)``), so no object identity is ever in two splits whatever the counts.

    Raises:
        ShapeError: unknown split, or a negative count or one larger than the split's range.
    """
    if split not in SPLIT_RANGES:
        raise ShapeError(f"unknown split {split!r}; expected one of {sorted(SPLIT_RANGES)}")
    start, stop = SPLIT_RANGES[split]
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or not 0 <= count <= stop - start:
        raise ShapeError(f"count must be an integer in [0, {stop - start}], got {count!r}")
    return list(range(start, start + int(count)))


def split_of_seed(seed: int) -> str:
    """The split a seed belongs to (inverse of :func:`split_seeds`)."""
    for name, (start, stop) in SPLIT_RANGES.items():
        if start <= seed < stop:
            return name
    raise ShapeError(f"seed {seed} is outside every split range {SPLIT_RANGES}")


def make_shape(family: str, seed: int) -> Shape:
    """Generates object ``(family, seed)``; deterministic (same arguments -> identical mesh).

    Raises:
        ShapeError: unknown family or invalid seed.
    """
    if family not in FAMILIES:
        raise ShapeError(f"unknown family {family!r}; expected one of {FAMILIES}")
    identity = ShapeId(family, int(seed))
    # crc32 rather than hash(): Python's string hash is randomised per process.
    rng = np.random.default_rng([zlib.crc32(family.encode()), int(seed)])
    solid, handle, attributes = _BUILDERS[family](rng)
    mesh = manifold_to_trimesh(solid)
    extent = mesh.extents
    diagonal = float(np.linalg.norm(extent))
    if diagonal > MAX_DIAGONAL:  # a generator bug, not bad input
        raise RuntimeError(f"{identity} has a bounds diagonal of {diagonal:.4f} m > {MAX_DIAGONAL} m")
    attributes.update(height=float(extent[2]), width_x=float(extent[0]), width_y=float(extent[1]),
                      diagonal=diagonal, volume=float(solid.volume()))
    attributes.setdefault("scale_to_fit", 1.0)
    return Shape(identity, mesh, None if handle is None else manifold_to_trimesh(handle), attributes)


# --------------------------------------------------------------------------------------------- helpers


def manifold_to_trimesh(solid: mf.Manifold) -> trimesh.Trimesh:
    """A manifold3d solid as a trimesh (the one conversion every shape source uses)."""
    out = solid.to_mesh()
    vertices = np.asarray(out.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(out.tri_verts, dtype=np.int64)
    # Manifold output already shares vertices and is consistently wound; skip trimesh's processing.
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _revolve(r: np.ndarray, z: np.ndarray) -> mf.Manifold:
    """Solid of revolution of the region between the axis and the profile r(z) (z ascending)."""
    pts = np.concatenate([[[0.0, z[0]]], np.stack([r, z], axis=1), [[0.0, z[-1]]]])
    return mf.CrossSection([pts], mf.FillRule.EvenOdd).revolve(_REVOLVE_SEGMENTS)


def _mirrored_section(r: np.ndarray, z: np.ndarray) -> mf.CrossSection:
    """The full vertical slice (x in [-r, r]) through a solid of revolution with profile r(z)."""
    right = np.stack([r, z], axis=1)
    left = np.stack([-r[::-1], z[::-1]], axis=1)
    return mf.CrossSection([np.concatenate([right, left])], mf.FillRule.EvenOdd)


def _cavity_section(r: np.ndarray, z: np.ndarray, wall: float, bottom: float) -> mf.CrossSection:
    """Slice of the cavity: the slice of profile r(z) shrunk by ``wall``, above z = ``bottom``.

    The profile must extend above the rim by more than ``wall`` so that the cavity opens at the top.
    """
    inner = _mirrored_section(r, z).offset(-wall, mf.JoinType.Round, 2.0, 16)
    above = mf.CrossSection.square((2.0, 2.0)).translate((-1.0, bottom))
    return inner ^ above


def _uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.uniform(low, high))


def _fit_factor(diagonal: float) -> float:
    """Uniform scale that brings a diagonal within the limit (1.0 if it already fits)."""
    return min(1.0, _FIT_DIAGONAL / diagonal)


# ------------------------------------------------------------------------------------------------ mugs

MUG_PROFILES: tuple[str, ...] = ("straight", "tapered", "barrel")
HANDLE_STYLES: tuple[str, ...] = ("ring", "d_shape", "square")


@dataclass
class _MugParams:
    square_body: bool
    profile: str
    height: float
    radius: float  # round body: reference radius; square body: half width
    taper: float  # tapered: bottom/top radius ratio (< 1 widens upwards, > 1 narrows); barrel: end/middle ratio
    flare: float  # straight: relative radius growth from bottom to top
    chamfer: float
    corner: float  # square body: corner rounding radius
    wall: float
    bottom: float
    has_handle: bool
    style: str
    reach: float  # how far the handle sticks out of the body (centre line), m
    span_frac: float  # vertical distance between the attachments / height
    position: float  # 0 = lowest possible attachment, 1 = highest
    tilt_deg: float  # positive: the outer part of the handle leans up
    thickness: float  # tube radius in the xz-plane
    corner_frac: float  # d_shape/square corner radius / thickness
    width: float  # tube half width along y


def _mug_radius_fn(p: _MugParams) -> Callable[[np.ndarray], np.ndarray]:
    """Outer body radius as a function of height (valid slightly above the rim too)."""
    if p.square_body:
        return lambda z: np.full_like(np.asarray(z, dtype=float), p.radius)
    if p.profile == "straight":
        return lambda z: p.radius * (1.0 + p.flare * np.asarray(z) / p.height)
    if p.profile == "tapered":
        # The reference radius is the larger end.
        r_bottom, r_top = (p.radius * p.taper, p.radius) if p.taper < 1.0 else (p.radius, p.radius / p.taper)
        return lambda z: r_bottom + (r_top - r_bottom) * np.asarray(z) / p.height
    r_end = p.radius * p.taper
    return lambda z: r_end + (p.radius - r_end) * np.sin(np.pi * np.clip(np.asarray(z) / p.height, 0.0, 1.2))


def _arc(centre: tuple[float, float], radius: float, start: float, stop: float) -> np.ndarray:
    angle = np.linspace(start, stop, max(3, int(np.ceil(abs(stop - start) / np.radians(10.0))) + 1))
    return np.stack([centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle)], axis=1)


def _handle_span(p: _MugParams) -> float:
    """Vertical distance between the handle's attachments (m)."""
    span = p.span_frac * p.height
    # A ring much taller than it is deep would be a flat arc: cap its span at 2.6 reaches.
    return min(span, 2.6 * p.reach) if p.style == "ring" else span


def _handle_centre_line(p: _MugParams) -> tuple[np.ndarray, float]:
    """(k, 2) handle centre line as (outward offset from the body surface, z), lower to upper attachment."""
    half = _handle_span(p) / 2.0
    low = 0.012 + p.thickness + half
    high = p.height - 0.006 - p.thickness - half
    zc = low + p.position * max(high - low, 0.0)
    if p.style == "ring":
        # Circular arc (a torus section) through both attachments with its apex `reach` out.
        rho = (p.reach**2 + half**2) / (2.0 * p.reach)
        x0 = p.reach - rho
        a0 = float(np.arctan2(half, -x0))
        return _arc((x0, zc), rho, -a0, a0), zc
    # Rounded rectangle: horizontal arms and a vertical outer side. Corner radii of 1.5-2.5 tube radii (capped
    # by the handle's size) keep the swept tube from folding onto itself. D: small upper corner and a large
    # round lower part; square: both corners small.
    small = min(p.corner_frac * p.thickness, 0.9 * p.reach, 0.45 * 2 * half)
    large = min(p.reach, 2 * half - small) * 0.95 if p.style == "d_shape" else small
    top, bottom = zc + half, zc - half
    return np.concatenate([
        [[0.0, bottom]],
        _arc((p.reach - large, bottom + large), large, -np.pi / 2, 0.0),
        _arc((p.reach - small, top - small), small, 0.0, np.pi / 2),
        [[0.0, top]],
    ]), zc


def _handle_path(p: _MugParams) -> np.ndarray:
    """(k, 3) centre line of the handle tube in the xz-plane on the +x side, uniformly resampled.

    Both ends continue along their tangent into the body by a wall and a tube radius, so the tube is
    anchored in the wall (the part that reaches the cavity is cut away with the cavity).
    """
    line, zc = _handle_centre_line(p)
    offset, z = line[:, 0], line[:, 1]
    # Tilt: shear the outer part up or down, keeping the attachments on the body.
    offset = offset + np.tan(np.radians(p.tilt_deg)) * (z - zc) * offset / p.reach
    xz = np.stack([_mug_radius_fn(p)(z) + offset, z], axis=1)
    depth = p.wall + p.thickness
    first = xz[1] - xz[0]
    last = xz[-1] - xz[-2]
    xz = np.concatenate([[xz[0] - first / np.linalg.norm(first) * depth], xz,
                         [xz[-1] + last / np.linalg.norm(last) * depth]])
    arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
    s = np.linspace(0.0, arclength[-1], max(8, int(np.ceil(arclength[-1] / 0.003)) + 1))
    x, z = np.interp(s, arclength, xz[:, 0]), np.interp(s, arclength, xz[:, 1])
    return np.stack([x, np.zeros_like(x), z], axis=1)


def _mug_extent(p: _MugParams) -> np.ndarray:
    z = np.linspace(0.0, p.height, 33)
    r_max = float(np.max(_mug_radius_fn(p)(z)))
    x_min, x_max, y_half = -r_max, r_max, r_max
    if p.has_handle:
        x_max = max(x_max, float(np.max(_handle_path(p)[:, 0])) + p.thickness)
        y_half = max(y_half, p.width)
    return np.array([x_max - x_min, 2.0 * y_half, p.height])


def _sample_mug(rng: np.random.Generator, broad: bool = False) -> _MugParams:
    """Mug parameters; ``broad`` widens every range (the ``mug_broad`` family)."""
    if broad:
        return _sample_broad_mug(rng)
    square_body = bool(rng.random() < 0.05)
    has_handle = bool(rng.random() >= 0.10)
    profile = "straight" if square_body else str(rng.choice(MUG_PROFILES))
    if profile == "tapered":
        # Mostly wider at the top (classic), sometimes wider at the bottom.
        taper = _uniform(rng, 0.72, 0.9) if rng.random() < 0.7 else 1.0 / _uniform(rng, 0.78, 0.92)
    elif profile == "barrel":
        taper = _uniform(rng, 0.8, 0.92)
    else:
        taper = 1.0
    wall = _uniform(rng, 0.003, 0.006)
    thickness = _uniform(rng, 0.0035, 0.006)
    return _MugParams(
        square_body=square_body, profile="square" if square_body else profile,
        height=_uniform(rng, 0.08, 0.12), radius=_uniform(rng, 0.035, 0.05), taper=taper,
        flare=_uniform(rng, 0.0, 0.06) if profile == "straight" and not square_body else 0.0,
        chamfer=_uniform(rng, 0.0005, 0.003), corner=_uniform(rng, 0.006, 0.015), wall=wall,
        bottom=_uniform(rng, max(wall, 0.004), 0.01), has_handle=has_handle, style=str(rng.choice(HANDLE_STYLES)),
        reach=_uniform(rng, 0.014, 0.034), span_frac=_uniform(rng, 0.4, 0.72), position=_uniform(rng, 0.0, 1.0),
        tilt_deg=0.0 if rng.random() < 0.6 else _uniform(rng, -25.0, 25.0),
        thickness=thickness, corner_frac=_uniform(rng, 1.5, 2.5), width=thickness * _uniform(rng, 1.0, 1.8))


def _sample_broad_mug(rng: np.random.Generator) -> _MugParams:
    profile = str(rng.choice(MUG_PROFILES))
    taper = {"straight": 1.0, "tapered": _uniform(rng, 0.6, 1.3), "barrel": _uniform(rng, 0.7, 0.95)}[profile]
    if profile == "tapered" and taper > 1.0:
        taper = 1.0 / (2.0 - taper)  # wider at the bottom: the larger end is the reference radius
    wall = _uniform(rng, 0.0025, 0.007)
    thickness = _uniform(rng, 0.003, 0.008)
    return _MugParams(
        square_body=False, profile=profile, height=_uniform(rng, 0.06, 0.15), radius=_uniform(rng, 0.028, 0.06),
        taper=taper, flare=_uniform(rng, -0.05, 0.1) if profile == "straight" else 0.0,
        chamfer=_uniform(rng, 0.0005, 0.004), corner=0.01, wall=wall, bottom=_uniform(rng, max(wall, 0.004), 0.012),
        has_handle=bool(rng.random() >= 0.05), style=str(rng.choice(HANDLE_STYLES)),
        reach=_uniform(rng, 0.01, 0.05), span_frac=_uniform(rng, 0.3, 0.85), position=_uniform(rng, 0.0, 1.0),
        tilt_deg=_uniform(rng, -35.0, 35.0), thickness=thickness, corner_frac=_uniform(rng, 1.5, 2.5),
        width=thickness * _uniform(rng, 0.8, 2.5))


def _build_mug(rng: np.random.Generator, broad: bool = False) -> tuple[mf.Manifold, mf.Manifold | None, dict]:
    p = _sample_mug(rng, broad)
    # mug_broad: a slightly elliptic body (x and y scaled apart; z is the profile's own height).
    stretch = np.array([_uniform(rng, 0.85, 1.2), _uniform(rng, 0.85, 1.2), 1.0]) if broad else np.ones(3)
    # Fit the size limit by shrinking height, radius and reach (walls and handle tube keep their thickness).
    scale = 1.0
    for _ in range(30):
        diagonal = float(np.linalg.norm(_mug_extent(p) * stretch))
        if diagonal <= _FIT_DIAGONAL:
            break
        factor = _FIT_DIAGONAL / diagonal * 0.999
        p = replace(p, height=p.height * factor, radius=p.radius * factor, reach=p.reach * factor)
        scale *= factor
    radius_at = _mug_radius_fn(p)
    top = p.height + p.wall + 0.004  # the cavity profile reaches above the rim so the mug is open
    if p.square_body:
        core = mf.CrossSection.square((2 * (p.radius - p.corner),) * 2, center=True)
        section = core.offset(p.corner, mf.JoinType.Round, 2.0, 32)
        body = mf.Manifold.extrude(section, p.height)
        cavity_section = section.offset(-p.wall, mf.JoinType.Round, 2.0, 32)
        cavity = mf.Manifold.extrude(cavity_section, top - p.bottom).translate((0.0, 0.0, p.bottom))
    else:
        levels = 12 if p.profile == "barrel" else 3  # straight and tapered profiles are lines
        z = np.concatenate([[0.0], np.linspace(p.chamfer, p.height, levels)])
        r = radius_at(z)
        r[0] -= p.chamfer
        body = _revolve(r, z)
        z_ext = np.linspace(0.0, top, levels + 2)
        cavity = _cavity_section(radius_at(z_ext), z_ext, p.wall, p.bottom).revolve(_REVOLVE_SEGMENTS)
    handle = None
    if p.has_handle:
        tube = _tube(_handle_path(p), p.thickness, p.width)
        solid = mf.Manifold.batch_boolean([body, tube], mf.OpType.Add) - cavity
        handle = tube - body
    else:
        solid = body - cavity
    if broad:
        # The extent model above does not know the stretch's effect on a tilted handle: fit the solid itself.
        (x0, y0, z0), (x1, y1, z1) = np.reshape(solid.bounding_box(), (2, 3))
        fit = _fit_factor(float(np.linalg.norm(np.array([x1 - x0, y1 - y0, z1 - z0]) * stretch)))
        stretch = stretch * fit
        scale *= fit
        solid = solid.scale(tuple(stretch))
        handle = None if handle is None else handle.scale(tuple(stretch))
    radii = radius_at(np.linspace(0.0, p.height, 33))
    attributes: dict[str, float | str | bool] = {
        "profile": p.profile, "square_body": p.square_body, "has_handle": p.has_handle,
        "radius": float(np.max(radii)), "radius_min": float(np.min(radii)), "wall": p.wall,
        "bottom_thickness": p.bottom, "scale_to_fit": scale,
        "handle_style": p.style if p.has_handle else "none",
    }
    if broad:
        attributes.update(stretch_x=float(stretch[0]), stretch_y=float(stretch[1]))
    if p.has_handle:
        _, handle_zc = _handle_centre_line(p)
        attributes.update(
            handle_reach=p.reach, handle_thickness=p.thickness, handle_width=p.width,
            handle_span=_handle_span(p), handle_center_z=handle_zc,
            handle_tilt_deg=p.tilt_deg, handle_size="large" if p.reach >= 0.024 else "small",
            handle_position="high" if p.position > 0.66 else "low" if p.position < 0.33 else "middle")
    return solid, handle, attributes


def _tube(path: np.ndarray, radius: float, half_width: float) -> mf.Manifold:
    """Tube of elliptic section (``radius`` in the xz-plane, ``half_width`` along y) swept along a path.

    The path lies in the xz-plane and is uniformly sampled; a straight extrusion with one level per path
    point is bent onto it (one primitive instead of a union of pieces: about 10x faster).
    """
    section = mf.CrossSection.circle(1.0, 12).scale((radius, half_width))
    length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
    straight = mf.Manifold.extrude(section, length, len(path) - 2)
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([tangent[:, 2], np.zeros(len(path)), -tangent[:, 0]], axis=1)  # in-plane, left of travel

    def bend(vertices: np.ndarray) -> np.ndarray:
        # Extrusion levels sit exactly at the path samples: snap each vertex to its level.
        at = np.clip(np.rint(vertices[:, 2] / length * (len(path) - 1)).astype(np.int64), 0, len(path) - 1)
        return path[at] + vertices[:, :1] * normal[at] + vertices[:, 1:2] * np.array([0.0, 1.0, 0.0])

    return straight.warp_batch(bend)


# --------------------------------------------------------------------------------------------- YCB-like

# Real YCB dimensions (m): boxes (x, y, z standing), cans (radius, height), bottles (radius, height, y-flatten).
_BOX_KINDS: Mapping[str, tuple[float, float, float]] = MappingProxyType({
    "cracker": (0.158, 0.060, 0.210),   # 003_cracker_box
    "sugar": (0.089, 0.038, 0.175),     # 004_sugar_box
    "pudding": (0.110, 0.035, 0.089),   # 008_pudding_box
    "gelatin": (0.085, 0.028, 0.073),   # 009_gelatin_box
    "cereal": (0.190, 0.070, 0.280),    # a cereal box
    "brick": (0.075, 0.050, 0.050),     # 061_foam_brick
})
_CAN_KINDS: Mapping[str, tuple[float, float]] = MappingProxyType({
    "soup": (0.033, 0.101),     # 005_tomato_soup_can
    "coffee": (0.051, 0.139),   # 002_master_chef_can
    "tuna": (0.043, 0.033),     # 007_tuna_fish_can
    "chips": (0.038, 0.250),    # 001_chips_can
    "soda": (0.033, 0.122),
})
_BOTTLE_KINDS: Mapping[str, tuple[float, float, float]] = MappingProxyType({
    "mustard": (0.048, 0.191, 0.62),   # 006_mustard_bottle (flattened)
    "bleach": (0.050, 0.250, 0.65),    # 021_bleach_cleanser (flattened)
    "water": (0.033, 0.205, 1.0),
    "sauce": (0.030, 0.150, 1.0),
})


def _jitter(rng: np.random.Generator, values: tuple[float, ...], amount: float = 0.15) -> np.ndarray:
    return np.asarray(values) * rng.uniform(1.0 - amount, 1.0 + amount, size=len(values))


def _build_box(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    kind = str(rng.choice(list(_BOX_KINDS)))
    size = _jitter(rng, _BOX_KINDS[kind])
    lying = bool(rng.random() < 0.25)
    if lying:  # lying on its largest face: the thinnest side becomes the height
        size = np.array([size[2], size[0], size[1]])
    scale = _fit_factor(float(np.linalg.norm(size)))
    size = size * scale
    solid = mf.Manifold.cube(tuple(size), center=True).translate((0.0, 0.0, size[2] / 2))
    return solid, None, {"kind": kind, "lying": lying, "scale_to_fit": scale}


def _build_can(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    kind = str(rng.choice(list(_CAN_KINDS)))
    radius, height = _jitter(rng, _CAN_KINDS[kind])
    scale = _fit_factor(float(np.hypot(2 * np.sqrt(2) * radius, height)))
    radius, height = radius * scale, height * scale
    lip = min(0.003, 0.08 * height)  # rolled rims: the lid and base are slightly narrower
    inset = _uniform(rng, 0.001, 0.003)
    r = np.array([radius - inset, radius, radius, radius - 0.5 * inset])
    z = np.array([0.0, lip, height - lip, height])
    return _revolve(r, z), None, {"kind": kind, "radius": radius, "scale_to_fit": scale}


def _build_bottle(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    kind = str(rng.choice(list(_BOTTLE_KINDS)))
    radius, height, flatten = _BOTTLE_KINDS[kind]
    radius, height = _jitter(rng, (radius, height))
    flatten = min(1.0, flatten * _uniform(rng, 0.9, 1.1))
    scale = _fit_factor(float(np.linalg.norm([2 * radius, 2 * radius * flatten, height])))
    radius, height = radius * scale, height * scale
    neck = radius * _uniform(rng, 0.28, 0.5)
    cap = neck * _uniform(rng, 1.05, 1.3)
    cap_height = height * _uniform(rng, 0.06, 0.12)
    shoulder_start = height * _uniform(rng, 0.5, 0.7)
    shoulder_end = shoulder_start + height * _uniform(rng, 0.08, 0.2)
    neck_top = height - cap_height
    chamfer = min(0.003, 0.1 * radius)
    t = np.linspace(0.0, 1.0, 10)
    shoulder_r = neck + (radius - neck) * 0.5 * (1.0 + np.cos(np.pi * t))  # smooth radius -> neck
    r = np.concatenate([[radius - chamfer, radius], shoulder_r, [neck, cap, cap]])
    z = np.concatenate([[0.0, chamfer], shoulder_start + (shoulder_end - shoulder_start) * t,
                        [neck_top, neck_top, height]])
    solid = _revolve(r, z)
    if flatten < 1.0:
        solid = solid.scale((1.0, flatten, 1.0))
    return solid, None, {"kind": kind, "radius": radius, "neck_radius": neck, "flatten": flatten,
                         "scale_to_fit": scale}


def _build_bowl(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    rim = _uniform(rng, 0.055, 0.085)  # YCB 024_bowl: 0.080 rim radius, 0.055 high
    height = _uniform(rng, 0.035, 0.07)
    base = rim * _uniform(rng, 0.38, 0.6)
    power = _uniform(rng, 0.45, 0.8)  # < 1: the wall rises steeply from the base, then flattens towards the rim
    wall = _uniform(rng, 0.003, 0.006)
    scale = _fit_factor(float(np.hypot(2 * np.sqrt(2) * rim, height)))
    rim, height, base = rim * scale, height * scale, base * scale
    top = height + wall + 0.004
    z = np.linspace(0.0, top, 28)
    r = base + (rim - base) * (z / height) ** power
    inside = z <= height
    z_out = np.concatenate([z[inside], [height]])
    r_out = np.concatenate([r[inside], [rim]])
    section = (_mirrored_section(r_out, z_out) - _cavity_section(r, z, wall, wall * _uniform(rng, 1.0, 1.6)))
    solid = section.revolve(_REVOLVE_SEGMENTS)
    return solid, None, {"rim_radius": rim, "base_radius": base, "wall": wall, "scale_to_fit": scale}


def _random_rotation_deg(rng: np.random.Generator) -> tuple[float, float, float]:
    return tuple(float(a) for a in rng.uniform(-180.0, 180.0, size=3))


def _build_irregular(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    kind = str(rng.choice(["blob", "ellipsoids", "boxes", "mixed"]))
    if kind == "blob":
        # Convex hull of jittered points on an ellipsoid: a pebble/potato-like solid.
        directions = rng.normal(size=(40, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        radii = rng.uniform(0.025, 0.06, size=3)
        points = directions * radii * rng.uniform(0.75, 1.0, size=(40, 1))
        solid = mf.Manifold.hull_points(points)
        parts = 1
    else:
        parts = int(rng.integers(2, 5))
        pieces = []
        centre = np.zeros(3)
        for i in range(parts):
            use_box = kind == "boxes" or (kind == "mixed" and i % 2 == 1)
            half = rng.uniform(0.012, 0.04, size=3)
            if use_box:
                piece = mf.Manifold.cube(tuple(2 * half), center=True)
            else:
                piece = mf.Manifold.sphere(1.0, 24).scale(tuple(half))
            pieces.append(piece.rotate(_random_rotation_deg(rng)).translate(tuple(centre)))
            # The next part is centred inside this one, so the union is one connected solid.
            step = rng.normal(size=3)
            centre = centre + step / np.linalg.norm(step) * 0.6 * float(np.min(half))
        solid = mf.Manifold.batch_boolean(pieces, mf.OpType.Add)
    (x0, y0, z0), (x1, y1, z1) = np.reshape(solid.bounding_box(), (2, 3))
    size = np.array([x1 - x0, y1 - y0, z1 - z0])
    scale = _fit_factor(float(np.linalg.norm(size)))
    solid = solid.translate((-(x0 + x1) / 2, -(y0 + y1) / 2, -z0)).scale((scale, scale, scale))
    return solid, None, {"kind": kind, "parts": parts, "scale_to_fit": scale}


# ------------------------------------------------------------------------------------------ broad families

BROAD_BOX_RANGES_M: tuple[tuple[float, float], ...] = ((0.03, 0.2), (0.02, 0.17), (0.03, 0.25))
"""Independent width (x), depth (y) and height (z) ranges of ``box_broad`` (redrawn until the box fits)."""
BROAD_STRETCH: tuple[float, float] = (0.7, 1.4)
"""Range of the independent per-axis factors of ``can_broad`` and ``bottle_broad`` (log-uniform)."""


def _build_box_broad(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    for _ in range(100):  # redraw rather than shrink: shrinking would tie the sides together again
        size = np.array([_uniform(rng, low, high) for low, high in BROAD_BOX_RANGES_M])
        if np.linalg.norm(size) <= _FIT_DIAGONAL:
            break
    else:
        size = size * _fit_factor(float(np.linalg.norm(size)))
    solid = mf.Manifold.cube(tuple(size), center=True).translate((0.0, 0.0, size[2] / 2))
    return solid, None, {"kind": "broad", "lying": False, "scale_to_fit": 1.0}


BOX_EDGE_KINDS: tuple[str, ...] = ("sharp", "bevelled", "rounded_vertical", "rounded")
BOX_EDGE_RANGE_M: tuple[float, float] = (0.002, 0.015)
"""Range of ``box_edged``'s bevel leg or rounding radius, capped at a third of the shortest side."""


def _build_box_edged(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
    solid, _, attributes = _build_box_broad(rng)
    size = np.ptp(np.reshape(solid.bounding_box(), (2, 3)), axis=0)
    kind = str(rng.choice(BOX_EDGE_KINDS))
    edge = min(_uniform(rng, *BOX_EDGE_RANGE_M), float(size.min()) / 3)
    half = size / 2
    if kind == "bevelled":  # each of the 12 edges cut at 45 degrees by a square prism turned about it
        cutters = []
        for axis in range(3):
            # A square prism turned 45 degrees about its axis, centred on the edge: its corner reaches `edge` in.
            prism = mf.Manifold.cube((edge * np.sqrt(2),) * 2 + (size[axis] + 0.01,), center=True).rotate((0, 0, 45))
            cutters += [_along(prism, axis).translate(offset) for offset in _edge_lines(half, axis)]
        box = mf.Manifold.cube(tuple(size), center=True) - mf.Manifold.batch_boolean(cutters, mf.OpType.Add)
    elif kind in ("rounded_vertical", "rounded"):
        # Classic CSG rounding: inset slabs plus cylinders along the rounded edges (and spheres at the corners).
        rounded_axes = (0, 1) if kind == "rounded_vertical" else (0, 1, 2)
        parts = []
        for axis in rounded_axes:
            inset = size.copy()
            inset[[k for k in rounded_axes if k != axis]] -= 2 * edge
            parts.append(mf.Manifold.cube(tuple(inset), center=True))
        for axis in (2,) if kind == "rounded_vertical" else (0, 1, 2):
            length = size[axis] - (2 * edge if axis in rounded_axes else 0.0)
            cylinder = _along(mf.Manifold.cylinder(length, edge, edge, 24, True), axis)
            parts += [cylinder.translate(offset) for offset in _edge_lines(half - edge, axis)]
        if kind == "rounded":
            parts += [mf.Manifold.sphere(edge, 24).translate(tuple(corner * (half - edge))) for corner in _CORNERS]
        box = mf.Manifold.batch_boolean(parts, mf.OpType.Add)
    else:
        box = mf.Manifold.cube(tuple(size), center=True)
    attributes.update(kind=f"edged_{kind}", edge_m=edge if kind != "sharp" else 0.0)
    return box.translate((0.0, 0.0, size[2] / 2)), None, attributes


_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def _along(solid: mf.Manifold, axis: int) -> mf.Manifold:
    """A solid made along z turned to lie along ``axis`` (0: x, 1: y, 2: z)."""
    return solid.rotate(((0, 90, 0), (90, 0, 0), (0, 0, 0))[axis])


def _edge_lines(half: np.ndarray, axis: int) -> list[tuple[float, float, float]]:
    """The centres of the four lines parallel to ``axis`` at +-half along the two other axes."""
    a, b = [k for k in range(3) if k != axis]
    offsets = []
    for sa in (-1, 1):
        for sb in (-1, 1):
            offset = np.zeros(3)
            offset[a], offset[b] = sa * half[a], sb * half[b]
            offsets.append(tuple(offset))
    return offsets


def _stretched(builder: Callable[[np.random.Generator], tuple[mf.Manifold, None, dict]]
               ) -> Callable[[np.random.Generator], tuple[mf.Manifold, None, dict]]:
    """A base family's builder followed by independent per-axis scaling (base stays at z = 0, axis at x = y = 0)."""

    def build(rng: np.random.Generator) -> tuple[mf.Manifold, None, dict]:
        solid, _, attributes = builder(rng)
        factors = np.exp(rng.uniform(*np.log(BROAD_STRETCH), size=3))
        (x0, y0, z0), (x1, y1, z1) = np.reshape(solid.bounding_box(), (2, 3))
        fit = _fit_factor(float(np.linalg.norm(np.array([x1 - x0, y1 - y0, z1 - z0]) * factors)))
        solid = solid.scale(tuple(factors * fit))
        attributes.update(stretch_x=float(factors[0]), stretch_y=float(factors[1]), stretch_z=float(factors[2]),
                          scale_to_fit=float(attributes.get("scale_to_fit", 1.0)) * fit)
        return solid, None, attributes

    return build


_Builder = Callable[[np.random.Generator], tuple[mf.Manifold, mf.Manifold | None, dict]]
_BUILDERS: Mapping[str, _Builder] = MappingProxyType({
    "mug": _build_mug,
    "box": _build_box,
    "can": _build_can,
    "bottle": _build_bottle,
    "bowl": _build_bowl,
    "irregular": _build_irregular,
    "mug_broad": lambda rng: _build_mug(rng, broad=True),
    "box_broad": _build_box_broad,
    "can_broad": _stretched(_build_can),
    "bottle_broad": _stretched(_build_bottle),
    "box_edged": _build_box_edged,
})
