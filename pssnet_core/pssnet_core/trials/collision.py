"""Collision shapes of the true objects: CoACD convex decomposition, cached on disk, and how faithful it is.

MuJoCo collides convex shapes only (a mesh geom collides as its convex hull), so a mug is given to the
physics engine as the union of CoACD's convex parts. A mug is thin-walled: the hull of a wall segment
bridges the wall's curvature, so a coarse decomposition adds volume and can close the handle's hole (then
a finger meant to pass the handle hits solid air). :func:`measure_faithfulness` measures both: the union's
volume against the true solid (exact boolean volumes with manifold3d), and, for a mug with a handle, the
clear gap between the body and the handle bar along the handle's centre plane and whether a line through
the hole stays clear of every part.

CoACD threshold 0.02 (its default is 0.05): on a test mug this gives ~50 parts and a union within ~2 % of
the true volume (0.05 gives ~20 parts and +18 %); the numbers of every object a run used are in its
summary. Barrel-shaped mugs decompose worse (+8 to +11 %); the scenes leave such objects out. A
decomposition takes ~10 s per mug, so parts are cached under ``cache_dir`` keyed by the mesh bytes and the
options.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import manifold3d as mf
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from pssnet_core.data.scenes import ObjectScene
from pssnet_core.data.store import write_npz_atomically
from pssnet_core.shapes import Shape

DEFAULT_CACHE_DIR = Path.home() / ".cache" / "pssnet" / "coacd"


@dataclass(frozen=True)
class DecompositionConfig:
    """CoACD options (see ``coacd.run_coacd``).

    Attributes:
        threshold: concavity threshold; lower = more, tighter parts.
        max_convex_hull: at most this many parts (-1 = no limit).
        preprocess: CoACD's ``preprocess_mode``. "off": the procedural meshes are watertight manifolds
            already, and CoACD's "auto" remeshing (at its 50^3 resolution) thickened one thin-walled test mug
            by 32 % of its volume.
        seed: CoACD's random seed (the decomposition is deterministic given it).
    """

    threshold: float = 0.02
    max_convex_hull: int = -1
    preprocess: str = "off"
    seed: int = 0


@dataclass(frozen=True)
class ConvexPart:
    """One convex part: its hull's vertices and triangles (object frame, metres)."""

    vertices: np.ndarray
    faces: np.ndarray


def _cache_key(mesh: trimesh.Trimesh, config: DecompositionConfig) -> str:
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    digest.update(json.dumps(asdict(config), sort_keys=True).encode())
    return digest.hexdigest()[:24]


def decompose(mesh: trimesh.Trimesh, config: DecompositionConfig | None = None,
              cache_dir: str | Path | None = DEFAULT_CACHE_DIR) -> list[ConvexPart]:
    """Convex parts of a watertight mesh (CoACD), from the cache when this mesh was decomposed before.

    Args:
        mesh: the solid (object frame).
        config: CoACD options.
        cache_dir: where parts are cached (None: no cache).
    """
    config = config or DecompositionConfig()
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{_cache_key(mesh, config)}.npz"
        if path.is_file():
            with np.load(path) as data:
                count = int(data["count"])
                return [ConvexPart(data[f"v{i}"], data[f"f{i}"]) for i in range(count)]
    # Local, and after open3d (imported above): importing coacd first makes `import open3d` fail (bad_cast).
    import coacd

    coacd.set_log_level("error")
    raw = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)),
                          threshold=config.threshold, max_convex_hull=config.max_convex_hull,
                          preprocess_mode=config.preprocess, seed=config.seed)
    parts = [ConvexPart(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)) for v, f in raw]
    if path is not None:
        arrays = {"count": np.array(len(parts))}
        for i, part in enumerate(parts):
            arrays[f"v{i}"], arrays[f"f{i}"] = part.vertices, part.faces
        write_npz_atomically(path, arrays)  # parallel runs decomposing the same mesh each write their own temp file
    return parts


@dataclass(frozen=True)
class Faithfulness:
    """How well the union of convex parts reproduces the true solid.

    Attributes:
        parts: number of convex parts.
        volume_true: volume of the true solid (m^3).
        volume_parts: volume of the union of the parts (m^3).
        extra: volume in the parts but not in the solid, as a fraction of the true volume.
        missing: volume in the solid but not in the parts, as a fraction of the true volume.
        hole_gap_true: clear gap between the mug body and the handle bar along the handle's centre line
            (m); None without a handle.
        hole_gap_parts: the same gap in the union of the parts (m); None without a handle.
        hole_kept: a line across the handle plane through the hole's centre misses every part; None
            without a handle.
    """

    parts: int
    volume_true: float
    volume_parts: float
    extra: float
    missing: float
    hole_gap_true: float | None = None
    hole_gap_parts: float | None = None
    hole_kept: bool | None = None

    @property
    def volume_error(self) -> float:
        """Relative volume error of the union, (parts - true) / true."""
        return self.volume_parts / self.volume_true - 1.0


def _manifold(vertices: np.ndarray, faces: np.ndarray) -> mf.Manifold:
    return mf.Manifold(mf.Mesh(np.asarray(vertices, dtype=np.float32), np.asarray(faces, dtype=np.uint32)))


def inside_parts(parts: list[ConvexPart], points: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """(M,) bool: the points lie inside at least one convex part (half-space test on each hull)."""
    points = np.asarray(points, dtype=np.float64)
    inside = np.zeros(len(points), dtype=bool)
    for part in parts:
        equations = ConvexHull(part.vertices).equations  # (F, 4): normal . x + offset <= 0 inside
        inside |= np.all(points @ equations[:, :3].T + equations[:, 3] <= tolerance, axis=1)
    return inside


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges of the True runs of a 1-D bool array."""
    padded = np.concatenate([[False], flags, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def measure_faithfulness(shape: Shape, parts: list[ConvexPart], step: float = 2e-4) -> Faithfulness:
    """Volumes of the true solid and of the union of parts, and (mugs) whether the handle's hole is kept.

    The hole is found on the handle's centre line (object frame: the handle points along +x, its centre at
    height ``attributes["handle_center_z"]``): sampled every ``step`` metres outwards from the body axis,
    the last two solid runs of the true mesh are the body wall and the handle bar, and the free run between
    them is the hole. The parts' gap is their free run around the hole's centre on the same line.
    """
    true = _manifold(shape.mesh.vertices, shape.mesh.faces)
    union = mf.Manifold.batch_boolean([mf.Manifold.hull_points(np.asarray(p.vertices, dtype=np.float64))
                                       for p in parts], mf.OpType.Add)
    volume = true.volume()
    result = {"parts": len(parts), "volume_true": volume, "volume_parts": union.volume(),
              "extra": (union - true).volume() / volume, "missing": (true - union).volume() / volume}
    zc = shape.attributes.get("handle_center_z")
    if shape.handle is not None and zc is not None:
        x = np.arange(0.0, float(shape.bounds[1, 0]) + 0.005, step)
        line = np.stack([x, np.zeros_like(x), np.full_like(x, float(zc))], axis=1)
        solid = ObjectScene(shape, threads=1).occupancy(line)  # the project's inside test (open3d ray parity)
        runs = _runs(solid)
        if len(runs) >= 2:
            (_, wall_end), (bar_start, _) = runs[-2], runs[-1]
            centre = 0.5 * (x[wall_end] + x[bar_start - 1])
            free_parts = ~inside_parts(parts, line)
            c = int(np.argmin(np.abs(x - centre)))
            if free_parts[c]:
                lo = c - int(np.argmin(free_parts[c::-1])) + 1 if not free_parts[:c + 1].all() else 0
                hi = c + int(np.argmin(free_parts[c:])) if not free_parts[c:].all() else len(x)
                gap_parts = (hi - lo) * step
            else:
                gap_parts = 0.0
            width = float(shape.bounds[1, 1] - shape.bounds[0, 1])
            across = np.stack([np.full(64, centre), np.linspace(-width, width, 64), np.full(64, float(zc))], axis=1)
            result.update(hole_gap_true=(bar_start - wall_end) * step, hole_gap_parts=gap_parts,
                          hole_kept=bool(not inside_parts(parts, across).any()))
    return Faithfulness(**result)
