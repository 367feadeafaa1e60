"""The plausibility-checked diverse sampler: the grid check, the spread selection and its weights, the sampler on
tiny and shipped models, and where its weights and notes go (grasp scores, pipeline)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_models_helpers import tiny_model

from pssnet_core.geometry import GridPose
from pssnet_core.grasps import plan_grasps
from pssnet_core.grasps.config import GraspError
from pssnet_core.inference import DEFAULT_CHECKPOINT, Completer, CompletionInputError
from pssnet_core.sampling import (
    REFINED,
    SOURCES,
    CheckedResult,
    CheckedSampler,
    CheckedSamplerConfig,
    GridCheck,
    spread_selection,
)
from pssnet_core.spread import BitRows, farthest_point_selection, row_bit_counts, row_bit_counts_portable

pytestmark = pytest.mark.usefixtures("one_torch_thread")
N = 16
VOXEL = 0.01


def camera_facing_grid(n: int = N) -> GridPose:
    """A grid whose x axis is the camera's optical axis: rays run along +x through the grid, camera 0.5 m away."""
    rotation = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # grid x, y, z in the camera frame
    origin = -(rotation @ np.array([0.0, n / 2, n / 2])) * VOXEL + np.array([0.0, 0.0, 0.5])
    return GridPose(rotation=rotation, origin=origin, voxel_size=VOXEL, size=n)


def slab_view(front: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A wall seen face-on at grid x = ``front`` over y, z in [4, 12): observed voxels, free space before them."""
    known_occupied = np.zeros((N, N, N), bool)
    known_occupied[front, 4:12, 4:12] = True
    known_free = np.zeros((N, N, N), bool)
    known_free[:front, 4:12, 4:12] = True
    return known_occupied, known_free


def test_grid_check_counts_what_alg1_would_reject():
    known_occupied, known_free = slab_view()
    check = GridCheck.prepare(known_occupied, known_free, camera_facing_grid(), delta=0.02)
    solid = np.zeros((N, N, N), bool)
    solid[6:10, 4:12, 4:12] = True  # the seen face and a body behind it: explains everything
    hollow = solid.copy()
    hollow[6:8] = False  # surface 2 voxels (= delta) behind the observed one: still within delta
    too_deep = solid.copy()
    too_deep[6:9] = False  # 3 voxels behind: beyond delta, every observed voxel unexplained
    half = solid.copy()
    half[6:10, 4:8] = False  # half the face missing
    shallow = solid.copy()
    shallow[5, 4:12, 4:12] = True  # one voxel in front of the surface: within delta of what was seen
    intruding = solid.copy()
    intruding[1:3, 6:8, 6:8] = True  # 8 voxels far in front: the camera saw through them
    grids = np.stack([solid, hollow, too_deep, half, shallow, intruding]).reshape(6, -1)
    missed, free = check.violations(grids, BitRows.pack(grids))
    np.testing.assert_allclose(missed, [0.0, 0.0, 1.0, 0.5, 0.0, 0.0])
    assert free.tolist() == [0, 0, 0, 0, 0, 8]
    # The same check of the same grids stored in another voxel order (the decoder's block order).
    order = np.random.default_rng(1).permutation(N**3)
    stored = np.zeros_like(grids)
    stored[:, order] = grids
    reordered = check.reordered(order).violations(stored, BitRows.pack(stored))
    np.testing.assert_array_equal(reordered[0], missed)
    np.testing.assert_array_equal(reordered[1], free)


def test_packed_jaccard_and_farthest_point_selection_with_cell_weights():
    rng = np.random.default_rng(0)
    centres = [rng.random(4096) < 0.3 for _ in range(3)]
    grids, labels = [], []
    for label, size in enumerate((10, 5, 1)):  # three clusters of near-copies
        for _ in range(size):
            g = centres[label].copy()
            g[rng.integers(0, 4096, 20)] ^= True
            grids.append(g)
            labels.append(label)
    grids_array = np.stack(grids)
    packed = BitRows.pack(grids_array)
    a, b = grids_array[0], grids_array[12]
    expected = 1.0 - (a & b).sum() / (a | b).sum()
    assert packed.jaccard_to(0)[12] == pytest.approx(expected) and packed.jaccard_to(0)[0] == 0.0
    others = BitRows.pack(grids_array[[0, 12]])  # each grid's distance to the nearer of two
    expected_nearest = np.minimum(packed.jaccard_to(0), packed.jaccard_to(12))
    np.testing.assert_allclose(packed.nearest_jaccard(others), expected_nearest)
    picked, cell = farthest_point_selection(packed, 3)
    assert sorted(np.asarray(labels)[picked].tolist()) == [0, 1, 2]  # one from each cluster
    counts = np.bincount(cell, minlength=3)
    assert sorted(counts.tolist()) == [1, 5, 10]
    for position, index in enumerate(picked):  # each picked grid's cell is its own cluster
        assert set(np.asarray(labels)[cell == position]) == {labels[index]}
    copies = BitRows.pack(np.repeat(grids_array[:1], 4, axis=0))
    assert len(farthest_point_selection(copies, 3)[0]) == 1  # identical grids: nothing more to spread over


def test_bit_counts_agree_with_and_without_numpy_bitwise_count():
    """numpy 1.26 (Ubuntu 24.04, apt ROS 2 Jazzy) has no np.bitwise_count: the portable popcount counts the same."""
    rng = np.random.default_rng(1)
    grids = rng.random((7, 32**3)) < rng.random((7, 1))
    grids[0], grids[1] = False, True
    assert row_bit_counts_portable(np.array([[2**64 - 1, 0, 1 << 63]], dtype=np.uint64)).tolist() == [65]
    words = BitRows.pack(grids).words
    expected = grids.sum(axis=1)
    np.testing.assert_array_equal(row_bit_counts_portable(words), expected)
    np.testing.assert_array_equal(row_bit_counts(words), expected)
    np.testing.assert_array_equal(row_bit_counts(words[::2] & words[1]), grids[::2].sum(axis=1))
    assert BitRows.pack(grids).sizes.dtype == np.int64


def test_config_checks_and_proposal_counts():
    config = CheckedSamplerConfig(source_shares=(0.4, 0.2, 0.1, 0.3))
    counts = config.proposal_counts(20, has_box=True)
    assert counts == {"posterior": 80, "widened": 40, "prior_box": 20, "turned_box": 60} and tuple(counts) == SOURCES
    # Without its flow (an old export) there is no box to turn: that share comes from the prior's box codes.
    assert config.proposal_counts(20, has_box=True, has_flow=False) == {"posterior": 80, "widened": 40,
                                                                         "prior_box": 80, "turned_box": 0}
    assert config.proposal_counts(20, has_box=False) == {"posterior": 200, "widened": 0, "prior_box": 0,
                                                         "turned_box": 0}
    assert sum(CheckedSamplerConfig(max_proposals=50).proposal_counts(20, True).values()) == 50
    for bad in ({"proposals_per_sample": 0}, {"source_shares": (0.0, 0.0, 0.0, 0.0)}, {"delta": -0.01},
                {"source_shares": (0.4, 0.2, 0.4)}, {"turned_rest_low": 1.5},
                {"max_missed_fraction": 1.0}, {"widened_temperature": float("nan")}, {"max_free_voxels": -1},
                {"refine_steps": -1}, {"refine_misses": 5000}, {"short_pool_refine_misses": -1},
                {"refine_rate": 0.0}, {"refine_anchor": -1.0}):
        with pytest.raises(ValueError):
            CheckedSamplerConfig(**bad)


class SlabObservation:
    """An observation with its grid pose, as the pipeline and the evaluation hand it over."""

    def __init__(self) -> None:
        self.known_occupied, self.known_free = slab_view()
        self.pose = camera_facing_grid()

    def network_input(self) -> np.ndarray:
        return np.stack([self.known_occupied, self.known_free]).astype(np.float32)


def tiny_completer(name: str = "pssnet") -> Completer:
    model = tiny_model(name, N)
    if hasattr(model, "encoder"):
        with torch.no_grad():  # a wide posterior: the proposals differ
            model.encoder.dense.bias[model.latent_dim:] = 1.0
    return Completer(model, model.config)


def test_spread_selection_repeats_few_accepted_or_fills_with_the_nearest_misses():
    rng = np.random.default_rng(1)
    grids = rng.random((8, 4096)) < 0.3  # eight different proposals
    packed = BitRows.pack(grids)
    ok = np.zeros(8, dtype=bool)
    ok[[5, 6]] = True  # two accepted
    badness = np.array([4.0, 1.0, 9.0, 2.0, 7.0, 0.0, 0.0, 3.0])
    chosen, weights = spread_selection(packed, ok, badness, 4)
    assert sorted(chosen.tolist()) == [5, 6] and weights.sum() == pytest.approx(1.0)  # the sampler repeats them
    chosen, weights = spread_selection(packed, ok, badness, 4, fill=True)
    assert sorted(chosen.tolist()) == [1, 3, 5, 6]  # the accepted and the two least-violating rejected
    assert weights.sum() == pytest.approx(1.0)
    assert sorted(spread_selection(packed, np.zeros(8, bool), badness, 3)[0].tolist()) == [1, 5, 6]
    assert sorted(spread_selection(packed, ok, badness, 2, fill=True)[0].tolist()) == [5, 6]  # enough accepted


def test_checked_sampler_on_a_tiny_model_returns_weighted_seeded_samples():
    sampler = CheckedSampler(tiny_completer(), CheckedSamplerConfig(proposals_per_sample=8, max_missed_fraction=0.9,
                                                                    max_free_voxels=10_000, refine_steps=0))
    observation = SlabObservation()
    result = sampler.complete(observation, num_samples=6, seed=3)
    assert isinstance(result, CheckedResult)
    assert result.occupancy.shape == (6, N, N, N) and result.probabilities.dtype == np.float32
    assert result.weights.shape == (6,) and result.weights.sum() == pytest.approx(1.0) and result.weights.min() > 0
    assert result.proposals == 48 and result.accepted == sum(result.accepted_by_source.values())
    again = sampler.complete(observation, num_samples=6, seed=3)
    np.testing.assert_array_equal(again.probabilities, result.probabilities)
    np.testing.assert_array_equal(again.weights, result.weights)
    assert sampler.grid_size == N and sampler.model_name == "pssnet" and sampler.box_temperature == 1.0


def test_checked_sampler_says_when_no_proposal_agrees_with_the_view():
    observation = SlabObservation()
    observation.known_free = ~observation.known_occupied  # everything else seen through: any body violates
    sampler = CheckedSampler(tiny_completer(), CheckedSamplerConfig(proposals_per_sample=4, max_free_voxels=0,
                                                                    max_missed_fraction=0.0,
                                                                    fill_with_nearest_misses=False, refine_steps=0))
    result = sampler.complete(observation, num_samples=3, seed=0)
    assert result.accepted == 0 and "no proposal of 12 agrees with the view" in result.note
    refining = CheckedSampler(tiny_completer(), CheckedSamplerConfig(proposals_per_sample=4, max_free_voxels=0,
                                                                     max_missed_fraction=0.0, refine_misses=5,
                                                                     short_pool_refine_misses=5))
    assert "no proposal of 17 (5 of them refined) agrees" in refining.complete(observation, 3, seed=0).note
    assert result.occupancy.shape[0] == 3 and result.weights.sum() == pytest.approx(1.0)
    filling = CheckedSampler(tiny_completer(), CheckedSamplerConfig(proposals_per_sample=4, max_free_voxels=0,
                                                                    max_missed_fraction=0.0,
                                                                    fill_with_nearest_misses=True, refine_steps=0))
    same = filling.complete(observation, num_samples=3, seed=0)  # nothing accepted: the same fall-back
    np.testing.assert_array_equal(same.probabilities, result.probabilities)
    assert same.note == result.note


def view_loss(probabilities: torch.Tensor, known_occupied: np.ndarray, check: GridCheck) -> np.ndarray:
    """Per proposal, what the refinement minimises (without its anchor): mean -log p on the observed voxels,
    sum of -log(1 - p) on the deep-free ones over the number of observed voxels."""
    p = probabilities.double().clamp(1e-6, 1 - 1e-6).numpy()
    observed = known_occupied.reshape(-1)
    return (-np.log(p[:, observed]).mean(1) - np.log(1 - p[:, check.deep_free]).sum(1) / observed.sum())


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped default model")
def test_refinement_moves_only_the_rest_of_the_latent_towards_the_view():
    """The shipped model's turned boxes on a rendered hidden-handle mug: refined, they explain the view better (the
    loss and the grid check's violations fall), with their box codes untouched and the decoder left alone."""
    from pssnet_core.data.scenes import render_view
    from pssnet_core.geometry import observe
    from pssnet_core.pipeline import CompletionPipeline
    from pssnet_core.shapes.procedural import make_shape

    view = render_view(make_shape("mug", 2_000_001), yaw_deg=0.0, tilt_deg=30.0)
    pipeline = CompletionPipeline.from_checkpoint(None, precision="fp32")  # the same arithmetic on every CPU
    observation = observe(view.depth, view.mask, view.intrinsics, np.asarray(view.up), pipeline.grid_config())
    completer = pipeline.completer
    model = completer.model
    plain = CheckedSampler(completer, CheckedSamplerConfig(refine_steps=0))
    counts = {name: 12 if name == "turned_box" else 0 for name in SOURCES}
    latents, _ = plain.propose(completer.network_input(observation), counts, torch.Generator().manual_seed(0),
                               completer.box_temperature)
    check = GridCheck.prepare(observation.known_occupied, observation.known_free, observation.pose, 0.01)
    # The refinement works in the decoder's block order: its inputs reordered, its probabilities put back.
    order = model.decoder.block_order()
    observed = np.zeros(len(order), bool)
    observed[order.numpy()] = observation.known_occupied.reshape(-1)
    in_blocks = check.reordered(order.numpy())
    unrefined = plain.refine(latents, observed, in_blocks)[:, order]  # no steps: as proposed
    decoded: list[torch.Tensor] = []
    original = model.decoder.logits_and_pullback
    model.decoder.logits_and_pullback = lambda z, dtype: (decoded.append(z.clone()), original(z, dtype))[1]
    try:
        with torch.inference_mode():  # as a caller may run it
            refined = CheckedSampler(completer, CheckedSamplerConfig(refine_steps=3)).refine(
                latents, observed, in_blocks)[:, order]
    finally:
        del model.decoder.logits_and_pullback  # the class's method again
    box = model.box_dim
    assert len(decoded) == 3 and all(torch.equal(z[:, :box], latents[:, :box].float()) for z in decoded)
    assert not torch.equal(decoded[-1][:, box:], latents[:, box:].float())  # the rest moved
    assert all(p.grad is None for p in model.parameters())  # no gradient for the decoder's weights
    assert view_loss(refined, observation.known_occupied, check).mean() < 0.8 * view_loss(
        unrefined, observation.known_occupied, check).mean()

    def badness(probabilities: torch.Tensor) -> np.ndarray:
        occupancy = probabilities.numpy() > 0.5
        return check.badness(*check.violations(occupancy, BitRows.pack(occupancy)))

    assert badness(refined).mean() < 0.5 * badness(unrefined).mean()
    # Only where the pool falls short, when so configured: this view's pool is full under the default check and
    # short under a check that accepts nothing; where it is short, short_pool_refine_misses are refined.
    lazy = CheckedSamplerConfig(refine_only_short_pools=True, refine_misses=10, short_pool_refine_misses=30)
    full = CheckedSampler(completer, lazy).complete(observation, num_samples=5, seed=0)
    assert full.accepted >= 5 and full.refine_s == 0 and full.accepted_by_source[REFINED] == 0
    every_call = CheckedSampler(completer, replace(lazy, refine_only_short_pools=False)).complete(observation, 5, 0)
    assert every_call.proposals == full.proposals + min(10, full.proposals - full.accepted)  # full: refine_misses
    strict = replace(lazy, max_missed_fraction=0.0, max_free_voxels=0)
    short = CheckedSampler(completer, strict).complete(observation, num_samples=5, seed=0)
    assert short.refine_s > 0 and short.proposals == full.proposals + 30


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped default model")
def test_novel_misses_are_those_least_like_the_accepted_spread():
    """On a full pool (the shipped model, a rendered hidden-handle mug) the novel choice refines misses from the
    3 x refine_misses least violating, farther from the accepted proposals' spread than the least violating ones;
    on a short pool it refines the least violating, as without it."""
    from pssnet_core.data.scenes import render_view
    from pssnet_core.geometry import observe
    from pssnet_core.pipeline import CompletionPipeline
    from pssnet_core.shapes.procedural import make_shape

    view = render_view(make_shape("mug", 2_000_001), yaw_deg=0.0, tilt_deg=30.0)
    pipeline = CompletionPipeline.from_checkpoint(None, precision="fp32")
    observation = observe(view.depth, view.mask, view.intrinsics, np.asarray(view.up), pipeline.grid_config())

    def refined_latents(**options: object) -> tuple[torch.Tensor, object]:
        sampler = CheckedSampler(pipeline.completer, CheckedSamplerConfig(refine_misses=6, **options))
        chosen: list[torch.Tensor] = []
        sampler.refine = lambda latents, *rest: (chosen.append(latents), CheckedSampler.refine(sampler, latents,
                                                                                                *rest))[1]
        result = sampler.complete(observation, num_samples=20, seed=0)
        return chosen[0], result

    nearest, plain = refined_latents(refine_novel_misses=False)
    novel, result = refined_latents()  # the default
    assert plain.accepted - plain.accepted_by_source[REFINED] >= 20  # a full pool
    assert len(novel) == len(nearest) == 6 and not torch.equal(novel, nearest)
    decode = pipeline.completer.model.decode_probabilities
    with torch.inference_mode():
        grids = [decode(z).reshape(len(z), -1).numpy() > 0.5 for z in (nearest, novel)]
    accepted = result.occupancy.reshape(len(result.occupancy), -1)  # the returned spread of accepted proposals

    def novelty(rows: np.ndarray) -> float:
        return float(np.mean(BitRows.pack(rows).nearest_jaccard(BitRows.pack(accepted))))

    assert novelty(grids[1]) > novelty(grids[0])
    strict = {"max_missed_fraction": 0.0, "max_free_voxels": 0, "short_pool_refine_misses": 6}
    assert torch.equal(refined_latents(**strict)[0], refined_latents(refine_novel_misses=False, **strict)[0])


@pytest.mark.parametrize("kernel", ["onednn", "addmm"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_decoder_pullback_is_the_gradient_autograd_gives(dtype, kernel, monkeypatch):
    """Logits in block order equal to the decoder's, and the pullback of a gradient on them equal to autograd's
    through the decoder; in bf16 within its rounding. With oneDNN's packed weights where this CPU runs the dtype,
    and with torch.addmm (forced here: the path of a GPU, or of bf16 on an AVX2-only CPU)."""
    from pssnet_core.models import networks

    if kernel == "onednn" and not networks.onednn_runs(dtype):
        pytest.skip("oneDNN has no bf16 linear on this CPU (AVX2-only): the addmm case covers it")
    if kernel == "addmm":
        monkeypatch.setattr(networks, "onednn_runs", lambda dtype: False)
    model = tiny_model("pssnet", N).eval()
    z = torch.randn(3, model.latent_dim, generator=torch.Generator().manual_seed(2), requires_grad=True)
    full = model.decoder(z).reshape(3, -1)
    upstream = torch.randn(full.shape, generator=torch.Generator().manual_seed(3))
    (expected,) = torch.autograd.grad((full * upstream).sum(), [z])
    with torch.inference_mode():
        logits, pullback = model.decoder.logits_and_pullback(z.detach(), dtype)
        order = model.decoder.block_order()
        gradient = pullback(upstream[:, torch.argsort(order)])  # the upstream gradient in block order
    tolerance = {} if dtype == torch.float32 else {"rtol": 0.05, "atol": 0.05 * float(expected.abs().max())}
    torch.testing.assert_close(logits[:, order], full.detach(), **tolerance)
    torch.testing.assert_close(gradient, expected, **tolerance)
    assert all(p.grad is None for p in model.parameters())
    packed = networks._PACKED[model.decoder]  # the kernel asked for ran
    assert {p.onednn for key in (("forward", dtype), ("pullback", dtype)) for p in packed[key][1]} == {
        kernel == "onednn"}


def test_decoder_probabilities_in_block_order_are_the_grid_reordered():
    model = tiny_model("pssnet", N).eval()
    z = torch.randn(2, model.latent_dim, generator=torch.Generator().manual_seed(4))
    order = model.decoder.block_order()
    with torch.inference_mode():
        spatial = model.decoder.probabilities(z).reshape(2, -1)
        blocks = model.decoder.probabilities(z, spatial=False)  # the fused path
    plain = model.decoder.probabilities(z, spatial=False).detach()  # with autograd on: the plain path
    torch.testing.assert_close(blocks[:, order], spatial)
    torch.testing.assert_close(plain[:, order], spatial)


def test_checked_sampler_refines_its_nearest_misses_and_counts_them():
    observation = SlabObservation()
    config = CheckedSamplerConfig(proposals_per_sample=4, max_missed_fraction=0.3, max_free_voxels=10_000,
                                  refine_misses=6, short_pool_refine_misses=6, refine_steps=5, refine_rate=0.3)
    sampler = CheckedSampler(tiny_completer(), config)
    result = sampler.complete(observation, num_samples=3, seed=1)
    plain = CheckedSampler(tiny_completer(), replace(config, refine_steps=0)).complete(observation, 3, seed=1)
    refined = result.proposals - plain.proposals
    assert plain.accepted_by_source[REFINED] == 0 and 0 < refined <= 6  # only the rejected ones are refined
    assert result.accepted == sum(result.accepted_by_source.values()) >= plain.accepted
    assert result.refine_s > 0 and plain.refine_s == 0
    again = sampler.complete(observation, num_samples=3, seed=1)
    np.testing.assert_array_equal(again.probabilities, result.probabilities)


def test_checked_sampler_refuses_models_without_a_latent_and_bare_inputs():
    with pytest.raises(ValueError, match="latent-variable model"):
        CheckedSampler(tiny_completer("recgan"))
    sampler = CheckedSampler(tiny_completer("vae"))
    with pytest.raises(CompletionInputError, match="grid pose"):
        sampler.complete(SlabObservation().network_input(), num_samples=2)
    with pytest.raises(CompletionInputError, match="num_samples"):
        sampler.complete(SlabObservation(), num_samples=0)
    counts = sampler.complete(SlabObservation(), num_samples=2, seed=0).accepted_by_source
    assert counts["widened"] == counts["prior_box"] == counts["turned_box"] == 0  # a VAE has no box: posterior only


def test_turned_box_codes_turn_the_box_about_the_vertical_axis():
    model = tiny_model("pssnet", N).eval()
    torch.manual_seed(1)
    codes = torch.randn(3, model.box_dim) * 0.5

    def corners(c: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return (model.flow.inverse(c) * model.config.box_scale + model.config.box_offset).view(-1, 8, 3)

    axis = torch.tensor([7.0, 9.0])
    quarter = model.turn_box_codes(codes, axis, torch.full((3,), torch.pi / 2))
    before, after = corners(codes), corners(quarter)
    # x, y turned a quarter about the axis: (dx, dy) -> (-dy, dx); heights unchanged.
    torch.testing.assert_close(after[..., 0] - axis[0], -(before[..., 1] - axis[1]), atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(after[..., 1] - axis[1], before[..., 0] - axis[0], atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(after[..., 2], before[..., 2], atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(model.turn_box_codes(codes, axis, torch.zeros(3)), codes, atol=1e-3, rtol=1e-3)
    model.train()
    model.turn_box_codes(codes, axis, torch.ones(3))
    assert model.flow.training  # the flow's mode is left as it was (it inverts in eval mode)


def test_checked_sampler_turns_boxes_only_with_the_flow():
    observation = SlabObservation()
    config = CheckedSamplerConfig(proposals_per_sample=10, source_shares=(0.5, 0.0, 0.0, 0.5),
                                  max_missed_fraction=0.9, max_free_voxels=10_000, refine_steps=0)
    old_export = tiny_completer()
    old_export.info["missing_modules"] = ["flow."]  # as the load of an export written without the flow says
    for completer, drawn in ((tiny_completer(), "turned_box"), (old_export, "prior_box")):
        sampler = CheckedSampler(completer, config)
        assert sampler.has_flow == (drawn == "turned_box")
        counts = config.proposal_counts(2, sampler.has_box_latent, sampler.has_flow)
        assert counts[drawn] == 10 and counts["posterior"] == 10 and sum(counts.values()) == 20
        result = sampler.complete(observation, num_samples=2, seed=0)
        assert result.proposals == 20 and np.isfinite(result.probabilities).all()
        again = sampler.complete(observation, num_samples=2, seed=0)
        np.testing.assert_array_equal(again.probabilities, result.probabilities)


def test_grasp_scores_are_the_weighted_fraction_of_completions():
    pose = camera_facing_grid(32)
    box = np.zeros((32, 32, 32), bool)
    box[12:20, 13:19, 4:16] = True  # a 6 cm block standing on the grid's floor
    empty = np.zeros_like(box)
    empty[12:13, 13:19, 4:16] = True  # only its front face: a grasp around the whole block holds nothing here
    occupancy = np.stack([box, empty, box])
    plain = plan_grasps(occupancy, pose)
    weighted = plan_grasps(occupancy, pose, weights=np.array([0.1, 0.8, 0.1]))
    assert len(plain) and len(weighted) == len(plain)
    by_pose = {tuple(np.round(p[:3, 3], 6)) + (round(w, 6),): s for p, w, s in zip(plain.poses, plain.widths,
                                                                                plain.scores, strict=True)}
    for grasp_pose, width, score, holds in zip(weighted.poses, weighted.widths, weighted.scores, weighted.holds,
                                               strict=True):
        assert score == pytest.approx(holds @ np.array([0.1, 0.8, 0.1]))
        assert by_pose[tuple(np.round(grasp_pose[:3, 3], 6)) + (round(width, 6),)] == pytest.approx(holds.mean())
    for bad in (np.array([1.0, 1.0]), np.array([1.0, -1.0, 1.0]), np.zeros(3), np.array([np.nan, 1.0, 1.0])):
        with pytest.raises(GraspError, match="weights"):
            plan_grasps(occupancy, pose, weights=bad)


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped default model")
def test_pipeline_with_the_checked_sampler_and_the_up_vector_check():
    """The shipped model on a rendered mug, camera pitched 30 degrees: weights and a note through the pipeline,
    and a wrong (level-camera) up vector reported with its tilt."""
    from pssnet_core.data.scenes import render_view
    from pssnet_core.pipeline import CompletionPipeline, PipelineConfig
    from pssnet_core.shapes.procedural import make_shape

    view = render_view(make_shape("mug", 2_000_001), yaw_deg=0.0, tilt_deg=30.0)
    pipeline = CompletionPipeline.from_checkpoint(None, PipelineConfig(num_samples=5, up_vector=tuple(view.up),
                                                                       sampler="checked"))
    result = pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False)
    assert result.num_samples == 5 and result.weights.sum() == pytest.approx(1.0)
    assert result.up_disagreement_deg < 1.0 and "tilted" not in result.note
    pipeline.config = pipeline.with_config(up_vector=(0.0, -1.0, 0.0), sampler="posterior")
    level = pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False)
    assert level.up_disagreement_deg == pytest.approx(30.0, abs=1.0)
    assert "tilted 30 deg from up_vector" in level.note
    np.testing.assert_allclose(level.weights, 0.2)
    with pytest.raises(ValueError, match="sampler"):
        PipelineConfig(sampler="best")


def test_config_with_reads_each_value_as_its_fields_type_and_reaches_nested_configs():
    from pssnet_core.grasps import GraspConfig, GripperConfig
    from pssnet_core.options import config_with

    config = config_with(GraspConfig(), ["tilted_pitches=20,45,70", "side_yaws=48", "rank_by=fraction",
                                         "observed_points_check=false", "gripper.grip_force=40",
                                         "gripper.holds_axial_load=yes", "shallow_depths="])
    assert config == GraspConfig(tilted_pitches=(20.0, 45.0, 70.0), side_yaws=48, rank_by="fraction",
                                 observed_points_check=False, shallow_depths=(),
                                 gripper=GripperConfig(grip_force=40.0, holds_axial_load=True))
    assert config_with(GraspConfig(), []) == GraspConfig()
    for bad, reason in ((["side_yaws=1.5"], "'1.5' is not an integer"),
                        (["observed_points_check=maybe"], "is not true or false"),
                        (["gripper=1"], "set gripper's fields as gripper.FIELD=VALUE"),
                        (["seed.x=1"], "seed has no fields"),
                        (["gripper.palm=1"], "expected NAME=VALUE with NAME one of max_opening"),
                        (["gripper.max_opening=2"], "max_opening must be in"),  # the config's own check
                        (["rank_by=fraction"], "not rank_by: they have their own flags")):
        with pytest.raises(ValueError, match=reason):
            config_with(GraspConfig(), bad, "grasp option", refused=("rank_by",) if "rank_by" in bad[0] else ())


def test_checked_config_with_parses_command_line_options_by_field_type():
    from pssnet_core.pipeline import PipelineConfig
    from pssnet_core.sampling import checked_config_with

    config = checked_config_with(["turned_rest_low=0.75", "source_shares=0.5,0,0,0.5", "max_free_voxels=3"],
                                 CheckedSamplerConfig(delta=0.02))
    assert config == CheckedSamplerConfig(delta=0.02, turned_rest_low=0.75, source_shares=(0.5, 0.0, 0.0, 0.5),
                                          max_free_voxels=3)
    assert checked_config_with([]) == CheckedSamplerConfig()
    for bad, reason in ((["nonsense=1"], "expected NAME=VALUE with NAME one of proposals_per_sample"),
                        (["delta"], "expected NAME=VALUE"), (["max_free_voxels=1.5"], "'1.5' is not an integer"),
                        (["source_shares=a,b"], "is not comma-separated numbers"),
                        (["turned_rest_low=2"], r"turned_rest_low must lie in \[0, 1\]")):
        with pytest.raises(ValueError, match=reason):
            checked_config_with(bad)
    # The pipeline applies them after its own check_delta and proposals_per_sample, and refuses bad ones at once.
    pipeline = PipelineConfig(check_delta=0.02, sampler_options=("turned_rest_low=1.0",))
    assert pipeline.checked_sampler_config() == CheckedSamplerConfig(delta=0.02, turned_rest_low=1.0)
    with pytest.raises(ValueError, match="sampler option"):
        PipelineConfig(sampler_options=("widened=3",))
