"""Procedural object families: validity, size limit, determinism, splits, mug handle conventions."""

from __future__ import annotations

import numpy as np
import pytest

from pssnet_core.data.scenes import ObjectScene
from pssnet_core.shapes import (
    BROAD_FAMILIES,
    EDGED_FAMILIES,
    FAMILIES,
    MAX_DIAGONAL,
    SPLIT_RANGES,
    YCB_FAMILIES,
    Shape,
    ShapeError,
    ShapeId,
    make_shape,
    split_of_seed,
    split_seeds,
)

SEEDS = list(range(10))


@pytest.fixture(scope="module")
def mugs() -> list[Shape]:
    """Enough mugs to see every variant (5 % square bodies, 10 % without a handle)."""
    return [make_shape("mug", seed) for seed in range(120)]


def test_family_lists() -> None:
    assert FAMILIES[:6] == ("mug", "box", "can", "bottle", "bowl", "irregular")
    assert YCB_FAMILIES == FAMILIES[1:6]
    assert FAMILIES[6:10] == BROAD_FAMILIES == ("mug_broad", "box_broad", "can_broad", "bottle_broad")
    assert FAMILIES[10:] == EDGED_FAMILIES == ("box_edged",)


@pytest.mark.parametrize("family", FAMILIES)
def test_family_is_valid_solid_in_object_frame(family: str) -> None:
    for seed in SEEDS + split_seeds("test", 3):
        shape = make_shape(family, seed)
        mesh = shape.mesh
        assert shape.identity == ShapeId(family, seed)
        assert mesh.is_watertight, shape.identity
        assert mesh.is_winding_consistent, shape.identity
        assert mesh.volume > 1e-6, shape.identity  # more than 1 cm^3, outward normals
        assert len(mesh.split(only_watertight=False)) == 1, f"{shape.identity} is in several pieces"
        low, high = shape.bounds
        assert low[2] == pytest.approx(0.0, abs=1e-7), "base must be at z = 0"
        assert (low[1] + high[1]) / 2 == pytest.approx(0.0, abs=1e-6)
        if family not in ("mug", "mug_broad"):  # a handle shifts a mug's x-centre; its body axis is at x = 0
            assert (low[0] + high[0]) / 2 == pytest.approx(0.0, abs=1e-6)
        assert 0.02 < shape.attributes["height"] < 0.18
        assert shape.attributes["volume"] == pytest.approx(mesh.volume, rel=1e-3)
        assert 0.0 < shape.attributes["scale_to_fit"] <= 1.0


@pytest.mark.parametrize("family", FAMILIES)
def test_size_limit(family: str) -> None:
    seeds = range(60) if family.startswith("mug") else range(30)
    diagonals = [float(np.linalg.norm(np.ptp(make_shape(family, s).mesh.vertices, axis=0))) for s in seeds]
    assert max(diagonals) <= MAX_DIAGONAL
    assert min(diagonals) > 0.05, "objects should be hand-sized, not tiny"


@pytest.mark.parametrize("family", FAMILIES)
def test_deterministic_and_seed_dependent(family: str) -> None:
    a, b = make_shape(family, 7), make_shape(family, 7)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert np.array_equal(a.mesh.faces, b.mesh.faces)
    assert a.attributes == b.attributes
    c = make_shape(family, 8)
    assert c.mesh.vertices.shape != a.mesh.vertices.shape or not np.allclose(c.mesh.vertices, a.mesh.vertices)


def test_families_with_same_seed_differ() -> None:
    volumes = {family: make_shape(family, 3).mesh.volume for family in FAMILIES}
    assert len({round(v, 9) for v in volumes.values()}) == len(FAMILIES)


def test_shape_id_string_and_parse() -> None:
    identity = ShapeId("mug", 42)
    assert str(identity) == "mug-00042"
    assert ShapeId.parse("mug-00042") == identity
    assert ShapeId.parse(str(ShapeId("bowl", 2_000_001))) == ShapeId("bowl", 2_000_001)
    assert {ShapeId("mug", 1), ShapeId("mug", 1)} == {ShapeId("mug", 1)}  # hashable, value equality
    with pytest.raises(ShapeError, match="seed"):
        ShapeId("mug", -1)
    with pytest.raises(ShapeError, match="family"):
        ShapeId("my-mug", 1)
    with pytest.raises(ShapeError, match="identity"):
        ShapeId.parse("mug")


def test_make_shape_rejects_bad_input() -> None:
    with pytest.raises(ShapeError, match="unknown family 'teapot'"):
        make_shape("teapot", 0)
    with pytest.raises(ShapeError, match="seed"):
        make_shape("mug", -3)


def test_split_seeds_disjoint() -> None:
    train, val, test = (set(split_seeds(s, 5000)) for s in ("train", "val", "test"))
    assert len(train) == len(val) == len(test) == 5000
    assert not train & test and not train & val and not val & test
    assert split_seeds("train", 3) == split_seeds("train", 5)[:3]  # prefixes: growing a split keeps its objects
    assert all(split_of_seed(s) == "test" for s in test)
    ranges = sorted(SPLIT_RANGES.values())
    assert all(a[1] <= b[0] for a, b in zip(ranges, ranges[1:], strict=False))
    assert split_seeds("test", 0) == []
    with pytest.raises(ShapeError, match="unknown split"):
        split_seeds("holdout", 3)
    with pytest.raises(ShapeError, match="count"):
        split_seeds("train", -1)
    with pytest.raises(ShapeError, match="count"):
        split_seeds("train", 10**7)


def test_box_corners_order() -> None:
    shape = make_shape("box", 1)
    corners = shape.box_corners()
    low, high = shape.bounds
    assert corners.shape == (8, 3)
    for i, corner in enumerate(corners):
        expected = [high[a] if (i >> a) & 1 else low[a] for a in range(3)]
        np.testing.assert_allclose(corner, expected)
    np.testing.assert_allclose(corners.min(axis=0), low)
    np.testing.assert_allclose(corners.max(axis=0), high)
    # A box's corners are mesh vertices.
    assert np.min(np.linalg.norm(shape.mesh.vertices[None] - corners[:, None], axis=2), axis=1).max() < 1e-9


def test_mug_handle_points_along_plus_x(mugs: list[Shape]) -> None:
    with_handle = [m for m in mugs if m.attributes["has_handle"]]
    assert len(with_handle) > 90
    for mug in with_handle:
        handle = mug.handle
        assert handle is not None
        assert handle.is_watertight and handle.volume > 0, mug.identity
        assert handle.centroid[0] > mug.attributes["radius"], mug.identity
        assert abs(handle.centroid[1]) < 1e-3, mug.identity
        # The handle solid is what sticks out of the body: nothing of it lies inside the body's outline.
        radial = np.linalg.norm(handle.vertices[:, :2], axis=1)
        if not mug.attributes["square_body"]:
            assert radial.min() > mug.attributes["radius_min"] * 0.98, mug.identity
        assert handle.volume < 0.5 * mug.mesh.volume
        # The body's axis is at x = y = 0: its far side (-x) is at -radius.
        assert mug.bounds[0, 0] == pytest.approx(-mug.attributes["radius"], abs=1e-3)
        assert mug.bounds[1, 0] > mug.attributes["radius"] + 0.01  # the handle reaches out along +x
        assert mug.bounds[1, 0] == pytest.approx(handle.bounds[1, 0], abs=1e-9)


def test_mug_without_handle(mugs: list[Shape]) -> None:
    plain = [m for m in mugs if not m.attributes["has_handle"]]
    assert 3 <= len(plain) <= 25, "about 10 % of mugs have no handle"
    for mug in plain:
        assert mug.handle is None
        assert mug.attributes["handle_style"] == "none"
        low, high = mug.bounds
        assert (low[0] + high[0]) / 2 == pytest.approx(0.0, abs=1e-6)


def test_mug_variety(mugs: list[Shape]) -> None:
    attrs = [m.attributes for m in mugs]
    assert {a["profile"] for a in attrs} == {"straight", "tapered", "barrel", "square"}
    assert {a["handle_style"] for a in attrs} == {"ring", "d_shape", "square", "none"}
    square = sum(a["square_body"] for a in attrs)
    assert 1 <= square <= 15, "a few (about 5 %) square-bodied mugs"
    assert any(abs(a.get("handle_tilt_deg", 0.0)) > 10 for a in attrs)
    assert {a.get("handle_size") for a in attrs} >= {"small", "large"}
    assert {a.get("handle_position") for a in attrs} >= {"low", "high"}
    heights = [a["height"] for a in attrs]
    assert 0.07 < min(heights) and max(heights) <= 0.12 + 1e-9
    walls = [a["wall"] for a in attrs]
    assert 0.003 <= min(walls) and max(walls) <= 0.006


def _occupancy(shape: Shape, points: list[list[float]]) -> np.ndarray:
    import open3d as o3d  # imported here: slow to import, and only this test needs it

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(shape.mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(shape.mesh.faces, dtype=np.uint32)))
    return scene.compute_occupancy(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy() > 0.5


def test_mug_is_hollow() -> None:
    for seed in range(4):
        mug = make_shape("mug", seed)
        a = mug.attributes
        height, bottom, wall = a["height"], a["bottom_thickness"], a["wall"]
        # Radius of the body at mid-height, measured on the mesh along -x (away from the handle).
        mid = [[-x, 0.0, height / 2] for x in np.linspace(0.0, a["radius"] + 0.002, 400)]
        outer = max(-p[0] for p, inside in zip(mid, _occupancy(mug, mid), strict=True) if inside)
        probes = [[0.0, 0.0, bottom / 2],                     # the floor is solid
                  [0.0, 0.0, bottom + 0.003],                 # just above the floor: cavity
                  [0.0, 0.0, height / 2],                     # cavity
                  [0.0, 0.0, height + 0.005],                 # above the rim
                  [-(outer - wall / 2), 0.0, height / 2],     # inside the wall
                  [-(outer - wall - 0.001), 0.0, height / 2]]  # just inside the inner wall surface
        assert _occupancy(mug, probes).tolist() == [True, False, False, False, True, False], mug.identity


@pytest.mark.parametrize("family", YCB_FAMILIES)
def test_ycb_like_attributes(family: str) -> None:
    shapes = [make_shape(family, s) for s in range(12)]
    assert all(s.handle is None for s in shapes)
    if family != "bowl":
        assert len({s.attributes["kind"] for s in shapes}) >= 2
    if family == "box":
        for s in shapes:
            assert s.mesh.volume == pytest.approx(np.prod(s.mesh.extents), rel=1e-9)
    if family == "bowl":
        for s in shapes:  # open at the top and much lighter than a solid of the same outline
            assert s.mesh.volume < 0.5 * np.pi * s.attributes["rim_radius"] ** 2 * s.attributes["height"]


def test_edged_boxes_soften_their_edges_and_keep_their_sides() -> None:
    """box_edged: the bounds are the drawn sides; a bevel or rounding removes the corner (and a rounded vertical
    edge removes the area between a square and its inscribed 24-gon along the height), a sharp box keeps it."""
    shapes = [make_shape("box_edged", seed) for seed in range(40)]
    kinds = {s.attributes["kind"] for s in shapes}
    assert kinds == {"edged_sharp", "edged_bevelled", "edged_rounded_vertical", "edged_rounded"}
    for s in shapes:
        edge, extents = s.attributes["edge_m"], s.mesh.extents
        assert s.mesh.is_watertight and 0.0 <= edge <= extents.min() / 3 + 1e-9
        low = s.mesh.bounds[0]
        inset = edge / 4 if edge > 0 else 0.001
        near_corner = low + inset  # inside a sharp box, outside a bevelled or rounded one
        near_face = low + np.array([extents[0] / 2, extents[1] / 2, inset])  # inside every box
        inside = ObjectScene(s, threads=1).occupancy(np.array([near_corner, near_face]))
        assert inside[1] and inside[0] == (s.attributes["kind"] == "edged_sharp")
        if s.attributes["kind"] == "edged_rounded_vertical":
            removed = np.prod(extents) - s.mesh.volume
            # The rounded edge is a 24-gon: each corner keeps a quarter of its area, 6 sin(15 deg) r^2.
            assert removed == pytest.approx((4 - 24 / 2 * np.sin(2 * np.pi / 24)) * edge ** 2 * extents[2], rel=0.005)


def test_broad_families_break_the_base_families_priors() -> None:
    """box_broad: depth independent of the visible width and reaching what the grid holds; can/bottle_broad:
    proportions the base families never have; mug_broad: handles reaching further, and every mug with a handle
    solid for the handle measures."""
    def extents(family: str, count: int = 150) -> np.ndarray:
        return np.array([make_shape(family, seed).mesh.extents for seed in range(count)])

    base, broad = extents("box"), extents("box_broad")
    assert abs(np.corrcoef(broad[:, 0], broad[:, 1])[0, 1]) < 0.5  # width says little about depth
    assert broad[:, 1].max() > 0.14 > base[:, 1].max()  # deeper boxes than any base box
    assert np.ptp(np.log(broad[:, 1] / broad[:, 0])) > 1.5 * np.ptp(np.log(base[:, 1] / base[:, 0]))
    for family in ("can", "bottle"):
        ratio = {f: np.log(e[:, 2] / e[:, 0]) for f, e in ((family, extents(family, 60)),
                                                              (f"{family}_broad", extents(f"{family}_broad", 60)))}
        assert np.ptp(ratio[f"{family}_broad"]) > np.ptp(ratio[family])
    reaches = [make_shape("mug_broad", seed).attributes.get("handle_reach", 0.0) for seed in range(60)]
    assert max(reaches) > 0.04 > 0.034  # procedural mugs reach at most 0.034 m
    handled = [make_shape("mug_broad", seed) for seed in range(20)]
    assert all(m.handle is not None for m in handled if m.attributes["has_handle"])
