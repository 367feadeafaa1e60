"""Mesh folder loader: ShapeNet/YCB/flat layouts round-tripped through export, normalisation, repair, errors."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from pssnet_core.shapes import (
    FAMILIES,
    MeshLoadError,
    Shape,
    ShapeId,
    export_shapes,
    load_mesh,
    load_mesh_folder,
    make_shape,
    normalize_mesh,
)
from pssnet_core.shapes.mesh_io import detect_layout


@pytest.fixture(scope="module")
def shapes() -> list[Shape]:
    return [make_shape(family, seed) for family in FAMILIES for seed in (0, 1)]


def _assert_same_geometry(loaded: trimesh.Trimesh, original: trimesh.Trimesh) -> None:
    """Same vertex positions (both ways) and volume, after the loader's normalisation of the original."""
    reference, _ = normalize_mesh(original)
    assert len(loaded.vertices) == len(reference.vertices)
    assert cKDTree(reference.vertices).query(loaded.vertices)[0].max() < 1e-6
    assert cKDTree(loaded.vertices).query(reference.vertices)[0].max() < 1e-6
    assert loaded.is_watertight
    assert loaded.volume == pytest.approx(original.volume, rel=0.01)


@pytest.mark.parametrize("layout", ["shapenet", "ycb", "flat"])
def test_export_load_round_trip(tmp_path: Path, shapes: list[Shape], layout: str) -> None:
    paths = export_shapes(shapes, tmp_path, layout)
    assert all(p.is_file() and p.suffix == ".obj" for p in paths)
    if layout == "shapenet":
        assert paths[0].relative_to(tmp_path).parts == ("03797390", "mug-00000", "models", "model_normalized.obj")
    elif layout == "ycb":
        assert paths[0].relative_to(tmp_path).parts == ("mug-00000", "google_16k", "textured.obj")
    else:
        assert paths[0].relative_to(tmp_path).parts == ("mug-00000.obj",)
    assert detect_layout(tmp_path) == layout
    loaded = load_mesh_folder(tmp_path)  # layout="auto"
    assert len(loaded) == len(shapes)
    assert [s.identity for s in loaded] == [ShapeId(f"user:{layout}", i) for i in range(len(shapes))]
    by_name = {s.attributes["name"]: s for s in loaded}
    for original in shapes:
        shape = by_name[str(original.identity)]
        assert shape.handle is None
        assert shape.attributes["layout"] == layout
        assert Path(shape.attributes["source_path"]).is_file()
        assert shape.attributes["watertight"] is True and shape.attributes["repaired"] is False
        mesh = shape.mesh
        if layout == "shapenet":
            # Unit-normalised y-up on disk: the loader turns it z-up; target_size restores metres.
            assert shape.attributes["synset"] == str(Path(shape.attributes["source_path"]).parents[2].name)
            assert shape.attributes["diagonal"] == pytest.approx(1.0, rel=1e-6)
            largest = float(np.max(original.mesh.extents))
            mesh, _ = normalize_mesh(mesh, target_size=largest)
        assert shape.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
        _assert_same_geometry(mesh, original.mesh)


def test_shapenet_target_size_and_y_up(tmp_path: Path, shapes: list[Shape]) -> None:
    mug = shapes[0]
    (path,) = export_shapes([mug], tmp_path, "shapenet")
    raw = trimesh.load(path, force="mesh")
    # On disk the height is along y (ShapeNet's up axis).
    assert np.ptp(raw.vertices[:, 1]) / np.linalg.norm(raw.extents) == pytest.approx(
        mug.mesh.extents[2] / np.linalg.norm(mug.mesh.extents), rel=1e-6)
    (loaded,) = load_mesh_folder(tmp_path, layout="shapenet", target_size=0.12)
    assert float(np.max(loaded.mesh.extents)) == pytest.approx(0.12, rel=1e-9)
    assert loaded.attributes["height"] == pytest.approx(0.12 * mug.mesh.extents[2] / np.max(mug.mesh.extents))
    # Handle side stays on the same side: the loaded mug is the original, shifted to its bounds centre.
    _assert_same_geometry(normalize_mesh(loaded.mesh, target_size=float(np.max(mug.mesh.extents)))[0], mug.mesh)


def test_ycb_tsdf_fallback_and_scale(tmp_path: Path, shapes: list[Shape]) -> None:
    can = shapes[4]
    assert can.identity.family == "can"
    # A YCB download in millimetres with only the tsdf mesh.
    in_mm = Shape(can.identity, trimesh.Trimesh(can.mesh.vertices * 1000.0 + [5.0, -3.0, 40.0], can.mesh.faces),
                  None, {})
    (path,) = export_shapes([in_mm], tmp_path, "ycb")
    tsdf = path.parent.parent / "tsdf" / "textured.obj"
    tsdf.parent.mkdir()
    shutil.move(path, tsdf)
    path.parent.rmdir()
    (loaded,) = load_mesh_folder(tmp_path, scale=0.001)
    assert loaded.attributes["layout"] == "ycb" and loaded.attributes["source_path"] == str(tsdf)
    assert loaded.attributes["scale"] == 0.001
    _assert_same_geometry(loaded.mesh, can.mesh)


def test_flat_folder_reads_ply_and_stl(tmp_path: Path, shapes: list[Shape]) -> None:
    shapes[2].mesh.export(tmp_path / "a_box.ply")
    shapes[6].mesh.export(tmp_path / "b_bottle.STL")
    (tmp_path / "notes.txt").write_text("not a mesh")
    loaded = load_mesh_folder(tmp_path)
    assert [s.attributes["name"] for s in loaded] == ["a_box", "b_bottle"]
    _assert_same_geometry(loaded[0].mesh, shapes[2].mesh)
    # STL stores triangle soup; the loader merges the vertices back into a closed surface.
    assert loaded[1].mesh.is_watertight
    assert loaded[1].mesh.volume == pytest.approx(shapes[6].mesh.volume, rel=1e-4)


def test_normalize_mesh_conventions() -> None:
    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    box.apply_translation([10.0, -5.0, 7.0])
    moved, factor = normalize_mesh(box, scale=0.01)
    assert factor == 0.01
    np.testing.assert_allclose(moved.bounds, [[-0.01, -0.015, 0.0], [0.01, 0.015, 0.04]], atol=1e-12)
    upright, _ = normalize_mesh(box, y_up=True, target_size=0.1)
    np.testing.assert_allclose(upright.extents, [0.05, 0.1, 0.075], atol=1e-12)  # y (3) became z
    assert upright.bounds[0, 2] == pytest.approx(0.0)
    with pytest.raises(MeshLoadError, match="not both"):
        normalize_mesh(box, scale=0.5, target_size=0.1)
    with pytest.raises(MeshLoadError, match="positive"):
        normalize_mesh(box, scale=-1.0)


def test_repair_fills_a_small_hole_and_flags_a_big_one(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    trimesh.Trimesh(box.vertices, box.faces[1:]).export(tmp_path / "one_triangle_missing.obj")
    cylinder = trimesh.creation.cylinder(radius=0.02, height=0.05, sections=24)
    side = np.abs(cylinder.face_normals[:, 2]) < 0.5
    trimesh.Trimesh(cylinder.vertices, cylinder.faces[side]).export(tmp_path / "open_tube.obj")  # no caps
    fixed, open_tube = load_mesh_folder(tmp_path, layout="flat")
    assert fixed.attributes["repaired"] is True and fixed.attributes["watertight"] is True
    assert fixed.mesh.volume == pytest.approx(0.05**3, rel=1e-9)
    assert open_tube.attributes["watertight"] is False
    assert "volume" not in open_tube.attributes
    assert len(open_tube.mesh.faces) == int(side.sum())  # kept, flagged, not dropped


def test_corrupt_obj_names_the_file(tmp_path: Path, shapes: list[Shape]) -> None:
    export_shapes(shapes[:2], tmp_path, "flat")
    bad = tmp_path / "broken.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 7\n")  # face refers to a missing vertex
    with pytest.raises(MeshLoadError, match="broken.obj"):
        load_mesh_folder(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = load_mesh_folder(tmp_path, skip_errors=True)
    assert any("broken.obj" in str(w.message) for w in caught)
    # Sorted order: broken.obj (index 0) is skipped, the others keep their index.
    assert [s.identity.seed for s in loaded] == [1, 2]
    empty = tmp_path / "empty.obj"
    empty.write_text("this is not an obj file\n")
    with pytest.raises(MeshLoadError, match="empty.obj.*no triangles"):
        load_mesh(empty)
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(MeshLoadError, match="garbage.stl"):
        load_mesh(garbage)


def test_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(MeshLoadError, match="does not exist"):
        load_mesh_folder(tmp_path / "nope")
    with pytest.raises(MeshLoadError, match="cannot tell the layout"):
        load_mesh_folder(tmp_path)
    with pytest.raises(MeshLoadError, match="unknown layout"):
        load_mesh_folder(tmp_path, layout="obj")
    with pytest.raises(MeshLoadError, match="no meshes found"):
        load_mesh_folder(tmp_path, layout="shapenet")
    (tmp_path / "002_master_chef_can" / "poisson").mkdir(parents=True)
    with pytest.raises(MeshLoadError, match="google_16k/textured.obj"):
        load_mesh_folder(tmp_path, layout="ycb")
    with pytest.raises(MeshLoadError, match="does not exist"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(MeshLoadError, match="unknown export layout"):
        export_shapes([], tmp_path, "zip")
