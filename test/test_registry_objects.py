"""Real modelled objects from registry packages (pssnet_core.shapes.registry_objects), offline.

Every test works on a small fake wheel written here (meshes exported by trimesh from procedural shapes, placed
and oriented like a package would): no network, no third-party mesh. The real manifest is checked for form only.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from pssnet_core.shapes import MAX_DIAGONAL, make_shape
from pssnet_core.shapes.registry_objects import (
    MANIFEST,
    REGISTRY_FAMILIES,
    RegistryObject,
    RegistryObjectError,
    RegistryPart,
    cache_dir,
    fetch_archive,
    load_registry_object,
    read_member,
    registry_identities,
)

BODY_SEED = 2000025  # a round, straight test mug without a handle


def _export(mesh: trimesh.Trimesh, suffix: str) -> bytes:
    return mesh.export(file_type=suffix) if suffix == "stl" else mesh.export(file_type=suffix).encode()


@pytest.fixture(scope="module")
def fake_wheel(tmp_path_factory):
    """A wheel holding a mug modelled as modelled mugs often are: a closed body and a handle ring whose ends are left
    open inside the body, in millimetres, handle along +y, base below z = 0; plus a box.

    Returns the cache folder, the wheel, the members' sha256 and the expected mug (body and its handle outside it,
    in the object frame).
    """
    root = tmp_path_factory.mktemp("registry_cache")
    body = make_shape("mug", BODY_SEED).mesh.copy()
    body.apply_scale(0.8)  # with its handle well within the size limit (no fitting to compare against)
    v = np.asarray(body.vertices)
    radius = float(np.hypot(v[:, 0], v[:, 1]).max())
    ring = trimesh.creation.torus(major_radius=0.02, minor_radius=0.004, major_sections=48, minor_sections=12)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # in the xz-plane
    centre = np.array([radius + 0.006, 0.0, 0.5 * body.bounds[1, 2]])
    ring.apply_translation(centre)
    expected_handle = ring.difference(body.convex_hull, engine="manifold")
    # The ring's sections on the body side removed whole: two open ends, buried in the body.
    open_ring = ring.copy()
    offset = open_ring.triangles_center - centre
    open_ring.update_faces(np.abs(np.arctan2(offset[:, 2], offset[:, 0])) < 0.625 * np.pi)  # 15 of 48 sections
    assert not open_ring.is_watertight
    members = {}
    for name, part in (("fake/mug_body.obj", body), ("fake/mug_handle.obj", open_ring)):
        part = part.copy()
        part.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1]))  # handle to +y
        part.apply_scale(1000.0)  # millimetres
        part.apply_translation([0.0, 0.0, -20.0])
        members[name] = _export(part, "obj")
    members["fake/box.stl"] = _export(trimesh.creation.box((40.0, 20.0, 60.0)), "stl")
    path = root / "fakepkg-1.0-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
        z.writestr("fakepkg-1.0.dist-info/METADATA", "Name: fakepkg\nVersion: 1.0\nLicense: MIT\n")
    sha = {name: hashlib.sha256(data).hexdigest() for name, data in members.items()}
    return root, path, sha, (body, expected_handle)


def _mug_entry(sha) -> RegistryObject:
    parts = tuple(RegistryPart(name, sha[name]) for name in ("fake/mug_body.obj", "fake/mug_handle.obj"))
    return RegistryObject("fake_mug", "rmug", "fakepkg", "1.0", "MIT", "https://example.invalid/fakepkg", parts,
                          yaw_deg=-90.0, scale=0.001, real_size="a procedural mug exported in millimetres")


def test_a_modelled_mug_becomes_a_watertight_mug_with_its_handle_on_plus_x(fake_wheel):
    root, _, sha, (body, handle) = fake_wheel
    shape = load_registry_object(_mug_entry(sha), 0, root)
    mesh = shape.mesh
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1
    assert shape.attributes["repair"] == "filled holes, parts united"
    # Metres, base at z = 0, the body's axis at x = y = 0: the body and its handle where they were made.
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(mesh.bounds[0], body.bounds[0], atol=2e-4)
    assert mesh.bounds[1, 0] == pytest.approx(handle.bounds[1, 0], abs=2e-4)
    assert mesh.volume == pytest.approx(body.volume + handle.volume, rel=0.02)
    assert shape.attributes["scale_to_fit"] == 1.0 and shape.attributes["diagonal"] <= MAX_DIAGONAL
    # The handle split off by the body's solid of revolution is the ring outside the body.
    assert shape.handle is not None and shape.attributes["has_handle"]
    np.testing.assert_allclose(shape.handle.bounds, handle.bounds, atol=1.5e-3)
    assert shape.handle.volume == pytest.approx(handle.volume, rel=0.15)
    assert str(shape.identity) == "rmug-00000"


def test_a_box_is_scaled_and_fitted_to_the_size_limit(fake_wheel):
    root, _, sha, _ = fake_wheel
    entry = RegistryObject("fake_box", "rbox", "fakepkg", "1.0", "MIT", "https://example.invalid/fakepkg",
                           (RegistryPart("fake/box.stl", sha["fake/box.stl"]),), yaw_deg=0.0, scale=0.004,
                           real_size="16 x 8 x 24 cm: too large for the grid")
    shape = load_registry_object(entry, 3, root)
    fit = 0.175 / float(np.linalg.norm([0.16, 0.08, 0.24]))
    assert shape.attributes["scale_to_fit"] == pytest.approx(fit)
    np.testing.assert_allclose(shape.mesh.extents, np.array([0.16, 0.08, 0.24]) * fit, rtol=1e-6)
    np.testing.assert_allclose(shape.mesh.bounds[0], [-0.08 * fit, -0.04 * fit, 0.0], atol=1e-9)
    assert shape.handle is None and shape.attributes["repair"] == "none"


def test_bad_members_and_archives_give_clear_errors(fake_wheel, tmp_path):
    root, path, sha, _ = fake_wheel
    with pytest.raises(RegistryObjectError, match="has no member 'fake/teapot.obj'"):
        read_member(path, "fake/teapot.obj")
    with pytest.raises(RegistryObjectError, match="a different file"):
        read_member(path, "fake/box.stl", "0" * 64)
    entry = _mug_entry(sha)
    with pytest.raises(RegistryObjectError, match="has no member"):
        load_registry_object(replace(entry, parts=(RegistryPart("fake/missing.stl", "0" * 64),)), 0, root)
    # A corrupt archive (truncated download) and a corrupt member (not a mesh).
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "fakepkg-1.0-py3-none-any.whl").write_bytes(path.read_bytes()[: 2000])
    with pytest.raises(RegistryObjectError, match="cannot be read"):
        load_registry_object(entry, 0, broken)
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    with zipfile.ZipFile(garbage / "fakepkg-1.0-py3-none-any.whl", "w") as z:
        z.writestr("fake/box.stl", b"solid nothing\nendsolid nothing\n")
    bad = RegistryPart("fake/box.stl", hashlib.sha256(b"solid nothing\nendsolid nothing\n").hexdigest())
    with pytest.raises(RegistryObjectError, match=r"fakepkg==1\.0:fake/box\.stl"):
        load_registry_object(replace(entry, parts=(bad,)), 0, garbage)


def test_fetch_uses_the_cache_and_says_how_to_work_offline(fake_wheel, tmp_path, monkeypatch):
    root, path, _, _ = fake_wheel
    calls = []

    def offline(command, **kwargs):
        calls.append(command)
        return subprocess.CompletedProcess(command, 1, "", "ERROR: Could not find a version (network is down)")

    monkeypatch.setattr(subprocess, "run", offline)
    assert fetch_archive("fakepkg", "1.0", root) == path and not calls  # in the cache: no pip
    with pytest.raises(RegistryObjectError, match=r"cannot fetch otherpkg==2\.0.*network is down.*put its wheel"):
        fetch_archive("otherpkg", "2.0", tmp_path / "empty")
    assert calls and calls[0][1:5] == ["-m", "pip", "download", "--no-deps"] and "otherpkg==2.0" in calls[0]
    monkeypatch.setenv("PSSNET_REGISTRY_CACHE", str(tmp_path / "elsewhere"))
    assert cache_dir() == tmp_path / "elsewhere" and cache_dir(root) == root


def test_the_manifest_records_source_checksum_and_licence_of_every_object():
    assert len({o.name for o in MANIFEST}) == len(MANIFEST)
    for obj in MANIFEST:
        assert obj.family in REGISTRY_FAMILIES and obj.licence and obj.real_size and obj.scale > 0
        assert re.fullmatch(r"https://pypi\.org/project/[\w-]+/[\w.]+/", obj.url) and obj.version in obj.url
        for part in obj.parts:
            assert re.fullmatch(r"[0-9a-f]{64}", part.sha256) and part.member.lower().endswith((".obj", ".stl"))
    identities = registry_identities()
    assert [str(i) for i in identities[:2]] == ["rmug-00000", "rmug-00001"]
    assert {i.family for i in identities} == set(REGISTRY_FAMILIES)
