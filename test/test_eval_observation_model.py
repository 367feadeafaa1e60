"""Observation model (Alg. 1) on hand-made scenes where the answer is known."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pssnet_core.evaluation.observation_model import (
    DepthView,
    MeshRaycaster,
    MultiDeltaView,
    ObservationModelConfig,
    ObservationModelError,
    PlausibilityResult,
    depth_gradient_mask,
)
from pssnet_core.geometry import CameraIntrinsics

K = CameraIntrinsics(width=40, height=40, fx=100.0, fy=100.0, cx=19.5, cy=19.5)


def is_plausible(view: DepthView, raycaster: MeshRaycaster, camera_from_object: np.ndarray,
                 config: ObservationModelConfig | None = None) -> PlausibilityResult:
    """Alg. 1 at one delta, through the evaluation's own path (no early rejection: every result is complete)."""
    config = config or ObservationModelConfig()
    return MultiDeltaView(view, config, (config.delta,), sparse_pixels=0).judge(raycaster, camera_from_object)[
        config.delta]


def pose(t=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def box(extents, centre=(0.0, 0.0, 0.0)) -> MeshRaycaster:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(centre)
    return MeshRaycaster.from_trimesh(mesh)


def render(caster: MeshRaycaster, camera_from_object: np.ndarray, k: CameraIntrinsics = K) -> np.ndarray:
    return caster.depth(camera_from_object, k, np.arange(k.width), np.arange(k.height))


def wall_view(depth_m: float) -> DepthView:
    """A wall much wider than the field of view at ``depth_m``: every pixel is object, no silhouette."""
    caster = box((3.0, 3.0, 0.2))
    depth = render(caster, pose((0, 0, depth_m + 0.1)))
    assert np.isfinite(depth).all()
    return DepthView(depth=depth, mask=np.ones_like(depth, dtype=bool), intrinsics=K)


@pytest.mark.parametrize(("shift", "expected"), [(0.03, True), (0.05, False), (-0.035, True), (-0.045, False)])
def test_depth_offset_either_side_of_delta(shift, expected):
    view = wall_view(1.0)
    wall = box((3.0, 3.0, 0.2))
    result = is_plausible(view, wall, pose((0, 0, 1.1 + shift)), ObservationModelConfig(delta=0.04))
    assert result.plausible is expected
    assert result.compared == K.width * K.height
    assert result.violations == (0 if expected else K.width * K.height)
    assert result.max_object_error == pytest.approx(abs(shift), abs=1e-5)


def test_scaled_delta_is_stricter():
    view = wall_view(1.0)
    wall = box((3.0, 3.0, 0.2))
    candidate = pose((0, 0, 1.1 + 0.02))
    assert is_plausible(view, wall, candidate, ObservationModelConfig(delta=0.04)).plausible
    assert not is_plausible(view, wall, candidate, ObservationModelConfig(delta=0.01)).plausible


def step_scene(step_col: float):
    """Object of two walls: left of ``step_col`` (x, metres at 1 m) at 0.5 m, right at 0.6 m."""
    near = box((1.0, 3.0, 0.1), centre=(step_col - 0.5, 0, 0.05))  # x in [step-1, step] at z 0.5..0.6
    far = box((1.0, 3.0, 0.1), centre=(step_col + 0.5, 0, 0.15))   # z 0.6..0.7
    v = np.concatenate([near.vertices, far.vertices])
    f = np.concatenate([near.faces, far.faces + len(near.vertices)])
    return MeshRaycaster(v, f)


def test_gradient_edge_pixels_are_ignored():
    # Observed: the step between columns 19 and 20 (x = 0 at z=0.5). Candidate: step moved by one pixel.
    obs_caster = step_scene(0.0)
    depth = render(obs_caster, pose((0, 0, 0.5)))
    view = DepthView(depth=depth, mask=np.ones(depth.shape, dtype=bool), intrinsics=K)
    cfg = ObservationModelConfig(delta=0.04)
    unreliable = depth_gradient_mask(depth, 0.04, 1)
    assert unreliable.any() and not unreliable.all()
    one_px = step_scene(0.0 + 1.0 * 0.5 / 100.0)  # one pixel to the right at z=0.5
    assert is_plausible(view, one_px, pose((0, 0, 0.5)), cfg).plausible
    # Without inflation the moved edge pixel is compared and violates.
    strict = ObservationModelConfig(delta=0.04, inflate=0, margin_px=1)
    result = is_plausible(view, one_px, pose((0, 0, 0.5)), strict)
    assert not result.plausible and result.violations == K.height
    four_px = step_scene(4.0 * 0.5 / 100.0)
    result = is_plausible(view, four_px, pose((0, 0, 0.5)), cfg)
    assert not result.plausible
    # Columns 20..23 now differ by 10 cm; the observed edge (forward difference at column 19) inflated by one
    # pixel covers 18..20, so columns 21..23 violate.
    assert result.violations == 3 * K.height


def test_outlier_allowance():
    view = wall_view(1.0)
    wall = box((3.0, 3.0, 0.2))
    # A bump 6 cm in front of the wall (z 0.94..1.0) covering pixel columns 20..21 and rows 20..22 (pixel
    # centres at x = (u - 19.5) / 100 * z; the bump spans x in [0.002, 0.023], y in [0.002, 0.030]).
    bump = box((0.021, 0.028, 0.06), centre=(0.0125, 0.016, 1.0 - 0.03))
    f = np.concatenate([wall.faces, bump.faces + len(wall.vertices)])
    wall_in_place = wall.vertices + np.array([0, 0, 1.1], dtype=np.float32)
    candidate = MeshRaycaster(np.concatenate([wall_in_place, bump.vertices]), f)
    bump_pixels = int(np.isfinite(render(bump, pose())).sum())
    assert bump_pixels == 6
    cfg = ObservationModelConfig(delta=0.04)
    result = is_plausible(view, candidate, pose(), cfg)
    assert result.violations == bump_pixels and not result.plausible
    assert is_plausible(view, candidate, pose(), ObservationModelConfig(delta=0.04, outlier_count=6)).plausible
    assert not is_plausible(view, candidate, pose(), ObservationModelConfig(delta=0.04, outlier_count=5)).plausible
    frac = ObservationModelConfig(delta=0.04, outlier_fraction=6.5 / (K.width * K.height))
    assert is_plausible(view, candidate, pose(), frac).plausible


def small_object_scene():
    """A 10 cm cube at 1 m in front of a background wall at 1.5 m; slit occluder hides columns 0..9."""
    cube = box((0.1, 0.1, 0.1))
    bg = box((5.0, 5.0, 0.1))
    d_obj = render(cube, pose((0, 0, 1.05)))
    d_bg = render(bg, pose((0, 0, 1.55)))
    mask = d_obj < d_bg
    depth = np.where(mask, d_obj, d_bg)
    return cube, depth, mask


def test_background_and_occluded_pixels():
    cube, depth, mask = small_object_scene()
    view = DepthView(depth=depth, mask=mask, intrinsics=K)
    cfg = ObservationModelConfig(delta=0.04)
    assert is_plausible(view, cube, pose((0, 0, 1.05)), cfg).violations == 0
    # A wider candidate covers background pixels 50 cm behind it: the camera saw through it.
    wide = box((0.2, 0.1, 0.1))
    result = is_plausible(view, wide, pose((0, 0, 1.05)), cfg)
    assert not result.plausible and result.violations > 0
    # Candidate missing: object pixels unexplained.
    assert not is_plausible(view, cube, pose((0.5, 0, 1.05)), cfg).plausible
    # Behind a non-object reading (an occluder at 0.8 m over the right part): hidden, consistent.
    occluded = depth.copy()
    occluded[:, 25:] = 0.8
    occ_mask = mask.copy()
    occ_mask[:, 25:] = False
    view_occ = DepthView(depth=occluded, mask=occ_mask, intrinsics=K)
    wider_right = box((0.2, 0.1, 0.1), centre=(0.05, 0, 0))
    assert is_plausible(view_occ, wider_right, pose((0, 0, 1.05)), cfg).plausible
    # Slit-occluded pixels (depth 0, mask 0) are excluded: the same candidate is fine when they hide it.
    slit = depth.copy()
    slit_mask = mask.copy()
    slit[:, 25:] = 0.0
    slit_mask[:, 25:] = False
    view_slit = DepthView(depth=slit, mask=slit_mask, intrinsics=K)
    assert is_plausible(view_slit, wider_right, pose((0, 0, 1.05)), cfg).plausible
    assert not is_plausible(view, wider_right, pose((0, 0, 1.05)), cfg).plausible


def test_crop_offset_matches_full_image():
    cube, depth, mask = small_object_scene()
    full = DepthView(depth=depth, mask=mask, intrinsics=K)
    crop = DepthView(depth=depth[8:33, 5:30], mask=mask[8:33, 5:30], intrinsics=K, offset=(5, 8))
    cfg = ObservationModelConfig(delta=0.01)
    for shift in (0.0, 0.005, 0.02):
        candidate = pose((shift, 0, 1.05))
        assert is_plausible(full, cube, candidate, cfg).plausible == is_plausible(crop, cube, candidate, cfg).plausible


def test_multi_delta_matches_single():
    view = wall_view(1.0)
    wall = box((3.0, 3.0, 0.2))
    multi = MultiDeltaView(view, ObservationModelConfig(), (0.04, 0.01))
    res = multi.judge(wall, pose((0, 0, 1.12)))
    assert res[0.04].plausible and not res[0.01].plausible


def test_bad_input_raises():
    with pytest.raises(ObservationModelError, match="delta"):
        ObservationModelConfig(delta=0.0)
    with pytest.raises(ObservationModelError, match="gradient"):
        ObservationModelConfig(gradient="sideways")
    with pytest.raises(ObservationModelError, match="mask shape"):
        DepthView(depth=np.ones((4, 4)), mask=np.ones((3, 4)), intrinsics=K)
    view = wall_view(1.0)
    with pytest.raises(ObservationModelError, match="rigid"):
        is_plausible(view, box((1, 1, 1)), np.diag([2.0, 1, 1, 1]))
