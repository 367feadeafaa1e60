"""Loading a user's own mesh folders (ShapeNet, YCB or a flat folder) into :class:`Shape` objects, and export.

Layouts (``layout`` argument):

* ``"shapenet"``: ``<root>/<synset>/<model_id>/models/model_normalized.obj`` (ShapeNetCore v2). ShapeNet
  models are y-up and unit-normalised; they are turned z-up and ``target_size`` (metres) sets their largest
  dimension.
* ``"ycb"``: ``<root>/<object_name>/google_16k/textured.obj``, else ``<root>/<object_name>/tsdf/textured.obj``
  (YCB object set downloads: z-up, metres).
* ``"flat"``: every ``.obj``, ``.ply`` and ``.stl`` file directly in ``<root>`` (z-up, units set by ``scale``).
* ``"auto"``: the first of the above that matches anything under ``root``.

Every loaded mesh is brought to the conventions of the procedural shapes (see
:mod:`pssnet_core.shapes.procedural`): metres, z up, the centre of its axis-aligned bounds at x = y = 0 and
its base at z = 0. Textures and materials are ignored (only geometry matters here) and vertices that
coincide are merged (texture seams split them in OBJ files).

Watertightness: a mesh that is not watertight is repaired with trimesh (fill holes, consistent winding and
outward normals). If it still is not watertight it is kept, with ``attributes["watertight"] = False``:
inside/outside is then not well defined, so solid occupancy (ground-truth voxels) must use a fallback such
as a surface shell or ray-parity voxelization; the data module decides which. Check the flag.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import MappingProxyType

import numpy as np
import trimesh

from pssnet_core.shapes.procedural import MAX_DIAGONAL, Shape, ShapeId

LAYOUTS: tuple[str, ...] = ("shapenet", "ycb", "flat")
"""Folder layouts understood by :func:`load_mesh_folder` and written by :func:`export_shapes`."""

MESH_SUFFIXES: tuple[str, ...] = (".obj", ".ply", ".stl")
"""Mesh file types read from a flat folder."""

SHAPENET_SYNSETS: Mapping[str, str] = MappingProxyType(
    {"mug": "03797390", "bottle": "02876657", "bowl": "02880940", "can": "02946921", "box": "02883344"})
"""WordNet synset ids used as ShapeNet category folders on export; other families get ``"00000000"``."""

_SHAPENET_FILE = Path("models") / "model_normalized.obj"
_YCB_FILES = (Path("google_16k") / "textured.obj", Path("tsdf") / "textured.obj")

# ShapeNet is y-up: a +90 degree rotation about x takes y to z (and z to -y).
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class MeshLoadError(ValueError):
    """A mesh file or folder cannot be used; the message names the file and says why."""


def load_mesh_folder(root: str | Path, layout: str = "auto", target_size: float | None = None, scale: float = 1.0,
                     skip_errors: bool = False) -> list[Shape]:
    """Loads every mesh of a folder as a :class:`Shape` in the object-frame conventions.

    Args:
        root: the folder.
        layout: ``"auto"``, ``"shapenet"``, ``"ycb"`` or ``"flat"`` (see the module docstring).
        target_size: if given, each mesh is scaled uniformly so that its largest bounds dimension is this
            many metres (what ShapeNet's unit-normalised models need). Exclusive with ``scale``.
        scale: uniform factor from file units to metres (e.g. 0.001 for millimetres).
        skip_errors: skip unreadable files with a warning instead of raising.

    Returns:
        Shapes in sorted path order; identity ``ShapeId("user:<layout>", i)`` where ``i`` is the file's index
        in that order (stable when other files fail), ``handle`` None, and attributes ``source_path``,
        ``layout``, ``name``, ``watertight``, ``repaired``, ``scale`` (the factor applied), ``height``,
        ``width_x``, ``width_y``, ``diagonal``, ``fits_grid`` (diagonal <= :data:`MAX_DIAGONAL`), plus
        ``synset`` for ShapeNet and ``volume`` for watertight meshes.

    Raises:
        MeshLoadError: missing root, unknown layout, no meshes found, or (unless ``skip_errors``) a file that
            cannot be read or holds no triangles.
    """
    root = Path(root)
    if not root.is_dir():
        raise MeshLoadError(f"mesh folder {root} does not exist or is not a directory")
    if layout not in ("auto", *LAYOUTS):
        raise MeshLoadError(f"unknown layout {layout!r}; expected 'auto' or one of {LAYOUTS}")
    if layout == "auto":
        layout = detect_layout(root)
    entries = _find_meshes(root, layout, skip_errors)
    if not entries:
        raise MeshLoadError(f"no meshes found under {root} for layout {layout!r} ({_expected(layout)})")
    shapes = []
    for index, (path, name, synset) in enumerate(entries):
        try:
            mesh = load_mesh(path)
        except MeshLoadError as error:
            if not skip_errors:
                raise
            warnings.warn(f"skipping {path}: {error}", stacklevel=2)
            continue
        mesh, repaired = repair_mesh(mesh)
        mesh, factor = normalize_mesh(mesh, y_up=layout == "shapenet", scale=scale, target_size=target_size)
        shapes.append(Shape(ShapeId(f"user:{layout}", index), mesh, None,
                            _attributes(mesh, path, layout, name, synset, repaired, factor)))
    return shapes


def detect_layout(root: str | Path) -> str:
    """The layout of a mesh folder: ShapeNet if any ShapeNet model file exists, then YCB, then flat."""
    root = Path(root)
    if next(root.glob(f"*/*/{_SHAPENET_FILE.as_posix()}"), None) is not None:
        return "shapenet"
    if any(next(root.glob(f"*/{f.as_posix()}"), None) is not None for f in _YCB_FILES):
        return "ycb"
    if any(p.is_file() and p.suffix.lower() in MESH_SUFFIXES for p in root.iterdir()):
        return "flat"
    raise MeshLoadError(f"cannot tell the layout of {root}: no ShapeNet ({_expected('shapenet')}), YCB "
                        f"({_expected('ycb')}) or flat ({_expected('flat')}) meshes found")


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Reads one mesh file (geometry only; materials and textures skipped) as a single triangle mesh.

    Raises:
        MeshLoadError: the file is missing, unreadable, or holds no finite triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshLoadError(f"mesh file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshLoadError(f"{path}: unsupported mesh type {suffix!r}; expected one of {MESH_SUFFIXES}")
    kwargs = {"skip_materials": True} if suffix == ".obj" else {}
    try:
        loaded = trimesh.load(path, file_type=suffix[1:], force="mesh", process=False, **kwargs)
    except Exception as error:  # trimesh raises many types (IndexError, TypeError, ValueError) on bad files
        raise MeshLoadError(f"{path}: cannot be read as a {suffix} mesh ({type(error).__name__}: {error})") from error
    vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))), dtype=np.int64)
    if len(faces) == 0 or len(vertices) == 0:
        raise MeshLoadError(f"{path}: no triangles found (empty or corrupt {suffix} file)")
    if not np.all(np.isfinite(vertices)):
        raise MeshLoadError(f"{path}: vertex coordinates contain NaN or infinity")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshLoadError(f"{path}: faces refer to vertices that do not exist")
    # A plain mesh without visuals, so that vertices split only by texture coordinates merge. No validate=True:
    # dropping (near-)degenerate faces, which boolean output has, would open holes in closed meshes.
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=True)


def repair_mesh(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, bool]:
    """Tries to make a mesh a consistently wound, outward-facing closed surface.

    Returns:
        The mesh (modified in place) and whether holes had to be filled.
    """
    repaired = False
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
        repaired = True
    trimesh.repair.fix_normals(mesh, multibody=True)
    return mesh, repaired


def normalize_mesh(mesh: trimesh.Trimesh, y_up: bool = False, scale: float = 1.0,
                   target_size: float | None = None) -> tuple[trimesh.Trimesh, float]:
    """Brings a mesh to the object-frame conventions (returns a new mesh and the scale factor applied).

    Order: y-up -> z-up rotation (if ``y_up``), uniform scaling (by ``scale``, or to a largest bounds
    dimension of ``target_size`` metres), then translation putting the bounds centre at x = y = 0 and the
    base at z = 0.

    Raises:
        MeshLoadError: a non-positive or non-finite ``scale``/``target_size``, both given, or a flat mesh.
    """
    if target_size is not None and scale != 1.0:
        raise MeshLoadError(f"give either scale ({scale}) or target_size ({target_size}), not both")
    for label, value in (("scale", scale), ("target_size", target_size)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise MeshLoadError(f"{label} must be a positive number, got {value!r}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if y_up:
        vertices = vertices @ _Y_UP_TO_Z_UP.T
    factor = float(scale)
    if target_size is not None:
        largest = float(np.max(np.ptp(vertices, axis=0)))
        if largest <= 0:
            raise MeshLoadError("cannot scale a mesh whose bounds have zero size")
        factor = float(target_size) / largest
    vertices = vertices * factor
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    vertices = vertices - np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]])
    return trimesh.Trimesh(vertices=vertices, faces=np.array(mesh.faces), process=False), factor


def export_shapes(shapes: Iterable[Shape], root: str | Path, layout: str) -> list[Path]:
    """Writes shapes as ``.obj`` files in a folder layout that :func:`load_mesh_folder` reads back.

    * ``"shapenet"``: ``<root>/<synset>/<name>/models/model_normalized.obj``, y-up, centred at the bounds
      centre and scaled to a bounds diagonal of 1 (ShapeNet's normalisation); the synset comes from
      :data:`SHAPENET_SYNSETS` (or the shape's ``synset`` attribute). Load with ``target_size`` = the
      original largest dimension to recover metres.
    * ``"ycb"``: ``<root>/<name>/google_16k/textured.obj`` in metres, as is.
    * ``"flat"``: ``<root>/<name>.obj`` in metres, as is.

    ``<name>`` is ``str(shape.identity)`` with ``:`` replaced by ``_``.

    Returns:
        The written paths, in the order of ``shapes``.

    Raises:
        MeshLoadError: unknown layout, or two shapes with the same name.
    """
    if layout not in LAYOUTS:
        raise MeshLoadError(f"unknown export layout {layout!r}; expected one of {LAYOUTS}")
    root = Path(root)
    written: list[Path] = []
    for shape in shapes:
        name = str(shape.identity).replace(":", "_")
        mesh = shape.mesh
        if layout == "shapenet":
            synset = str(shape.attributes.get("synset", SHAPENET_SYNSETS.get(shape.identity.family, "00000000")))
            path = root / synset / name / _SHAPENET_FILE
            low, high = mesh.bounds
            vertices = (np.asarray(mesh.vertices) - (low + high) / 2) / float(np.linalg.norm(high - low))
            mesh = trimesh.Trimesh(vertices=vertices @ _Y_UP_TO_Z_UP, faces=mesh.faces, process=False)
        elif layout == "ycb":
            path = root / name / _YCB_FILES[0]
        else:
            path = root / f"{name}.obj"
        if path in written:
            raise MeshLoadError(f"two shapes map to the same file {path}")
        path.parent.mkdir(parents=True, exist_ok=True)
        mesh.export(path, file_type="obj", include_normals=False, include_texture=False)
        written.append(path)
    return written


def _find_meshes(root: Path, layout: str, skip_errors: bool) -> list[tuple[Path, str, str | None]]:
    """(path, name, synset) of every mesh of a layout, sorted by path."""
    if layout == "shapenet":
        files = sorted(root.glob(f"*/*/{_SHAPENET_FILE.as_posix()}"))
        return [(f, f.parents[1].name, f.parents[2].name) for f in files]
    if layout == "ycb":
        found = []
        for folder in sorted(p for p in root.iterdir() if p.is_dir()):
            candidates = [folder / f for f in _YCB_FILES if (folder / f).is_file()]
            if candidates:
                found.append((candidates[0], folder.name, None))
                continue
            message = (f"YCB object folder {folder} has no mesh: expected "
                       f"{' or '.join(str(folder / f) for f in _YCB_FILES)}")
            if not skip_errors:
                raise MeshLoadError(message)
            warnings.warn(f"skipping {folder}: {message}", stacklevel=3)
        return found
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    return [(f, f.stem, None) for f in files]


def _expected(layout: str) -> str:
    return {"shapenet": f"<root>/<synset>/<model_id>/{_SHAPENET_FILE.as_posix()}",
            "ycb": " or ".join(f"<root>/<object>/{f.as_posix()}" for f in _YCB_FILES),
            "flat": f"<root>/*{{{','.join(MESH_SUFFIXES)}}}"}[layout]


def _attributes(mesh: trimesh.Trimesh, path: Path, layout: str, name: str, synset: str | None, repaired: bool,
                factor: float) -> dict[str, float | str | bool]:
    extent = mesh.extents
    diagonal = float(np.linalg.norm(extent))
    watertight = bool(mesh.is_watertight)
    attributes: dict[str, float | str | bool] = {
        "source_path": str(path), "layout": layout, "name": name, "watertight": watertight, "repaired": repaired,
        "scale": factor, "height": float(extent[2]), "width_x": float(extent[0]), "width_y": float(extent[1]),
        "diagonal": diagonal, "fits_grid": diagonal <= MAX_DIAGONAL,
    }
    if synset is not None:
        attributes["synset"] = synset
    if watertight:
        attributes["volume"] = float(mesh.volume)
    return attributes

