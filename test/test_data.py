"""Synthetic datasets: rendering, ground truth, observation consistency, determinism, resume, CLI."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage

from pssnet_core.data import cli as data_cli
from pssnet_core.data.build import build_dataset, dataset_path
from pssnet_core.data.datasets import (
    DatasetSpec,
    DatasetSpecError,
    dataset_specs,
    full_images,
    make_sample,
    plan_view,
    rerender,
    sample_intrinsics,
)
from pssnet_core.data.scenes import (
    ObjectScene,
    SensorNoise,
    Slit,
    ground_truth_occupancy,
    render_view,
)
from pssnet_core.data.store import DatasetReader
from pssnet_core.geometry import GridConfig, GridPose, observe
from pssnet_core.shapes import make_shape

GRID = 32


def tiny_specs() -> list[DatasetSpec]:
    """One mug (8 views), two ycb training objects (6 views), one narrow-slit test object (6 views)."""
    mugs = dataset_specs("mugs", "train", grid_size=GRID, num_objects=1, views=8)
    ycb = dataset_specs("ycb", "train", grid_size=GRID, num_objects=2, views=6)
    narrow = dataset_specs("ycb", "test", grid_size=GRID, num_objects=1, views=6)[:1]
    return [*mugs, *ycb, *narrow]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    out = []
    for spec in tiny_specs():
        result = build_dataset(spec, dataset_path(root, spec), progress=False)
        out.append((spec, DatasetReader(result.path)))
    return out


def all_samples(built):
    for spec, reader in built:
        for i in range(len(reader)):
            yield spec, reader.get(i)


def grid_to_object(sample) -> np.ndarray:
    pose = GridPose.from_dict(sample["grid_pose"])
    return np.linalg.inv(np.asarray(sample["object_pose"])) @ np.asarray(sample["camera_pose"]) @ pose.to_matrix()


def centres_in_object(sample, grid: np.ndarray) -> np.ndarray:
    voxel = sample["grid_pose"]["voxel_size"]
    g2o = grid_to_object(sample)
    return (np.argwhere(grid) + 0.5) * voxel @ g2o[:3, :3].T + g2o[:3, 3]


def test_every_sample_has_the_documented_fields(built):
    for spec, sample in all_samples(built):
        n = spec.grid_size
        for key in ("known_occupied", "known_free", "occupancy"):
            assert sample[key].shape == (n, n, n) and sample[key].dtype == bool
        assert sample["box"].shape == (24,) and sample["box"].dtype == np.float32
        assert sample["depth"].dtype == np.uint16 and sample["mask"].dtype == np.uint8
        assert sample["occupancy"].sum() > 0 and sample["known_occupied"].sum() > 0
        assert sample["family"] == sample["identity"].split("-")[0]
        if spec.name == "mugs":
            assert sample["slit_width_m"] is None and isinstance(sample["handle_visible"], bool)
        else:
            assert sample["slit_width_m"] > 0 and sample["handle_visible"] is None


def test_known_free_never_intersects_ground_truth(built):
    for _, sample in all_samples(built):
        assert not np.any(sample["known_free"] & sample["occupancy"]), sample["identity"]


def test_known_occupied_lies_on_the_ground_truth_surface(built):
    # A voxel holding an observed surface point has its centre within half a voxel diagonal of that point;
    # depth is rounded to 1 mm, hence the tolerance.
    worst = 0.0
    for _, sample in all_samples(built):
        shape = make_shape(sample["family"], sample["seed"])
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(shape.mesh.vertices, dtype=np.float32)),
                            o3d.core.Tensor(np.asarray(shape.mesh.faces, dtype=np.uint32)))
        centres = centres_in_object(sample, sample["known_occupied"]).astype(np.float32)
        distance = scene.compute_distance(o3d.core.Tensor(centres)).numpy()
        tolerance = 0.5 * np.sqrt(3) * sample["grid_pose"]["voxel_size"] + 0.0006
        assert distance.max() <= tolerance, (sample["identity"], distance.max(), tolerance)
        worst = max(worst, float(distance.max() / sample["grid_pose"]["voxel_size"]))
    assert worst > 0.2  # the check measures something (centres are not all exactly on the surface)
    print(f"largest known-occupied centre to surface distance: {worst:.3f} voxels")


def test_box_corners_contain_the_ground_truth(built):
    for _, sample in all_samples(built):
        corners = sample["box"].reshape(8, 3).astype(np.float64)
        origin = corners[0]
        edges = np.stack([corners[1] - origin, corners[2] - origin, corners[4] - origin])
        centres = np.argwhere(sample["occupancy"]) + 0.5
        local = (centres - origin) @ np.linalg.inv(edges)  # box coordinates, [0, 1]^3 inside the box
        # Surface voxels' centres may lie outside the box, but at most half a voxel diagonal.
        outside = (np.clip(-local, 0, None) + np.clip(local - 1, 0, None)) * np.linalg.norm(edges, axis=1)
        assert np.linalg.norm(outside, axis=1).max() <= 0.5 * np.sqrt(3) + 1e-6, sample["identity"]
        # The corners are exactly the posed bounding box, and opposite edges are parallel (a box, not a blob).
        np.testing.assert_allclose(corners[7] - corners[6], corners[1] - corners[0], atol=1e-4)


def test_node_path_on_stored_images_gives_identical_grids(built):
    for _, reader in built:
        config = GridConfig(**reader.meta["grid_config"])
        for i in range(len(reader)):
            sample = reader.get(i)
            depth, mask = full_images(sample)
            obs = observe(depth, mask, sample_intrinsics(sample), np.asarray(sample["up"]), config)
            assert np.array_equal(obs.known_occupied, sample["known_occupied"])
            assert np.array_equal(obs.known_free, sample["known_free"])
            np.testing.assert_allclose(obs.pose.origin, sample["grid_pose"]["origin"], atol=1e-12)


def test_rerender_reproduces_the_stored_crop(built):
    _, reader = built[1]  # ycb train: slit, random translation
    sample = reader.get(3)
    view = rerender(sample)
    v0, u0 = sample["crop"]
    h, w = sample["depth"].shape
    crop = np.rint(view.depth[v0:v0 + h, u0:u0 + w].astype(np.float64) * 1000).astype(np.uint16)
    assert np.array_equal(crop, sample["depth"])
    assert np.array_equal(view.mask[v0:v0 + h, u0:u0 + w], sample["mask"])


def test_slit_columns_are_neither_occupied_nor_free(built):
    checked = 0
    for _, sample in all_samples(built):
        if sample["slit_columns"] is None:
            continue
        u0, u1 = sample["slit_columns"]
        intr = sample_intrinsics(sample)
        pose = GridPose.from_dict(sample["grid_pose"])
        for key in ("known_free", "known_occupied"):
            u, _, z = intr.project(pose.occupied_centres(sample[key]))
            # A free voxel's centre projects into the slit; an occupied voxel's centre lies within half a
            # voxel diagonal of a point seen in the slit.
            margin = 0.0 if key == "known_free" else 0.5 * np.sqrt(3) * pose.voxel_size * intr.fx / z + 0.5
            assert np.all(np.rint(u) >= u0 - margin) and np.all(np.rint(u) < u1 + margin), (key, sample["identity"])
        # The slit really hides something: free space is carved only inside it.
        depth, mask = full_images(sample)
        assert not depth[:, :u0].any() and not depth[:, u1:].any() and not mask[:, :u0].any()
        checked += 1
    assert checked >= 12


def test_ground_truth_is_the_filled_surface_and_holds_every_observed_point():
    shape = make_shape("mug", 5)
    view = render_view(shape, yaw_deg=40.0, distance=0.6, tilt_deg=25.0)
    obs = view.observe(GridConfig.for_size(GRID))
    occupancy = ground_truth_occupancy(shape, view.object_pose, obs.pose, view.camera_pose)
    # Every voxel whose centre is inside the solid (queried over the whole grid, not just the object's block).
    every_voxel = obs.pose.occupied_centres(np.ones((obs.pose.size,) * 3, bool))
    world = every_voxel @ view.camera_pose[:3, :3].T + view.camera_pose[:3, 3]
    local = (world - view.object_pose[:3, 3]) @ view.object_pose[:3, :3]
    centre_inside = ObjectScene(shape).occupancy(local).reshape(occupancy.shape)
    assert centre_inside.sum() > 100 and not (centre_inside & ~occupancy).any()
    # Observed voxels are ground-truth voxels (thin walls: centres alone miss about half of them). Depth is
    # rounded to millimetres, so a point within 0.5 mm of a voxel face may land in the neighbour: allow a
    # few of those, all face-adjacent to the ground truth.
    observed = obs.known_occupied
    assert observed.sum() > 100
    assert (observed & ~occupancy).sum() <= 0.03 * observed.sum()
    assert (observed & ~centre_inside).sum() > 0.3 * observed.sum()
    assert not (observed & ~ndimage.binary_dilation(occupancy)).any()
    # The added voxels are surface voxels: their centre lies within half a voxel diagonal of the surface.
    mesh_scene = o3d.t.geometry.RaycastingScene()
    mesh_scene.add_triangles(o3d.core.Tensor(np.asarray(shape.mesh.vertices, dtype=np.float32)),
                             o3d.core.Tensor(np.asarray(shape.mesh.faces, dtype=np.uint32)))
    added = local.reshape(*occupancy.shape, 3)[occupancy & ~centre_inside].astype(np.float32)
    distance = mesh_scene.compute_distance(o3d.core.Tensor(added)).numpy()
    assert len(added) > 50 and distance.max() <= 0.5 * np.sqrt(3) * obs.pose.voxel_size + 1e-6


def mug_with_handle() -> int:
    return next(s for s in range(50) if make_shape("mug", s).handle is not None)


def test_handle_visibility_follows_the_yaw():
    shape = make_shape("mug", mug_with_handle())
    scene = ObjectScene(shape)
    # Camera on the -x side: yaw 0 turns the handle (+x) away, 90 / 180 / 270 show it.
    assert render_view(shape, 0.0, 0.7, 20.0, scene=scene).handle_visible is False
    for yaw in (90.0, 180.0, 270.0):
        view = render_view(shape, yaw, 0.7, 20.0, scene=scene)
        assert view.handle_visible is True and view.handle_area_m2 > 2e-4, yaw
    assert render_view(make_shape("can", 1)).handle_visible is None


def test_render_view_basics():
    shape = make_shape("box", 3)
    view = render_view(shape, yaw_deg=20.0, distance=0.8, tilt_deg=35.0)
    assert view.depth.shape == (480, 640) and view.depth.dtype == np.float32 and view.mask.sum() > 100
    # The plane is visible around the object; depth is whole millimetres.
    assert (view.depth[view.mask == 0] > 0).mean() > 0.5
    np.testing.assert_allclose(view.depth * 1000, np.rint(view.depth * 1000), atol=1e-3)
    # up is world z in the camera frame: looking down 35 degrees, it points to image-up (-y) and back (-z).
    assert np.isclose(np.degrees(np.arcsin(-view.up[2])), 35.0, atol=1e-6) and view.up[1] < 0
    # The object touches the plane.
    lowest = (np.asarray(shape.mesh.vertices) @ view.object_pose[:3, :3].T + view.object_pose[:3, 3])[:, 2].min()
    assert abs(lowest) < 1e-9


def test_slit_and_noise_options():
    shape = make_shape("can", 2)
    plain = render_view(shape, distance=0.6)
    slit = render_view(shape, distance=0.6, slit=Slit(0.036))
    u0, u1 = slit.slit_columns
    assert 0.8 * 0.036 * 525 / 0.6 < u1 - u0 < 1.2 * 0.036 * 525 / 0.6
    assert slit.mask.sum() < plain.mask.sum() and not slit.depth[:, :u0].any()
    noisy = render_view(shape, distance=0.6, noise=SensorNoise(), noise_seed=1)
    again = render_view(shape, distance=0.6, noise=SensorNoise(), noise_seed=1)
    assert np.array_equal(noisy.depth, again.depth) and not np.array_equal(noisy.depth, plain.depth)
    assert np.array_equal(noisy.mask, plain.mask)
    with pytest.raises(ValueError, match="slit width"):
        Slit(0.0)
    with pytest.raises(ValueError, match="tilt"):
        render_view(shape, tilt_deg=90.0)


def shard_contents(root):
    reader = DatasetReader(root)
    return reader.records, [reader.load_shard(s, images=True) for s in range(reader.num_shards)]


def assert_same_dataset(a, b) -> None:
    records_a, shards_a = shard_contents(a)
    records_b, shards_b = shard_contents(b)
    assert records_a == records_b
    for sa, sb in zip(shards_a, shards_b, strict=True):
        assert sa.keys() == sb.keys()
        for key in sa:
            for x, y in zip(sa[key], sb[key], strict=True):
                assert np.array_equal(x, y), key


def test_build_is_deterministic_and_resumes(tmp_path):
    # The same build on a 2-worker Ray: test_ray_tasks.py.
    spec = dataclasses.replace(dataset_specs("ycb", "train", grid_size=16, num_objects=2, views=3)[0],
                               objects_per_shard=1)
    serial = build_dataset(spec, tmp_path / "a", progress=False)
    again = build_dataset(spec, tmp_path / "b", progress=False)
    assert serial.samples == again.samples == 6 and serial.shards_built == 2
    assert_same_dataset(serial.path, again.path)
    # Resume: delete one shard, rebuild: only it is made again, and the result is identical.
    (tmp_path / "b" / "shards" / "00001.npz").unlink()
    resumed = build_dataset(spec, tmp_path / "b", progress=False)
    assert resumed.shards_built == 1 and resumed.shards_skipped == 1
    assert_same_dataset(serial.path, resumed.path)
    # Another seed makes other samples; resuming into a directory of another spec is refused.
    other = build_dataset(dataclasses.replace(spec, seed=1), tmp_path / "c", progress=False)
    assert shard_contents(other.path)[0] != shard_contents(serial.path)[0]
    with pytest.raises(DatasetSpecError, match="different build"):
        build_dataset(dataclasses.replace(spec, seed=1), tmp_path / "a", progress=False)


def test_make_sample_is_independent_of_order():
    spec = dataset_specs("mugs", "train", grid_size=16, num_objects=1, views=4)[0]
    identity = spec.object_identities()[0]
    scene = ObjectScene(make_shape(identity.family, identity.seed))
    forward = [make_sample(spec, i, scene) for i in range(4)]
    backward = [make_sample(spec, i, scene) for i in reversed(range(4))][::-1]
    for a, b in zip(forward, backward, strict=True):
        assert np.array_equal(a["known_free"], b["known_free"]) and a["camera_pose"] == b["camera_pose"]


def test_specs_defaults_splits_and_errors():
    train = {s.name: s for s in dataset_specs("all", "train")}
    test = {s.name: s for s in dataset_specs("all", "test")}
    assert set(train) == {"mugs", "ycb"} and set(test) == {"mugs", "mugs_narrow", "ycb_narrow", "ycb_wide"}
    assert 10_000 <= sum(s.num_samples for s in train.values()) <= 20_000
    assert all(500 <= s.num_samples <= 1000 for s in test.values())
    assert train["mugs"].views == 72 and train["ycb"].views == 24
    assert test["ycb_narrow"].slit_width_m == pytest.approx(0.036) and test["ycb_wide"].slit_width_m == 0.18
    train_ids = {str(i) for s in train.values() for i in s.object_identities()}
    test_ids = {str(i) for s in test.values() for i in s.object_identities()}
    val = {s.name: s for s in dataset_specs("all", "val")}
    val_ids = {str(i) for s in val.values() for i in s.object_identities()}
    assert not train_ids & test_ids and not val_ids & (train_ids | test_ids)
    assert set(val) == {"mugs", "ycb"} and val["ycb"].slit_mode == "random"  # validated like training
    # Narrow and wide test sets show the same objects in the same poses.
    a, b = (dataclasses.replace(test[n], num_objects=1) for n in ("ycb_narrow", "ycb_wide"))
    ident = a.object_identities()[0]
    shape = make_shape(ident.family, ident.seed)
    scene = ObjectScene(shape)
    sa, sb = make_sample(a, 5, scene), make_sample(b, 5, scene)
    assert sa["camera_pose"] == sb["camera_pose"] and sa["slit_width_m"] != sb["slit_width_m"]
    assert spec_roundtrip(train["ycb"]) == train["ycb"]
    with pytest.raises(DatasetSpecError, match="family"):
        dataset_specs("chairs", "train")
    with pytest.raises(DatasetSpecError, match="split"):
        dataset_specs("mugs", "holdout")
    with pytest.raises(DatasetSpecError, match="views must be at most"):
        dataset_specs("ycb", "train", views=25)
    with pytest.raises(DatasetSpecError, match="num_objects"):
        dataset_specs("mugs", "train", num_objects=0)


def spec_roundtrip(spec: DatasetSpec) -> DatasetSpec:
    return DatasetSpec.from_dict(spec.to_dict())


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="pssnet")
    data_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_build_preview_stats(tmp_path, capsys):
    out = tmp_path / "ds"
    assert run_cli(["dataset", "build", "--family", "mugs", "--split", "test", "--out", str(out), "--grid", "16",
                    "--num-objects", "1", "--views", "4", "--quiet"]) == 0
    assert (out / "test" / "mugs" / "index.json").exists()
    assert run_cli(["dataset", "stats", str(out)]) == 0
    text = capsys.readouterr().out
    assert "mug" in text and "4 samples" in text
    png = tmp_path / "sheet.png"
    assert run_cli(["dataset", "preview", str(out), "--out", str(png), "--count", "2"]) == 0
    # The mug test split is two datasets (the open views and the same views through the slit): a sheet each.
    for name in ("mugs", "mugs_narrow"):
        assert (tmp_path / f"sheet_test_{name}.png").stat().st_size > 10_000
    # Bad input: a clear error and exit code 2, not a traceback.
    assert run_cli(["dataset", "stats", str(tmp_path / "nothing")]) == 2
    assert "no dataset" in capsys.readouterr().err


def test_large_scale_is_many_objects_few_random_yaw_views_and_half_noisy():
    large = {s.name: s for s in dataset_specs("all", "train", scale="large")}
    assert {s.num_objects for s in large.values()} == {20_000} and {s.views for s in large.values()} == {4}
    assert sum(s.num_samples for s in large.values()) >= 150_000
    assert all(s.random_yaw and s.noise is not None and s.noise_fraction == 0.5 for s in large.values())
    assert not {str(i) for s in large.values() for i in s.object_identities()[:500]} & \
        {str(i) for s in dataset_specs("all", "val") for i in s.object_identities()}
    # Validation and test sets do not depend on the scale: models of either scale are compared alike.
    for split in ("val", "test"):
        assert dataset_specs("all", split, scale="large") == dataset_specs("all", split)
    with pytest.raises(DatasetSpecError, match="scale"):
        dataset_specs("all", "train", scale="huge")
    with pytest.raises(DatasetSpecError, match="noise_fraction"):
        dataclasses.replace(large["mugs"], noise_fraction=1.5)

    spec = dataclasses.replace(large["mugs"], num_objects=1, views=8, grid_size=16)
    assert spec_roundtrip(spec) == spec
    identity = spec.object_identities()[0]
    scene = ObjectScene(make_shape(identity.family, identity.seed))
    samples = [make_sample(spec, i, scene) for i in range(spec.views)]
    yaws = [s["rotation_deg"] for s in samples]
    assert len({round(y, 3) for y in yaws}) == 8 and all(0 <= y < 360 for y in yaws)
    assert sorted(yaws) != [i * 45.0 for i in range(8)]  # drawn, not the fixed steps
    noisy = [s["noise"] is not None for s in samples]
    assert any(noisy) and not all(noisy)  # half of the views on average: both kinds in 8 draws (seeded)
    for sample in samples:  # the record says what the view got: re-rendering reproduces the stored crop
        depth, _ = full_images(sample)
        again = rerender(sample, scene.shape)
        v0, u0 = sample["crop"]
        h, w = sample["depth"].shape
        np.testing.assert_allclose(again.depth[v0:v0 + h, u0:u0 + w], depth[v0:v0 + h, u0:u0 + w], atol=6e-4)


def test_boxes_scale_adds_independent_and_edged_boxes_to_the_ycb_objects_only():
    boxes = {s.name: s for s in dataset_specs("all", "train", scale="boxes", num_objects=14)}
    large = {s.name: s for s in dataset_specs("all", "train", scale="large", num_objects=14)}
    assert boxes["mugs"] == large["mugs"]
    assert dataclasses.replace(boxes["ycb"], families=large["ycb"].families) == large["ycb"]
    families = [i.family for i in boxes["ycb"].object_identities()]
    assert sum(f.startswith("box") for f in families) == 6 and {"box_broad", "box_edged"} <= set(families)
    for split in ("val", "test"):
        assert dataset_specs("all", split, scale="boxes") == dataset_specs("all", split)


def test_broad_scale_mixes_prior_breaking_families_and_hides_mug_handles_behind_slits():
    broad = {s.name: s for s in dataset_specs("all", "train", scale="broad", num_objects=8)}
    assert broad["mugs"].families == ("mug", "mug_broad") and broad["mugs"].is_mugs
    assert broad["mugs"].slit_mode == "random" and broad["mugs"].slit_range_m[1] > 0.2  # often wider than a mug
    assert set(broad["ycb"].families) >= {"box_broad", "can_broad", "bottle_broad", "box"}
    assert {str(i).split("-")[0] for i in broad["mugs"].object_identities()} == {"mug", "mug_broad"}
    for split in ("val", "test"):
        assert dataset_specs("all", split, scale="broad") == dataset_specs("all", split)
    spec = dataclasses.replace(broad["mugs"], num_objects=2, views=6, grid_size=16)
    identity = spec.object_identities()[1]
    scene = ObjectScene(make_shape(identity.family, identity.seed))
    samples = [make_sample(spec, spec.views + i, scene) for i in range(spec.views)]
    assert all(s["slit_width_m"] is not None and s["family"] == "mug_broad" for s in samples)


def test_slits_scale_shows_half_the_mug_views_through_a_slit_with_the_cameras_of_large():
    slits = {s.name: s for s in dataset_specs("all", "train", scale="slits", num_objects=8)}
    large = {s.name: s for s in dataset_specs("all", "train", scale="large", num_objects=8)}
    assert slits["ycb"] == large["ycb"] and slits["mugs"].slit_range_m == large["ycb"].slit_range_m
    for split in ("val", "test"):
        assert dataset_specs("all", split, scale="slits") == dataset_specs("all", split)
    plans = [(plan_view(slits["mugs"], i), plan_view(large["mugs"], i)) for i in range(64)]
    slitted = [a.slit is not None for a, _ in plans]
    assert 16 <= sum(slitted) <= 48 and not any(b.slit for _, b in plans)
    # Only the slit differs: the same yaw, camera and noise as the mugs of --scale large, view for view.
    assert all(dataclasses.replace(a, slit=None) == b for a, b in plans)
    with pytest.raises(DatasetSpecError, match="slit_fraction"):
        dataclasses.replace(slits["mugs"], slit_fraction=1.5)


def test_a_smaller_slit_fraction_slits_a_subset_of_the_same_mug_views():
    half = {s.name: s for s in dataset_specs("all", "train", scale="slits", num_objects=8)}["mugs"]
    fifth = {s.name: s for s in dataset_specs("all", "train", scale="slits", num_objects=8, slit_fraction=0.2)}["mugs"]
    assert fifth.slit_fraction == 0.2 and dataclasses.replace(fifth, slit_fraction=0.5) == half
    plans = [(plan_view(fifth, i), plan_view(half, i)) for i in range(200)]
    slitted = [a.slit is not None for a, _ in plans]
    assert 20 <= sum(slitted) <= 60  # about 40 of 200
    # The share drawn per view from the slit's own stream: each view slitted at 0.2 is slitted at 0.5, alike.
    assert all(a == b for a, b in plans if a.slit is not None)
    assert all(dataclasses.replace(a, slit=None) == dataclasses.replace(b, slit=None) for a, b in plans)
    for scale, split in (("large", "train"), ("slits", "val")):
        with pytest.raises(DatasetSpecError, match="slit fraction"):
            dataset_specs("mugs", split, scale=scale, slit_fraction=0.2)


def test_mug_test_sets_behind_the_narrow_slit_pair_with_the_open_ones_view_by_view():
    specs = {s.name: s for s in dataset_specs("mugs", "test", grid_size=16, num_objects=2, views=6)}
    assert list(specs) == ["mugs", "mugs_narrow"]
    narrow = specs["mugs_narrow"]
    assert (narrow.slit_mode, narrow.slit_width_m, narrow.stream) == ("fixed", 0.036, "mugs")
    identity = narrow.object_identities()[0]
    assert identity == specs["mugs"].object_identities()[0]
    scene = ObjectScene(make_shape(identity.family, identity.seed))
    for i in range(3):
        seen, slitted = make_sample(specs["mugs"], i, scene), make_sample(narrow, i, scene)
        assert slitted["camera_pose"] == seen["camera_pose"] and slitted["object_pose"] == seen["object_pose"]
        assert slitted["mask"].sum() < seen["mask"].sum() and slitted["slit_width_m"] == 0.036
        assert not (slitted["known_occupied"] & seen["known_free"]).any()  # the same scene, less of it seen
    oof = {s.name: s for s in dataset_specs("oof", "test", num_objects=2)}
    assert oof["oof_mugs_narrow"].identities == oof["oof_mugs"].identities
    assert oof["oof_mugs_narrow"].stream == "oof_mugs" and oof["oof_mugs_narrow"].slit_width_m == 0.036


def test_a_build_spec_written_before_a_field_existed_still_resumes(tmp_path):
    spec = dataset_specs("mugs", "train", grid_size=16, num_objects=1, views=2)[0]
    first = build_dataset(spec, tmp_path / "a", progress=False)
    spec_file = first.path / "build_spec.json"
    old = json.loads(spec_file.read_text())
    for field in ("noise_fraction", "random_yaw", "slit_fraction"):
        del old["spec"][field]
    spec_file.write_text(json.dumps(old))
    again = build_dataset(spec, first.path, progress=False)
    assert again.shards_built == 0 and again.samples == 2
    with pytest.raises(DatasetSpecError, match="different build"):
        build_dataset(dataclasses.replace(spec, random_yaw=True), first.path, progress=False)
