"""Plausible sets (the paper's Alg. 2): which test shapes explain each test observation.

For every reference observation ``i`` and every other observation ``j`` of the same test set:

1. ICP (open3d, point-to-point) aligns ``j``'s known-occupied cloud (observed voxel centres, ``j``'s camera
   frame) to ``i``'s. It starts from the transform that maps ``j``'s observation grid onto ``i``'s (the grids are
   gravity aligned and placed from the observed points, so this lines up the visible fronts, bottoms and sides,
   as the authors' identity start in their object-centred grids did).
2. ``j``'s ground-truth mesh, placed by ``j``'s object pose and moved by the ICP transform into ``i``'s camera
   frame, is judged by the observation model against ``i``'s depth image.
3. Accepted candidates are stored as ``(j, T)`` with ``T`` the 4x4 transform from ``j``'s camera frame to ``i``'s;
   the plausible shape is ``mesh_j`` at pose ``T @ object_pose_j`` in ``i``'s camera frame. ``i``'s own ground
   truth (``(i, identity)``) is always a member.

Speed: the cost is quadratic. The ICP (the expensive part) and the render are done once per pair for all deltas
(only the pixel comparison depends on delta). A prefilter skips ICP and rendering where no rigid placement of
``j``'s mesh can pass (see :func:`diameter_bound_rejects`). Each reference observation is a Ray task
(:mod:`pssnet_core.ray_tasks`); the views, meshes and ICP clouds go into the object store once. Finished
references are written to a parts directory as they come in, so a killed run resumes, and the whole result is cached.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.data.store import write_npz_atomically
from pssnet_core.evaluation.observation_model import (
    DepthView,
    MeshRaycaster,
    MultiDeltaView,
    ObservationModelConfig,
    ObservationModelError,
)
from pssnet_core.geometry import GridPose
from pssnet_core.ray_tasks import TaskRunner

# Finished references are buffered and written to the parts directory at most this often (a killed run loses at
# most this much work; one file per reference would be 100,000 files for a large test set).
PART_FLUSH_SECONDS = 30.0


class PlausibleSetError(ValueError):
    """Bad input to the plausible-set computation, or an unusable cache file."""


@dataclass
class EvalView:
    """What the evaluation needs of one test observation.

    Attributes:
        index: position in the test set.
        identity: the object's identity (same string = same mesh), e.g. "mug-01234".
        depth_view: the observed depth (crop), mask and intrinsics.
        object_pose: 4x4 pose of the object (mesh frame) in this view's camera frame.
        grid_pose: where the observation grid lies in the camera frame.
        known_occupied: (N, N, N) bool observed voxels.
        known_free: (N, N, N) bool voxels seen to be empty (the network's second input channel).
        meta: free-form record (family, handle_visible, rotation_deg, slit_width_m, ...).
    """

    index: int
    identity: str
    depth_view: DepthView
    object_pose: np.ndarray
    grid_pose: GridPose
    known_occupied: np.ndarray
    known_free: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def network_input(self) -> np.ndarray:
        """(2, N, N, N) float32: known occupied, known free (as ``Observation.network_input``)."""
        if self.known_free is None:
            raise PlausibleSetError(f"view {self.index} has no known_free grid")
        return np.stack([self.known_occupied, self.known_free]).astype(np.float32)

    def observed_cloud(self) -> np.ndarray:
        """Camera-frame centres of the known-occupied voxels, (M, 3)."""
        return self.grid_pose.occupied_centres(self.known_occupied)


class MeshTable:
    """Meshes by identity from a dict of (vertices, faces) arrays: picklable, for tests and small sets."""

    def __init__(self, meshes: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        self.meshes = {k: (np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64))
                       for k, (v, f) in meshes.items()}

    def __call__(self, identity: str) -> tuple[np.ndarray, np.ndarray]:
        try:
            return self.meshes[identity]
        except KeyError:
            raise PlausibleSetError(f"no mesh for identity {identity!r}") from None


class ShapeMeshes:
    """Meshes of any object by identity ("mug-00042", "imug-2000003", "rmug-00000") via
    ``pssnet_core.shapes.shape_of``."""

    def __call__(self, identity: str) -> tuple[np.ndarray, np.ndarray]:
        from pssnet_core.shapes import RegistryObjectError, ShapeError, shape_of  # only when meshes are rebuilt

        try:
            mesh = shape_of(identity).mesh
        except (ShapeError, RegistryObjectError) as error:
            raise PlausibleSetError(str(error)) from error
        return np.asarray(mesh.vertices), np.asarray(mesh.faces)


MeshSource = Callable[[str], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class PlausibleConfig:
    """Parameters of the plausible-set computation.

    Attributes:
        deltas: observation-model tolerances (metres) to build sets for, all in one pass.
        observation: the other observation-model parameters (its delta is ignored).
        icp_max_distance: ICP correspondence distance (metres).
        icp_iterations: ICP iterations.
        prefilter: skip work on pairs that provably cannot pass: the diameter bound before ICP (see
            :func:`diameter_bound_rejects`) and the sparse-pixel check before the full render (see
            :class:`~pssnet_core.evaluation.observation_model.MultiDeltaView`). Neither changes the result.
        sparse_pixels: size of the sparse pixel sample of that check.
        icp_points: "observed": the observed object points (from the depth crop) averaged per ``icp_voxel``
            cell; "known_occupied": the known-occupied voxel centres. Both are the observed cloud at voxel
            resolution and cost the same; averaging the points instead of snapping them to voxel centres
            gives sub-voxel alignment (measured on test mugs: median 2 instead of 5.5, worst 21 instead of 99
            violating pixels between views of the same mug with the handle hidden).
        icp_voxel: downsampling cell (metres) of the "observed" cloud; None = the view's grid voxel size.
        record_fraction: candidates with up to this fraction of the reference's object pixels violating are
            stored with their violation counts, so that any outlier allowance up to it is applied later
            (:meth:`PlausibleSets.members`) without recomputing. 0 stores strict (paper) members only and
            enables the diameter prefilter, which is only safe without an allowance.
    """

    deltas: tuple[float, ...] = (0.04, 0.01)
    observation: ObservationModelConfig = ObservationModelConfig()
    icp_max_distance: float = 0.05
    icp_iterations: int = 30
    prefilter: bool = True
    sparse_pixels: int = 512
    icp_points: str = "observed"
    icp_voxel: float | None = None
    record_fraction: float = 0.01

    def __post_init__(self) -> None:
        if not self.deltas or any(not (math.isfinite(d) and d > 0) for d in self.deltas):
            raise PlausibleSetError(f"deltas must be positive numbers of metres, got {self.deltas}")
        if len(set(self.deltas)) != len(self.deltas):
            raise PlausibleSetError(f"deltas must be distinct, got {self.deltas}")
        if self.icp_points not in ("observed", "known_occupied"):
            raise PlausibleSetError(f"icp_points must be 'observed' or 'known_occupied', got {self.icp_points!r}")
        if not 0.0 <= self.record_fraction < 1.0:
            raise PlausibleSetError(f"record_fraction must be in [0, 1), got {self.record_fraction}")
        if self.icp_max_distance <= 0 or self.icp_iterations < 1:
            raise PlausibleSetError("icp_max_distance must be > 0 and icp_iterations >= 1")

    @property
    def recording_observation(self) -> ObservationModelConfig:
        """The observation model candidates are judged with: the recording allowance (the largest any later query
        may use), so nothing it could accept is lost; :meth:`PlausibleSets.members` applies the smaller ones."""
        return replace(self.observation,
                       outlier_fraction=max(self.observation.outlier_fraction, self.record_fraction))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["deltas"] = list(self.deltas)
        return d


def diameter(points: np.ndarray) -> float:
    """Largest distance between two of the points (convex hull, then all hull pairs)."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    if len(pts) > 8:
        try:
            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # coplanar/degenerate sets: fall back to all points (subsampled)
            pts = pts[:: max(1, len(pts) // 3000)]
    diff = pts[:, None, :] - pts[None, :, :]
    return float(np.sqrt((diff**2).sum(-1).max()))


def diameter_bound_rejects(observed_diameter: float, ray_scale: float, mesh_diameter: float,
                           delta: float) -> bool:
    """True when no rigid placement of a mesh can explain the view's reliable object pixels within delta.

    Why this is safe (never rejects a candidate the observation model would accept, with no outlier
    allowance and the unreliable set taken from the observation): an accepted candidate must have, for every
    reliable object pixel p, a surface hit H_p on p's ray with |E - O| <= delta; the observed point P_p and
    H_p lie on the same ray, so |P_p - H_p| = |E - O| * |(x/z, y/z, 1)| <= delta * ray_scale. Hence for any
    two reliable pixels |P_p - P_q| <= |H_p - H_q| + 2 delta ray_scale <= diam(mesh) + 2 delta ray_scale, and
    a rigid motion does not change the mesh's diameter. If the reliable points are wider than that, every
    placement (whatever ICP returns) fails.
    """
    return observed_diameter > mesh_diameter + 2.0 * delta * ray_scale + 1e-9


@dataclass
class PlausibleSets:
    """Plausible sets of a test set, for several deltas.

    Rows are (reference i, candidate j, transform T (j's camera -> i's camera), violations per delta). Rows are
    stored for candidates within the recording allowance at some delta; every reference has its own row
    (j = i, T = identity), which is always a member.

    Attributes:
        deltas: the deltas (columns of ``violations``).
        references: indices of the reference observations computed.
        object_pixels: (R,) valid object pixels of each reference (what outlier fractions refer to).
        ref: (K,) reference index per row.
        other: (K,) candidate index per row.
        transforms: (K, 4, 4).
        violations: (K, D) violating pixels counted by the observation model (own rows: measured too).
        outlier_count, outlier_fraction: the default allowance of :meth:`members`.
        record_fraction: the largest outlier fraction the stored rows support.
        stats: timings and counts.
    """

    deltas: tuple[float, ...]
    references: np.ndarray
    object_pixels: np.ndarray
    ref: np.ndarray
    other: np.ndarray
    transforms: np.ndarray
    violations: np.ndarray
    outlier_count: int = 0
    outlier_fraction: float = 0.0
    record_fraction: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)

    def delta_column(self, delta: float) -> int:
        for k, d in enumerate(self.deltas):
            if abs(d - delta) < 1e-12:
                return k
        raise PlausibleSetError(f"no plausible sets for delta {delta}; computed for {list(self.deltas)}")

    def allowance(self, i: int, outlier_fraction: float | None = None, outlier_count: int | None = None) -> int:
        """Violations allowed for reference ``i``."""
        fraction = self.outlier_fraction if outlier_fraction is None else outlier_fraction
        count = self.outlier_count if outlier_count is None else outlier_count
        if fraction > self.record_fraction + 1e-12 or (count > 0 and self.record_fraction == 0
                                                       and self.outlier_count < count):
            raise PlausibleSetError(
                f"outlier allowance (fraction {fraction}, count {count}) exceeds what these sets recorded "
                f"(record_fraction {self.record_fraction}); recompute with a larger record_fraction")
        k = np.searchsorted(self.references, i)
        if k >= len(self.references) or self.references[k] != i:
            raise PlausibleSetError(f"observation {i} is not among the computed references")
        return int(count + math.floor(fraction * int(self.object_pixels[k])))

    def members(self, i: int, delta: float, outlier_fraction: float | None = None,
                outlier_count: int | None = None) -> list[tuple[int, np.ndarray]]:
        """[(j, T)] of reference ``i`` at ``delta`` (own ground truth first).

        ``outlier_fraction``/``outlier_count`` override the default allowance (up to ``record_fraction``).
        """
        col = self.delta_column(delta)
        allowed = self.allowance(i, outlier_fraction, outlier_count)
        rows = np.nonzero(self.ref == i)[0]
        own = [r for r in rows if self.other[r] == i]
        rest = [r for r in rows if self.other[r] != i and self.violations[r, col] <= allowed]
        return [(int(self.other[r]), self.transforms[r]) for r in own + rest]

    def sizes(self, delta: float, outlier_fraction: float | None = None) -> dict[int, int]:
        """Plausible-set size per reference at ``delta``."""
        return {int(i): len(self.members(int(i), delta, outlier_fraction)) for i in self.references}

    def save(self, path: str | Path) -> None:
        write_npz_atomically(path, {
            "deltas": np.array(self.deltas), "references": self.references, "object_pixels": self.object_pixels,
            "ref": self.ref, "other": self.other, "transforms": self.transforms, "violations": self.violations,
            "allowance": np.array([self.outlier_count, self.outlier_fraction, self.record_fraction]),
            "stats": np.array(json.dumps(self.stats))})

    @classmethod
    def load(cls, path: str | Path) -> PlausibleSets:
        try:
            with np.load(path) as data:
                count, fraction, record = data["allowance"].tolist()
                return cls(deltas=tuple(float(d) for d in data["deltas"]), references=data["references"],
                           object_pixels=data["object_pixels"], ref=data["ref"], other=data["other"],
                           transforms=data["transforms"], violations=data["violations"], outlier_count=int(count),
                           outlier_fraction=float(fraction), record_fraction=float(record),
                           stats=json.loads(str(data["stats"])))
        except (OSError, KeyError, ValueError) as error:
            raise PlausibleSetError(f"plausible-set cache {path} is unreadable: {error}") from error


def icp_cloud(view: EvalView, config: PlausibleConfig) -> np.ndarray:
    """(M, 3) camera-frame points that ICP aligns for ``view`` (see ``PlausibleConfig.icp_points``)."""
    import open3d as o3d

    if config.icp_points == "observed" and view.depth_view is not None:
        points = view.depth_view.object_points()
    else:
        points = view.observed_cloud()
    if config.icp_points != "observed":
        return np.asarray(points, dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.voxel_down_sample(config.icp_voxel or view.grid_pose.voxel_size).points)


class _PairJudge:
    """The views, their ICP clouds and meshes (open3d objects built lazily), for judging pairs."""

    def __init__(self, views: Sequence[EvalView], meshes: MeshSource, clouds: Sequence[np.ndarray],
                 config: PlausibleConfig) -> None:
        import open3d as o3d

        self.o3d = o3d
        self.views = views
        self.meshes = meshes
        self.points = clouds
        self.config = config
        self._raycasters: dict[str, MeshRaycaster] = {}
        self._clouds: dict[int, Any] = {}

    def raycaster(self, identity: str) -> MeshRaycaster:
        if identity not in self._raycasters:
            vertices, faces = self.meshes(identity)
            self._raycasters[identity] = MeshRaycaster(vertices, faces)
        return self._raycasters[identity]

    def cloud(self, index: int) -> Any:
        if index not in self._clouds:
            # A copy: open3d wants a writeable array, and arrays from Ray's object store are read-only.
            points = np.array(self.points[index], dtype=np.float64)
            self._clouds[index] = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(points))
        return self._clouds[index]

    def initial_transform(self, i: int, j: int) -> np.ndarray:
        """Where ICP starts: the transform mapping j's observation grid onto i's (j's camera frame -> i's)."""
        return self.views[i].grid_pose.to_matrix() @ np.linalg.inv(self.views[j].grid_pose.to_matrix())

    def icp(self, i: int, j: int) -> np.ndarray:
        """Transform from j's camera frame to i's aligning j's observed cloud to i's."""
        reg = self.o3d.pipelines.registration
        result = reg.registration_icp(
            self.cloud(j), self.cloud(i), self.config.icp_max_distance, self.initial_transform(i, j),
            reg.TransformationEstimationPointToPoint(),
            reg.ICPConvergenceCriteria(max_iteration=self.config.icp_iterations))
        return np.asarray(result.transformation, dtype=np.float64)

    def run(self, i: int, candidates: Sequence[int] | None = None) -> dict[str, Any]:
        """All candidates judged against reference i; returns accepted rows and counts."""
        cfg = self.config
        deltas = cfg.deltas
        view_i = self.views[i]
        recording = cfg.recording_observation
        multi = MultiDeltaView(view_i.depth_view, recording, deltas,
                               sparse_pixels=cfg.sparse_pixels if cfg.prefilter else 0)
        use_prefilter = cfg.prefilter and recording.gradient == "observed" and not recording.has_allowance
        bounds = []
        if use_prefilter:
            for d in deltas:
                prepared = multi.prepared[d]
                bounds.append((d, diameter(prepared.reliable_object_points), prepared.max_ray_scale))
        rows: list[tuple[int, np.ndarray, list[int]]] = []
        # Own ground truth: always a member; judged too, as a check of the pipeline's consistency.
        own = MultiDeltaView(view_i.depth_view, cfg.observation, deltas, sparse_pixels=0).judge(
            self.raycaster(view_i.identity), view_i.object_pose)
        rows.append((i, np.eye(4), [own[d].violations for d in deltas]))
        own_ok = [bool(own[d].plausible) for d in deltas]
        n_pairs = n_pruned = n_early = 0
        t_icp = t_judge = 0.0
        others = range(len(self.views)) if candidates is None else candidates
        for j in others:
            if j == i:
                continue
            n_pairs += 1
            view_j = self.views[j]
            caster = self.raycaster(view_j.identity)
            if use_prefilter and all(diameter_bound_rejects(dia, scale, caster.diameter, d)
                                     for d, dia, scale in bounds):
                n_pruned += 1
                continue
            t0 = time.perf_counter()
            transform = self.icp(i, j)
            t1 = time.perf_counter()
            results = multi.judge(caster, transform @ view_j.object_pose)
            t_judge += time.perf_counter() - t1
            t_icp += t1 - t0
            if results is None:  # rejected on the sparse pixels at every delta
                n_early += 1
                continue
            if any(results[d].plausible for d in deltas):
                rows.append((j, transform, [results[d].violations for d in deltas]))
        return {"i": i, "rows": rows, "pairs": n_pairs, "pruned": n_pruned, "early": n_early, "own_plausible": own_ok,
                "object_pixels": multi.any.num_object_pixels,
                "t_icp": t_icp, "t_judge": t_judge}


def _judge_reference(i: int, views: Sequence[EvalView], meshes: MeshSource, clouds: Sequence[np.ndarray],
                     config: PlausibleConfig) -> dict[str, Any]:
    """The unit of work (a Ray task): every candidate judged against reference ``i``."""
    return _PairJudge(views, meshes, clouds, config).run(i)


def _write_part(parts_dir: Path, outputs: Sequence[dict[str, Any]], deltas: int) -> None:
    """Finished references as one file of ``parts_dir`` (atomic: a killed run leaves whole files only)."""
    rows = [(o["i"], j, transform, violations) for o in outputs for j, transform, violations in o["rows"]]
    arrays = {
        "refs": np.array([o["i"] for o in outputs], dtype=np.int64),
        "counts": np.array([[o["pairs"], o["pruned"], o["early"], o["object_pixels"]] for o in outputs],
                           dtype=np.int64),
        "own_plausible": np.array([o["own_plausible"] for o in outputs], dtype=bool).reshape(-1, deltas),
        "seconds": np.array([[o["t_icp"], o["t_judge"]] for o in outputs], dtype=np.float64),
        "row_ref": np.array([r[0] for r in rows], dtype=np.int64),
        "other": np.array([r[1] for r in rows], dtype=np.int64),
        "transforms": np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4, 4),
        "violations": np.array([r[3] for r in rows], dtype=np.int64).reshape(-1, deltas),
    }
    write_npz_atomically(parts_dir / f"part_{outputs[0]['i']:09d}.npz", arrays, compressed=False)


def _read_parts(parts_dir: Path) -> dict[int, dict[str, Any]]:
    """The references a killed run finished (as :func:`_judge_reference` returned them), by index."""
    outputs: dict[int, dict[str, Any]] = {}
    for path in sorted(parts_dir.glob("part_*.npz")):
        try:
            with np.load(path) as data:
                part = {k: data[k] for k in data.files}
        except (OSError, ValueError, KeyError) as error:
            raise PlausibleSetError(f"plausible-set part {path} is unreadable ({error}); delete it") from error
        for k, i in enumerate(part["refs"].tolist()):
            rows = np.nonzero(part["row_ref"] == i)[0]
            pairs, pruned, early, pixels = part["counts"][k].tolist()
            outputs[i] = {"i": i, "pairs": pairs, "pruned": pruned, "early": early, "object_pixels": pixels,
                          "own_plausible": part["own_plausible"][k].tolist(),
                          "t_icp": float(part["seconds"][k, 0]), "t_judge": float(part["seconds"][k, 1]),
                          "rows": [(int(part["other"][r]), part["transforms"][r], part["violations"][r].tolist())
                                   for r in rows]}
    return outputs


def compute_plausible_sets(views: Sequence[EvalView], meshes: MeshSource, config: PlausibleConfig | None = None,
                           references: Sequence[int] | None = None, runner: TaskRunner | None = None,
                           progress: bool = True, desc: str = "plausible sets",
                           parts_dir: str | Path | None = None) -> PlausibleSets:
    """Alg. 2 over a test set, one Ray task per reference observation.

    Args:
        views: the whole test set (``views[k].index == k``).
        meshes: identity -> (vertices, faces) in the mesh frame (called here, once per identity).
        config: parameters.
        references: observations to build sets for (default all); candidates are always the whole set.
        runner: where the references are computed (default: in this process).
        progress: show a tqdm bar.
        desc: bar label.
        parts_dir: where finished references are written as they come in and read back on the next call, so a
            killed run resumes; it must belong to this computation alone (same views, config and references).

    Returns:
        The :class:`PlausibleSets`, with ``stats`` (pairs, pruned, seconds, pairs_per_second, own-GT pass rate).
    """
    config = config or PlausibleConfig()
    for k, v in enumerate(views):
        if v.index != k:
            raise PlausibleSetError(f"views[{k}].index is {v.index}; views must be listed in index order")
    refs = list(range(len(views))) if references is None else [int(r) for r in references]
    if any(not 0 <= r < len(views) for r in refs):
        raise PlausibleSetError(f"reference indices must be in [0, {len(views)})")
    parts = Path(parts_dir) if parts_dir is not None else None
    done = {i: o for i, o in _read_parts(parts).items() if i in set(refs)} if parts is not None else {}
    todo = [i for i in refs if i not in done]
    runner = runner or TaskRunner()  # the default runs in this process: nothing to close
    t_start = time.perf_counter()
    pairs_done = 0

    def rate(out: dict[str, Any]) -> dict[str, str]:
        nonlocal pairs_done
        pairs_done += out["pairs"]
        return {"pairs_per_s": f"{pairs_done / max(time.perf_counter() - t_start, 1e-9):.0f}"}

    outputs = dict(done)
    if todo:
        # What every task reads, made once: meshes and ICP clouds for the whole set (candidates are all views).
        table = MeshTable({identity: meshes(identity) for identity in sorted({v.identity for v in views})})
        shared = {"views": list(views), "meshes": table, "clouds": [icp_cloud(v, config) for v in views],
                  "config": config}
        unsaved: list[dict[str, Any]] = []
        last_save = time.monotonic()
        try:
            for _, out in runner.map(_judge_reference, todo, shared, desc=desc, unit_name="obs", done=len(done),
                                     progress=progress, postfix=rate):
                outputs[out["i"]] = out
                unsaved.append(out)
                if parts is not None and time.monotonic() - last_save >= PART_FLUSH_SECONDS:
                    _write_part(parts, unsaved, len(config.deltas))
                    unsaved, last_save = [], time.monotonic()
        finally:  # also when interrupted: what finished is kept
            if parts is not None and unsaved:
                _write_part(parts, unsaved, len(config.deltas))
    elapsed = time.perf_counter() - t_start
    ordered = [outputs[i] for i in sorted(outputs)]
    deltas = config.deltas
    ref_l, oth_l, tf_l, vio_l = [], [], [], []
    for out in ordered:
        for j, transform, viol in out["rows"]:
            ref_l.append(out["i"])
            oth_l.append(j)
            tf_l.append(transform)
            vio_l.append(viol)
    pairs = sum(o["pairs"] for o in ordered)
    pruned = sum(o["pruned"] for o in ordered)
    early = sum(o["early"] for o in ordered)
    own = np.array([o["own_plausible"] for o in ordered], dtype=bool).reshape(len(ordered), len(deltas))
    computed_pairs = sum(outputs[i]["pairs"] for i in todo)
    stats = {
        "observations": len(views), "references": len(refs), "pairs": pairs, "pruned_by_prefilter": pruned,
        "rejected_on_sparse_pixels": early, "resumed_references": len(done),
        "seconds": elapsed, "pairs_per_second": computed_pairs / max(elapsed, 1e-9),
        "workers": runner.parallelism if todo else 0, "executor": runner.describe() if todo else "resumed",
        "icp_seconds": sum(o["t_icp"] for o in ordered), "judge_seconds": sum(o["t_judge"] for o in ordered),
        "own_ground_truth_plausible_rate": {str(d): float(own[:, k].mean()) if len(own) else float("nan")
                                            for k, d in enumerate(deltas)},
        "config": config.to_dict(),
    }
    result = PlausibleSets(deltas=tuple(deltas), references=np.array([o["i"] for o in ordered], dtype=np.int64),
                           object_pixels=np.array([o["object_pixels"] for o in ordered], dtype=np.int64),
                           ref=np.array(ref_l, dtype=np.int64), other=np.array(oth_l, dtype=np.int64),
                           transforms=np.array(tf_l, dtype=np.float64).reshape(-1, 4, 4),
                           violations=np.array(vio_l, dtype=np.int64).reshape(-1, len(deltas)),
                           outlier_count=config.observation.outlier_count,
                           outlier_fraction=config.observation.outlier_fraction,
                           record_fraction=max(config.record_fraction, config.observation.outlier_fraction),
                           stats=stats)
    for d in deltas:
        sizes = list(result.sizes(d).values())
        stats.setdefault("mean_set_size", {})[str(d)] = float(np.mean(sizes)) if sizes else float("nan")
    return result


def dataset_fingerprint(root: str | Path) -> str:
    """SHA-256 of a dataset directory's index and shard files (the cache key's dataset part)."""
    root = Path(root)
    files = [root / "index.json", *sorted((root / "shards").glob("*.npz"))]
    if not files[0].exists():
        raise PlausibleSetError(f"{root} is not a dataset (no index.json)")
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode())
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def cache_key(fingerprint: str, config: PlausibleConfig, references: Sequence[int] | None) -> str:
    """Cache file stem for a dataset fingerprint, parameters and reference subset."""
    payload = json.dumps({"data": fingerprint, "config": config.to_dict(),
                          "references": None if references is None else [int(r) for r in references],
                          "version": 1}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:24]


def cached_plausible_sets(views: Sequence[EvalView], meshes: MeshSource, fingerprint: str, cache_dir: str | Path,
                          config: PlausibleConfig | None = None, references: Sequence[int] | None = None,
                          runner: TaskRunner | None = None, progress: bool = True, desc: str = "plausible sets",
                          recompute: bool = False) -> tuple[PlausibleSets, Path, bool]:
    """:func:`compute_plausible_sets` with an on-disk cache keyed by dataset fingerprint + parameters.

    A run that was killed left its finished references in ``plausible_<key>.parts/`` beside the cache file; the
    next call computes only the rest (``recompute`` starts over).

    Returns:
        (sets, cache file, whether it came from the cache).
    """
    config = config or PlausibleConfig()
    path = Path(cache_dir) / f"plausible_{cache_key(fingerprint, config, references)}.npz"
    parts = path.with_suffix(".parts")
    if recompute:
        shutil.rmtree(parts, ignore_errors=True)
    elif path.exists():
        return PlausibleSets.load(path), path, True
    sets = compute_plausible_sets(views, meshes, config, references, runner, progress, desc, parts_dir=parts)
    sets.stats["fingerprint"] = fingerprint
    sets.save(path)
    shutil.rmtree(parts, ignore_errors=True)
    return sets, path, False


def plausible_shape_occupancy(views: Sequence[EvalView], meshes: MeshSource | Callable[[str], MeshRaycaster],
                              i: int, members: Sequence[tuple[int, np.ndarray]],
                              raycasters: dict[str, MeshRaycaster] | None = None) -> np.ndarray:
    """Occupancy grids of plausible shapes in reference ``i``'s observation grid.

    One definition of occupancy everywhere: :func:`pssnet_core.geometry.solid_occupancy`.

    Args:
        views: the test set.
        meshes: identity -> (vertices, faces).
        i: the reference observation.
        members: [(j, T)] from :meth:`PlausibleSets.members`.
        raycasters: optional cache of raycasters by identity (filled in).

    Returns:
        (P, N, N, N) bool.
    """
    raycasters = {} if raycasters is None else raycasters
    pose = views[i].grid_pose
    n = pose.size
    out = np.zeros((len(members), n, n, n), dtype=bool)
    for k, (j, transform) in enumerate(members):
        identity = views[j].identity
        if identity not in raycasters:
            vertices, faces = meshes(identity)
            raycasters[identity] = MeshRaycaster(vertices, faces)
        placed = np.asarray(transform) @ views[j].object_pose
        out[k] = raycasters[identity].occupancy_grid(pose, placed)
    return out


__all__ = ["EvalView", "MeshSource", "MeshTable", "ObservationModelError", "PlausibleConfig", "PlausibleSetError",
           "PlausibleSets", "ShapeMeshes", "cache_key", "cached_plausible_sets", "compute_plausible_sets",
           "dataset_fingerprint", "diameter", "diameter_bound_rejects", "icp_cloud", "plausible_shape_occupancy"]
