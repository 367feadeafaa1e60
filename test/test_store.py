"""Dataset shards: round trip, streaming batches, resume support and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from test_models_helpers import DatasetWriter

from pssnet_core.data.store import DatasetError, DatasetReader, finalize, shard_exists, write_shard


def make_sample(i: int, n: int = 8) -> dict:
    rng = np.random.default_rng(i)
    return {
        "known_occupied": rng.random((n, n, n)) < 0.1,
        "known_free": rng.random((n, n, n)) < 0.5,
        "occupancy": rng.random((n, n, n)) < 0.2,
        "box": rng.random(24).astype(np.float32),
        "depth": rng.integers(0, 5000, size=(3 + i % 4, 5), dtype=np.uint16),  # crops of varying size
        "identity": f"mug-{i:05d}",
        "handle_visible": bool(i % 2),
    }


@pytest.fixture
def dataset(tmp_path):
    writer = DatasetWriter(tmp_path / "ds", {"grid_size": 8, "voxel_size": 0.025}, shard_size=3)
    samples = [make_sample(i) for i in range(8)]
    for s in samples:
        writer.add(s)
    assert writer.close() == 8
    return DatasetReader(tmp_path / "ds"), samples


def test_round_trip_every_sample(dataset):
    reader, samples = dataset
    assert len(reader) == 8 and reader.num_shards == 3
    assert reader.grid_size == 8 and reader.voxel_size == 0.025
    for i, expected in enumerate(samples):
        got = reader.get(i)
        for key, value in expected.items():
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(got[key], value)
                assert got[key].dtype == value.dtype
            else:
                assert got[key] == value


def test_batches_cover_the_dataset_once_and_shuffle_by_seed(dataset):
    reader, samples = dataset
    batches = list(reader.iter_batches(batch_size=3, shuffle=True, seed=4))
    order = np.concatenate([b["index"] for b in batches])
    assert sorted(order.tolist()) == list(range(8))
    assert [len(b["index"]) for b in batches] == [3, 3, 2]
    for batch in batches:
        assert set(batch) == {"known_occupied", "known_free", "occupancy", "box", "index"}
        for row, index in enumerate(batch["index"]):
            np.testing.assert_array_equal(batch["occupancy"][row], samples[index]["occupancy"])
    again = np.concatenate([b["index"] for b in reader.iter_batches(batch_size=3, shuffle=True, seed=4)])
    other = np.concatenate([b["index"] for b in reader.iter_batches(batch_size=3, shuffle=True, seed=5)])
    np.testing.assert_array_equal(order, again)
    assert not np.array_equal(order, other)
    plain = np.concatenate([b["index"] for b in reader.iter_batches(batch_size=3, shuffle=False)])
    np.testing.assert_array_equal(plain, np.arange(8))


def test_drop_last_and_subsets(dataset):
    reader, _ = dataset
    assert [len(b["index"]) for b in reader.iter_batches(3, shuffle=False, drop_last=True)] == [3, 3]
    subset = np.concatenate([b["index"] for b in reader.iter_batches(2, shuffle=False, indices=[1, 5, 6])])
    np.testing.assert_array_equal(subset, [1, 5, 6])


def test_resume_skips_written_shards_and_refuses_gaps(tmp_path):
    root = tmp_path / "ds"
    write_shard(root, 0, [make_sample(0)])
    write_shard(root, 2, [make_sample(2)])
    assert shard_exists(root, 0) and not shard_exists(root, 1)
    with pytest.raises(DatasetError, match="shard 00001 is missing"):
        finalize(root, {"grid_size": 8, "voxel_size": 0.025})
    write_shard(root, 1, [make_sample(1)])
    assert finalize(root, {"grid_size": 8, "voxel_size": 0.025}) == 3


def test_clear_errors(tmp_path):
    with pytest.raises(DatasetError, match="index.json is missing"):
        DatasetReader(tmp_path)
    (tmp_path / "index.json").write_text("{not json")
    with pytest.raises(DatasetError, match="corrupt"):
        DatasetReader(tmp_path)
    with pytest.raises(DatasetError, match="no samples"):
        write_shard(tmp_path / "x", 0, [])


def test_corrupt_shard_is_reported(dataset):
    reader, _ = dataset
    (reader.root / "shards" / "00001.npz").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="00001.npz is unreadable"):
        list(reader.iter_batches(3, shuffle=False))


def test_several_directories_read_as_one_dataset(tmp_path):
    parts = []
    for name, first, count, voxel in (("a", 0, 5, 0.025), ("b", 100, 4, 0.025), ("c", 200, 2, 0.05)):
        writer = DatasetWriter(tmp_path / name, {"grid_size": 8, "voxel_size": voxel}, shard_size=3)
        samples = [make_sample(first + i) for i in range(count)]
        for s in samples:
            writer.add(s)
        writer.close()
        parts.append(samples)
    reader = DatasetReader(f"{tmp_path / 'a'},{tmp_path / 'b'}")
    assert len(reader) == 9 and reader.num_shards == 4 and reader.grid_size == 8
    expected = parts[0] + parts[1]
    for i in (0, 4, 5, 8):  # both sides of the boundary between the two directories
        got = reader.get(i)
        assert got["identity"] == expected[i]["identity"]
        np.testing.assert_array_equal(got["occupancy"], expected[i]["occupancy"])
    seen = np.concatenate([b["index"] for b in reader.iter_batches(2, shuffle=True, seed=1)])
    assert sorted(seen.tolist()) == list(range(9))
    boxes = {int(i): b["box"][k] for b in reader.iter_batches(4, seed=3) for k, i in enumerate(b["index"])}
    for i, box in boxes.items():
        np.testing.assert_array_equal(box, expected[i]["box"])
    with pytest.raises(DatasetError, match="voxel_size"):
        DatasetReader([tmp_path / "a", tmp_path / "c"])
    with pytest.raises(DatasetError, match="no dataset"):
        DatasetReader(" , ")
