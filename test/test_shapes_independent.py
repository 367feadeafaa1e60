"""The independent out-of-family generator (pssnet_core.shapes.independent) and the one identity lookup (shape_of).

Same contract as the procedural generator (watertight, object frame, size limit, deterministic, handles as
declared), and measurably outside procedural's ranges: the point of an out-of-family test set.
"""

from __future__ import annotations

import numpy as np
import pytest

from pssnet_core.shapes import (
    INDEPENDENT_FAMILIES,
    MAX_DIAGONAL,
    ShapeError,
    ShapeId,
    make_independent_shape,
    make_shape,
    shape_of,
    split_seeds,
)

SEEDS = split_seeds("test", 24)


@pytest.fixture(scope="module")
def shapes():
    return {f: [make_independent_shape(f, s) for s in SEEDS] for f in INDEPENDENT_FAMILIES}


def _back_radius(shape) -> float:
    """Largest radial distance of the body on the side away from the handle (x < 0)."""
    v = np.asarray(shape.mesh.vertices)
    return float(np.hypot(v[v[:, 0] < 0, 0], v[v[:, 0] < 0, 1]).max())


def test_every_shape_is_a_watertight_solid_in_the_object_frame(shapes):
    for family, group in shapes.items():
        for shape in group:
            mesh = shape.mesh
            assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, shape.identity
            assert len(mesh.split(only_watertight=False)) == 1, f"{shape.identity} is in several pieces"
            low, high = shape.bounds
            assert low[2] == pytest.approx(0.0, abs=1e-9)
            assert np.linalg.norm(high - low) <= MAX_DIAGONAL
            if family != "imug":  # symmetric objects: the bounds are centred on the axis
                np.testing.assert_allclose((low[:2] + high[:2]) / 2, 0.0, atol=1e-6)
            else:  # the body reaches about as far along -x as along +-y (polygons: within a corner's rounding)
                assert low[1] == pytest.approx(-high[1], abs=2e-4)  # rounded corners: polygonised unevenly
                assert -low[0] == pytest.approx(high[1], rel=0.12)
            assert shape.attributes["generator"] == "independent"


def test_generation_is_deterministic_and_seeds_differ():
    a, b = make_independent_shape("imug", SEEDS[3]), make_independent_shape("imug", SEEDS[3])
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    assert a.attributes == b.attributes
    c = make_independent_shape("imug", SEEDS[4])
    assert a.mesh.volume != pytest.approx(c.mesh.volume, rel=1e-3)


def test_handles_are_present_exactly_when_declared_and_point_along_plus_x(shapes):
    declared = [s.attributes["has_handle"] for s in shapes["imug"]]
    assert any(declared), "no test mug has a handle"
    for shape in shapes["imug"]:
        assert (shape.handle is not None) == shape.attributes["has_handle"], shape.identity
        if shape.handle is None:
            assert shape.attributes["handle_style"] == "none"
            continue
        handle = shape.handle
        assert handle.is_watertight and handle.volume > 1e-7, shape.identity
        # Outside the body, on +x, within the object.
        assert handle.bounds[0, 0] > 0.0 and handle.bounds[1, 0] == pytest.approx(shape.bounds[1, 0], abs=1e-6)
        assert handle.bounds[1, 0] > _back_radius(shape) + 0.003
        assert abs(handle.bounds[0, 1] + handle.bounds[1, 1]) < 1e-3  # symmetric about the xz-plane
    for family in ("ibox", "ican", "ibottle"):
        assert all(s.handle is None for s in shapes[family])


def test_shapes_reach_outside_the_procedural_ranges(shapes):
    """Measured on the meshes: handles thinner along y and with shorter reaches than procedural's can be, bodies
    taller or shorter, and several constructions of each kind."""
    procedural = [make_shape("mug", s) for s in SEEDS]
    proc_handles = [m for m in procedural if m.handle is not None]
    proc_y = min(m.handle.extents[1] for m in proc_handles)  # >= 2 x 3.5 mm tube half-width by construction
    proc_reach = min(m.handle.bounds[1, 0] - m.attributes["radius"] for m in proc_handles)  # >= 14 mm
    handled = [s for s in shapes["imug"] if s.handle is not None]
    assert min(s.handle.extents[1] for s in handled) < min(proc_y, 0.007) * 0.7  # wire handles
    assert min(s.handle.bounds[1, 0] - _back_radius(s) for s in handled) < min(proc_reach, 0.014) * 0.8
    heights = [s.attributes["height"] for s in shapes["imug"]]
    assert min(heights) < 0.08 or max(heights) > 0.12  # procedural mugs are 8-12 cm tall
    assert len({s.attributes["kind"] for s in shapes["imug"]}) >= 3
    assert len({s.attributes["handle_style"].split("_")[0] for s in handled}) == 3
    # Boxes: the hidden side is drawn independently of the visible face, so slabs and deep boxes both occur.
    ratios = [s.mesh.extents[1] / s.mesh.extents[0] for s in shapes["ibox"]]
    assert min(ratios) < 0.25 and max(ratios) > 1.0


def test_shape_of_looks_up_every_generator():
    assert shape_of("imug-2000001").identity == ShapeId("imug", 2000001)
    np.testing.assert_array_equal(shape_of(ShapeId("box", 2000000)).mesh.vertices,
                                  make_shape("box", 2000000).mesh.vertices)
    with pytest.raises(ShapeError, match="unknown family"):
        shape_of("teapot-00001")
    with pytest.raises(ShapeError, match="expected one of"):
        make_independent_shape("mug", 1)  # procedural's family: not this generator's
    with pytest.raises(ShapeError):
        make_independent_shape("imug", -1)
