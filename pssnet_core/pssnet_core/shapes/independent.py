"""A second object generator, written independently of :mod:`pssnet_core.shapes.procedural`: out-of-family test objects.

The models train only on procedural objects, so a test on procedural objects cannot tell learning the *kind* of
object from learning the generator's habits (its revolved profiles, its swept elliptic handle tubes, its YCB
proportions). The objects here share the contract (watertight manifold3d solids, object frame, :class:`Shape`
with ``handle`` for mugs, deterministic from ``(family, seed)``) but are built differently:

* ``imug``: bodies are unions of stacked frusta, extruded many-sided polygons tapered by the extrusion, barrels
  cut from an ellipsoid, or convex hulls of stacked discs; handles are flat plates cut from a 2-D loop outline
  (rectangular section, D-shaped or squared loops), straps lofted as convex hulls of consecutive flat-oval or
  rectangular sections, or thin wires built as chains of capsules. Proportions reach past the training ranges
  (heights 7-13.5 cm, reaches 0.9-4.5 cm, handle sections 3-20 mm wide, attachments at any height).
* ``ibox``: boxes with rounded edges (hull of corner spheres), chamfered corners (hull of cut corners) or
  rounded vertical edges (rounded rectangle extruded); the three sides are drawn independently, so thin slabs
  and deep boxes occur whatever the visible face.
* ``ican``: cylinders with proud rolled rims and ribs, tapered tumblers, oval tins.
* ``ibottle``: rounded-rectangle bodies whose shoulder is a tapering extrusion, or bodies lofted as hulls of
  discs, with a neck and a wider cap.

Object frame as in procedural: metres, base at z = 0, the body's vertical axis at x = y = 0, a mug's handle along
+x. An object whose bounds diagonal would exceed :data:`MAX_DIAGONAL` is scaled down uniformly (handles and walls
included, unlike procedural); ``attributes["scale_to_fit"]`` records the factor.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

import manifold3d as mf
import numpy as np

from pssnet_core.shapes.procedural import MAX_DIAGONAL, Shape, ShapeError, ShapeId, manifold_to_trimesh

INDEPENDENT_FAMILIES: tuple[str, ...] = ("imug", "ibox", "ican", "ibottle")
"""Families of this generator (no name is shared with procedural's)."""

MUG_BODIES: tuple[str, ...] = ("frusta", "polygon", "barrel", "hull")
HANDLE_KINDS: tuple[str, ...] = ("plate", "strap", "wire")
BOX_KINDS: tuple[str, ...] = ("rounded", "chamfered", "rounded_vertical")
CAN_KINDS: tuple[str, ...] = ("rimmed", "tumbler", "oval")
BOTTLE_KINDS: tuple[str, ...] = ("square", "lofted")

_FIT_DIAGONAL = 0.175  # a little under the limit: polygonisation must not push an object over it
_SEGMENTS = 48  # circles: chord error 0.1 mm at 5 cm


@dataclass(frozen=True)
class _Part:
    """What a family builder returns: the solid, the handle (mugs), and the generation attributes."""

    solid: mf.Manifold
    handle: mf.Manifold | None
    attributes: dict[str, float | str | bool]


def make_independent_shape(family: str, seed: int) -> Shape:
    """Generates out-of-family object ``(family, seed)``; deterministic (same arguments -> identical mesh).

    Raises:
        ShapeError: unknown family or invalid seed.
    """
    if family not in INDEPENDENT_FAMILIES:
        raise ShapeError(f"unknown independent family {family!r}; expected one of {INDEPENDENT_FAMILIES}")
    identity = ShapeId(family, int(seed))
    # A stream of its own (the "independent/" prefix): seeds shared with procedural draw unrelated numbers.
    rng = np.random.default_rng([zlib.crc32(f"independent/{family}".encode()), int(seed)])
    part = _BUILDERS[family](rng)
    solid, handle = part.solid, part.handle
    low, high = (np.asarray(b) for b in np.reshape(solid.bounding_box(), (2, 3)))
    scale = min(1.0, _FIT_DIAGONAL / float(np.linalg.norm(high - low)))
    # The frame: axis through the body's centre (builders put it at x = y = 0), base on z = 0.
    shift = (0.0, 0.0, -float(low[2]))
    solid = solid.translate(shift).scale((scale,) * 3)
    handle = None if handle is None else handle.translate(shift).scale((scale,) * 3)
    mesh = manifold_to_trimesh(solid)
    extent = mesh.extents
    diagonal = float(np.linalg.norm(extent))
    if diagonal > MAX_DIAGONAL or not mesh.is_watertight:  # a generator bug, not bad input
        raise RuntimeError(f"{identity}: diagonal {diagonal:.4f} m, watertight {mesh.is_watertight}")
    attributes = dict(part.attributes)
    for key in [k for k, v in attributes.items() if k.endswith("_m") and isinstance(v, float)]:
        attributes[key] = attributes[key] * scale  # lengths (keys ending in _m) as built, after fitting
    attributes.update(generator="independent", height=float(extent[2]), width_x=float(extent[0]),
                      width_y=float(extent[1]), diagonal=diagonal, volume=float(solid.volume()), scale_to_fit=scale)
    return Shape(identity, mesh, None if handle is None else manifold_to_trimesh(handle), attributes)


def _u(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.uniform(low, high))


def _disc(radius: float, z: float, thickness: float = 1e-4) -> mf.Manifold:
    """A thin disc at height ``z``: hulls of stacked discs loft a smooth convex body."""
    return mf.Manifold.cylinder(thickness, radius, radius, _SEGMENTS).translate((0.0, 0.0, z))


# ------------------------------------------------------------------------------------------------ mugs


@dataclass(frozen=True)
class _MugBody:
    """A mug body: the outer solid, the cavity to subtract, and the outer radius at a height (for handles)."""

    outer: mf.Manifold
    cavity: mf.Manifold
    radius_at: Callable[[float], float]
    radius: float


def _frusta_body(rng: np.random.Generator, height: float, radius: float, wall: float, bottom: float) -> _MugBody:
    """Two to four frusta stacked: a foot, the body (tapered either way), optionally a lip band."""
    levels = int(rng.integers(2, 5))
    cuts = np.sort(rng.uniform(0.1, 0.9, size=levels - 1)) * height
    z = np.concatenate([[0.0], cuts, [height]])
    # Radii at each level: a random walk around `radius` (steps between frusta are allowed: that is a foot).
    r = radius * rng.uniform(0.82, 1.08, size=levels + 1)
    r[0] = min(r[0], r[1])
    pieces, holes = [], []
    for k in range(levels):
        h = z[k + 1] - z[k]
        pieces.append(mf.Manifold.cylinder(h, r[k], r[k + 1], _SEGMENTS).translate((0.0, 0.0, z[k])))
    inner = [max(ri - wall, 0.5 * ri) for ri in r]
    for k in range(levels):
        lo, hi = max(z[k], bottom), z[k + 1] + (0.01 if k == levels - 1 else 0.0)
        if hi <= lo:
            continue
        t_lo = (lo - z[k]) / (z[k + 1] - z[k])
        r_lo = inner[k] + (inner[k + 1] - inner[k]) * t_lo
        r_hi = inner[k + 1] + (inner[k + 1] - inner[k]) * (hi - z[k + 1]) / (z[k + 1] - z[k])
        holes.append(mf.Manifold.cylinder(hi - lo, r_lo, max(r_hi, 1e-3), _SEGMENTS).translate((0.0, 0.0, lo)))
    outer = mf.Manifold.batch_boolean(pieces, mf.OpType.Add)
    cavity = mf.Manifold.batch_boolean(holes, mf.OpType.Add)

    def radius_at(height_z: float) -> float:
        return float(np.interp(height_z, z, r))

    return _MugBody(outer, cavity, radius_at, float(r.max()))


def _polygon_body(rng: np.random.Generator, height: float, radius: float, wall: float, bottom: float) -> _MugBody:
    """A regular polygon with 7-16 rounded corners, extruded with a linear taper (scale of the top face)."""
    sides = int(rng.integers(7, 17))
    corner = radius * _u(rng, 0.05, 0.2)
    angles = np.arange(sides) * 2 * np.pi / sides + np.pi / sides  # a flat side faces +x (the handle side)
    core = (radius - corner) / np.cos(np.pi / sides)  # so the rounded polygon's inscribed radius is `radius`
    polygon = mf.CrossSection([np.stack([core * np.cos(angles), core * np.sin(angles)], axis=1)])
    section = polygon.offset(corner, mf.JoinType.Round, 2.0, 16)
    taper = _u(rng, 0.85, 1.2)
    outer = mf.Manifold.extrude(section, height, 0, 0.0, (taper, taper))
    inner = section.offset(-wall, mf.JoinType.Round, 2.0, 16)
    top = height + 0.01
    grow = 1.0 + (taper - 1.0) * top / height
    base = 1.0 + (taper - 1.0) * bottom / height
    cavity = mf.Manifold.extrude(inner.scale((base, base)), top - bottom, 0, 0.0, (grow / base, grow / base))
    cavity = cavity.translate((0.0, 0.0, bottom))

    def radius_at(z: float) -> float:  # the inscribed radius: where a handle on +x meets the flat side
        return radius * (1.0 + (taper - 1.0) * z / height)

    return _MugBody(outer, cavity, radius_at, max(radius, radius * taper) / np.cos(np.pi / sides))


def _barrel_body(rng: np.random.Generator, height: float, radius: float, wall: float, bottom: float) -> _MugBody:
    """The middle of an ellipsoid between two horizontal planes: bulging sides, flat base and rim."""
    c = height / 2 / _u(rng, 0.7, 0.92)  # semi-axis along z, longer than half the height: the ends are cut off
    ellipsoid = mf.Manifold.sphere(1.0, _SEGMENTS).scale((radius, radius, c)).translate((0.0, 0.0, height / 2))
    slab = mf.Manifold.cube((4 * radius, 4 * radius, height)).translate((-2 * radius, -2 * radius, 0.0))
    outer = ellipsoid ^ slab
    inner_r = radius - wall
    inner = mf.Manifold.sphere(1.0, _SEGMENTS).scale((inner_r, inner_r, c)).translate((0.0, 0.0, height / 2))
    above = mf.Manifold.cube((4 * radius, 4 * radius, 2 * c)).translate((-2 * radius, -2 * radius, bottom))
    # The inner ellipsoid reaches above the rim (c > height / 2), so the cavity opens at the top.
    cavity = inner ^ above

    def radius_at(z: float) -> float:
        return radius * float(np.sqrt(max(1.0 - ((z - height / 2) / c) ** 2, 0.0)))

    return _MugBody(outer, cavity, radius_at, radius)


def _hull_body(rng: np.random.Generator, height: float, radius: float, wall: float, bottom: float) -> _MugBody:
    """Convex hull of discs on a concave profile (a bell or a tulip): no revolve, no sweep."""
    z = np.linspace(0.0, height, 6)
    foot = _u(rng, 0.7, 1.0)
    bulge = _u(rng, 0.0, 0.12)
    r = radius * (foot + (1.0 - foot) * z / height + bulge * np.sin(np.pi * z / height))
    outer = mf.Manifold.batch_hull([_disc(ri, zi) for ri, zi in zip(r, z, strict=True)])
    z_in = np.linspace(bottom, height + 0.01, 6)
    r_in = np.interp(z_in, z, r, right=r[-1]) - wall
    cavity = mf.Manifold.batch_hull([_disc(ri, zi) for ri, zi in zip(r_in, z_in, strict=True)])

    def radius_at(h: float) -> float:
        return float(np.interp(h, z, r))

    return _MugBody(outer, cavity, radius_at, float(r.max()))


_MUG_BODY_BUILDERS: Mapping[str, Callable[..., _MugBody]] = MappingProxyType({
    "frusta": _frusta_body, "polygon": _polygon_body, "barrel": _barrel_body, "hull": _hull_body})


@dataclass(frozen=True)
class _HandleSpec:
    """Handle geometry in the xz-plane (metres): attachments, reach, section."""

    kind: str
    z_low: float  # lower attachment (centre line)
    z_high: float  # upper attachment
    reach: float  # outermost point of the centre line beyond the body
    thickness: float  # section size in the xz-plane (radial)
    width: float  # section size along y
    loop: str  # plate: "d" or "square"; strap/wire: "arc" or "squared"


def _loop_centre_line(spec: _HandleSpec, body: _MugBody, count: int = 24) -> np.ndarray:
    """(k, 2) handle centre line (x, z) from the lower to the upper attachment, both ends inside the body wall."""
    mid, half = (spec.z_low + spec.z_high) / 2, (spec.z_high - spec.z_low) / 2
    t = np.linspace(-np.pi / 2, np.pi / 2, count)
    if spec.loop == "arc":  # half an ellipse: apex `reach` out at mid height
        x_out, z = spec.reach * np.cos(t), mid + half * np.sin(t)
    else:  # a squircle half: flat outer side, tight corners
        x_out = spec.reach * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.25
        z = mid + half * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.25
    # Anchored a wall's depth inside the body surface (the cavity cut removes what reaches the inside).
    x = np.array([body.radius_at(zi) for zi in z]) - 0.5 * spec.thickness + x_out
    return np.stack([x, z], axis=1)


def _plate_handle(spec: _HandleSpec, body: _MugBody) -> mf.Manifold:
    """A loop cut from a flat plate: a 2-D outline (D or squared) less its inner offset, extruded along y."""
    inner_x = min(body.radius_at(spec.z_low), body.radius_at(spec.z_high)) - 0.004
    outer_x = max(body.radius_at(spec.z_low), body.radius_at(spec.z_high)) + spec.reach + spec.thickness / 2
    lo, hi = spec.z_low - spec.thickness / 2, spec.z_high + spec.thickness / 2
    box = mf.CrossSection.square((outer_x - inner_x, hi - lo)).translate((inner_x, lo))
    if spec.loop == "d":  # half an ellipse on a straight inner side
        ellipse = mf.CrossSection.circle(1.0, 48).scale((outer_x - inner_x, (hi - lo) / 2))
        outline = ellipse.translate((inner_x, (hi + lo) / 2)) ^ box
    else:
        corner = min(spec.thickness, (hi - lo) / 4)
        outline = box.offset(-corner, mf.JoinType.Round, 2.0, 12).offset(corner, mf.JoinType.Round, 2.0, 12)
    hole = outline.offset(-spec.thickness, mf.JoinType.Round, 2.0, 16)
    ring = outline - hole
    # The loop's inner side (x = inner_x ... body surface) lies inside the body wall, merged by the union.
    plate = mf.Manifold.extrude(ring, spec.width).translate((0.0, 0.0, -spec.width / 2))
    return plate.rotate((90.0, 0.0, 0.0))  # outline (x, y) -> (x, z); extrusion z -> y


def _section_ring(centre: np.ndarray, tangent: np.ndarray, spec: _HandleSpec) -> np.ndarray:
    """(m, 3) points of the strap's section at a centre-line point: a flat oval or a rectangle."""
    normal = np.array([tangent[1], -tangent[0]])  # in-plane, perpendicular to the centre line
    if spec.loop == "arc":  # flat oval section
        a = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
        u, v = np.cos(a) * spec.thickness / 2, np.sin(a) * spec.width / 2
    else:  # rectangle section
        u = np.array([-1, 1, 1, -1]) * spec.thickness / 2
        v = np.array([-1, -1, 1, 1]) * spec.width / 2
    x = centre[0] + u * normal[0]
    z = centre[1] + u * normal[1]
    return np.stack([x, v, z], axis=1)


def _strap_handle(spec: _HandleSpec, body: _MugBody) -> mf.Manifold:
    """A strap lofted along the centre line as a union of convex hulls of consecutive sections.

    Each hull spans three sections, so neighbours overlap (hulls that only share a face stay separate solids).
    """
    line = _loop_centre_line(spec, body)
    tangents = np.gradient(line, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    rings = [_section_ring(p, t, spec) for p, t in zip(line, tangents, strict=True)]
    pieces = [mf.Manifold.hull_points(np.concatenate(rings[k:k + 3])) for k in range(len(rings) - 2)]
    return mf.Manifold.batch_boolean(pieces, mf.OpType.Add)


def _wire_handle(spec: _HandleSpec, body: _MugBody) -> mf.Manifold:
    """A thin round wire: a chain of capsules (hulls of two spheres) along the centre line."""
    line = _loop_centre_line(spec, body, count=16)
    radius = spec.thickness / 2
    spheres = [mf.Manifold.sphere(radius, 16).translate((float(x), 0.0, float(z))) for x, z in line]
    pieces = [mf.Manifold.batch_hull([spheres[k], spheres[k + 1]]) for k in range(len(spheres) - 1)]
    return mf.Manifold.batch_boolean(pieces, mf.OpType.Add)


_HANDLE_BUILDERS: Mapping[str, Callable[[_HandleSpec, _MugBody], mf.Manifold]] = MappingProxyType({
    "plate": _plate_handle, "strap": _strap_handle, "wire": _wire_handle})


def _handle_spec(rng: np.random.Generator, height: float) -> _HandleSpec:
    kind = str(rng.choice(HANDLE_KINDS, p=[0.4, 0.4, 0.2]))
    if kind == "wire":
        thickness = _u(rng, 0.003, 0.0045)
        width = thickness
    elif kind == "plate":
        thickness = _u(rng, 0.004, 0.009)
        width = _u(rng, 0.005, 0.02)
    else:  # flat straps: thin radially, wide along y (or the reverse for a few)
        thickness, width = sorted((_u(rng, 0.003, 0.006), _u(rng, 0.01, 0.02)))
        if rng.random() < 0.25:
            thickness, width = width * 0.7, thickness
    span = height * _u(rng, 0.25, 0.85)
    margin = 0.008 + thickness
    centre = _u(rng, margin + span / 2, max(height - margin - span / 2, margin + span / 2))
    return _HandleSpec(kind=kind, z_low=centre - span / 2, z_high=min(centre + span / 2, height - margin),
                       reach=_u(rng, 0.009, 0.045), thickness=thickness, width=width,
                       loop=str(rng.choice(["d", "square"] if kind == "plate" else ["arc", "squared"])))


def _build_imug(rng: np.random.Generator) -> _Part:
    body_kind = str(rng.choice(MUG_BODIES))
    height = _u(rng, 0.07, 0.135)
    radius = _u(rng, 0.03, 0.056)
    wall = _u(rng, 0.002, 0.008)
    bottom = _u(rng, max(wall, 0.004), 0.014)
    body = _MUG_BODY_BUILDERS[body_kind](rng, height, radius, wall, bottom)
    has_handle = bool(rng.random() >= 0.1)
    attributes: dict[str, float | str | bool] = {
        "kind": body_kind, "has_handle": has_handle, "body_height_m": height, "body_radius_m": body.radius,
        "wall_m": wall, "square_body": False}
    if not has_handle:
        return _Part(body.outer - body.cavity, None, {**attributes, "handle_style": "none"})
    spec = _handle_spec(rng, height)
    raw = _HANDLE_BUILDERS[spec.kind](spec, body)
    solid = (body.outer + raw) - body.cavity
    handle = raw - body.outer  # the part outside the body, as procedural's Shape.handle
    attributes.update(handle_style=f"{spec.kind}_{spec.loop}", handle_reach_m=spec.reach,
                      handle_thickness_m=spec.thickness, handle_width_m=spec.width,
                      handle_span_m=spec.z_high - spec.z_low, handle_center_z_m=(spec.z_low + spec.z_high) / 2)
    return _Part(solid, handle, attributes)


# --------------------------------------------------------------------------------------------- the rest


def _fit_sides(rng: np.random.Generator, low: tuple[float, ...], high: tuple[float, ...]) -> np.ndarray:
    """Independent side lengths, redrawn until the diagonal fits (thin slabs and deep boxes stay as drawn)."""
    for _ in range(64):
        sides = rng.uniform(low, high)
        if np.linalg.norm(sides) <= _FIT_DIAGONAL:
            return sides
    return sides  # rare: make_independent_shape scales it down uniformly


def _build_ibox(rng: np.random.Generator) -> _Part:
    kind = str(rng.choice(BOX_KINDS))
    sx, sy, sz = _fit_sides(rng, (0.03, 0.012, 0.03), (0.17, 0.15, 0.17))
    edge = min(_u(rng, 0.002, 0.012), 0.3 * min(sx, sy, sz))
    half = np.array([sx, sy, sz]) / 2
    if kind == "rounded":  # every edge rounded: the hull of eight corner spheres
        corners = [mf.Manifold.sphere(edge, 16).translate(tuple(s * (half - edge))) for s in _SIGNS]
        solid = mf.Manifold.batch_hull(corners)
    elif kind == "chamfered":  # every corner and edge cut at 45 degrees: the hull of the cut corners
        points = [s * (half - edge * np.array(axis)) for s in _SIGNS for axis in np.eye(3)]
        solid = mf.Manifold.hull_points(np.asarray(points))
    else:  # tissue-box style: only the vertical edges rounded
        section = mf.CrossSection.square((sx - 2 * edge, sy - 2 * edge), center=True)
        solid = mf.Manifold.extrude(section.offset(edge, mf.JoinType.Round, 2.0, 16), sz)
        solid = solid.translate((0.0, 0.0, -sz / 2))
    return _Part(solid, None, {"kind": kind, "size_x_m": sx, "size_y_m": sy, "size_z_m": sz, "edge_m": edge})


_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def _build_ican(rng: np.random.Generator) -> _Part:
    kind = str(rng.choice(CAN_KINDS))
    radius = _u(rng, 0.02, 0.062)
    height = _u(rng, 0.03, 0.17)
    if kind == "tumbler":  # a frustum, wider at the top (a paper-cup-like can)
        solid = mf.Manifold.cylinder(height, radius * _u(rng, 0.7, 0.9), radius, _SEGMENTS)
    else:
        body = mf.Manifold.cylinder(height, radius, radius, _SEGMENTS)
        rim = min(0.004, 0.1 * height)
        proud = _u(rng, 0.0008, 0.002)  # rolled rims stand out of the body (procedural's are set in)
        parts = [body, mf.Manifold.cylinder(rim, radius + proud, radius + proud, _SEGMENTS),
                 mf.Manifold.cylinder(rim, radius + proud, radius + proud, _SEGMENTS).translate((0, 0, height - rim))]
        for z in np.linspace(0.25, 0.75, int(rng.integers(0, 4))) * height:  # ribs of food cans
            parts.append(mf.Manifold.cylinder(0.002, radius + proud / 2, radius + proud / 2, _SEGMENTS)
                         .translate((0.0, 0.0, float(z))))
        solid = mf.Manifold.batch_boolean(parts, mf.OpType.Add)
        if kind == "oval":  # a tin: squashed along y
            solid = solid.scale((1.0, _u(rng, 0.45, 0.75), 1.0))
    return _Part(solid, None, {"kind": kind, "radius_m": radius, "can_height_m": height})


def _build_ibottle(rng: np.random.Generator) -> _Part:
    kind = str(rng.choice(BOTTLE_KINDS))
    height = _u(rng, 0.1, 0.17)
    half = _u(rng, 0.02, 0.05)
    shoulder = height * _u(rng, 0.5, 0.72)
    neck_r = _u(rng, 0.008, 0.015)
    neck_top = height * _u(rng, 0.86, 0.92)
    if kind == "square":  # rounded-rectangle section; the shoulder is the same section extruded to a point
        depth = half * _u(rng, 0.5, 1.0)
        section = mf.CrossSection.square((2 * half, 2 * depth), center=True)
        section = section.offset(-0.3 * depth, mf.JoinType.Round).offset(0.3 * depth, mf.JoinType.Round, 2.0, 16)
        body = mf.Manifold.extrude(section, shoulder)
        taper = neck_r / depth
        top = mf.Manifold.extrude(section, neck_top - shoulder, 0, 0.0, (taper, taper)).translate((0, 0, shoulder))
        parts = [body, top]
    else:  # a smooth convex body: the hull of discs
        z = np.linspace(0.0, shoulder, 4)
        profile = half * (0.92 + 0.08 * np.sin(np.pi * z / shoulder))
        body = mf.Manifold.batch_hull([_disc(r, zi) for r, zi in zip(profile, z, strict=True)]
                                      + [_disc(neck_r, neck_top - 0.01)])
        parts = [body]
    neck = mf.Manifold.cylinder(neck_top - shoulder + 0.005, neck_r, neck_r, _SEGMENTS).translate((0, 0, shoulder))
    cap_r = neck_r * _u(rng, 1.1, 1.5)
    cap = mf.Manifold.cylinder(height - neck_top, cap_r, cap_r, _SEGMENTS).translate((0.0, 0.0, neck_top))
    solid = mf.Manifold.batch_boolean([*parts, neck, cap], mf.OpType.Add)
    return _Part(solid, None, {"kind": kind, "half_width_m": half, "bottle_height_m": height})


_BUILDERS: Mapping[str, Callable[[np.random.Generator], _Part]] = MappingProxyType({
    "imug": _build_imug, "ibox": _build_ibox, "ican": _build_ican, "ibottle": _build_ibottle})
