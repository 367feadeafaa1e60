"""Model registry, configs, networks, flow and the PSSNet box replacement (tiny 16^3 configs, seconds)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_models_helpers import cuboid_sample, tiny_model

from pssnet_core.models import (
    ConfigError,
    ModelInputError,
    PSSNetConfig,
    StepContext,
    build_model,
    config_from_dict,
    default_config,
    get_model_class,
    model_names,
    networks,
)
from pssnet_core.models.base import bce_sum
from pssnet_core.models.flow import RealNVP
from pssnet_core.models.networks import BlockConv3d, BlockDeconv3d, Decoder3D, Encoder3D

GRID = 16
CPU = StepContext(torch.device("cpu"))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def batch(num: int = 4, seed: int = 0) -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(seed)
    samples = [cuboid_sample(rng, GRID) for _ in range(num)]
    stack = lambda k: np.stack([s[k] for s in samples])  # noqa: E731
    return {"input": torch.from_numpy(np.stack([stack("known_occupied"), stack("known_free")], 1)).float(),
            "target": torch.from_numpy(stack("occupancy")[:, None]).float(),
            "box": torch.from_numpy(stack("box")).float()}


def test_registry_names_and_errors():
    assert model_names() == ["pssnet", "recgan", "vae", "vae_gan"]
    for name in model_names():
        assert get_model_class(name).name == name
    with pytest.raises(ConfigError, match="unknown model"):
        get_model_class("gan3000")


@pytest.mark.parametrize("name", ["pssnet", "vae", "vae_gan", "recgan"])
def test_config_round_trip(name):
    config = default_config(name, grid_size=64)
    assert config_from_dict(config.to_dict()) == config
    import yaml
    assert config_from_dict(yaml.safe_load(config.to_yaml())) == config


def test_config_defaults_follow_the_paper():
    c = default_config("pssnet", grid_size=64)
    assert (c.latent_dim, c.box_dim, c.channels, c.bottleneck) == (200, 24, [64, 128, 256, 512], 4)
    assert (c.flow_couplings, c.flow_hidden, c.flow_hidden_layers, c.flow_batchnorm_every) == (8, 512, 2, 2)
    assert c.box_offset == c.box_scale == 32.0
    assert default_config("pssnet", grid_size=32).bottleneck == 2


def test_bad_configs_are_rejected():
    with pytest.raises(ConfigError, match="multiple"):
        PSSNetConfig(grid_size=24)
    with pytest.raises(ConfigError, match="box_dim"):
        PSSNetConfig(latent_dim=20, box_dim=24)
    with pytest.raises(ConfigError, match="unknown fields"):
        config_from_dict({"model": "vae", "latnt_dim": 3})
    with pytest.raises(ConfigError, match="'model' key"):
        config_from_dict({"grid_size": 32})


@pytest.mark.parametrize("name", ["pssnet", "vae", "vae_gan", "recgan"])
def test_shapes_and_dtypes(name):
    model = tiny_model(name).eval()
    x = batch(2)["input"]
    with torch.inference_mode():
        probs = model.sample(x[:1], 5, generator=torch.Generator().manual_seed(0))
        multi = model.sample(x, 3)
        logits = model.reconstruct(x)
    assert probs.shape == (5, 1, GRID, GRID, GRID) and probs.dtype == torch.float32
    assert float(probs.min()) >= 0.0 and float(probs.max()) <= 1.0
    assert multi.shape == (6, 1, GRID, GRID, GRID)
    assert logits.shape == (2, 1, GRID, GRID, GRID)


def test_full_size_models_build_at_32_and_64():
    # Real sizes (not tiny): the decoder really starts from b x b x b x 512.
    for grid in (32, 64):
        model = build_model(default_config("pssnet", grid_size=grid)).eval()
        with torch.inference_mode():
            out = model.sample(torch.zeros(1, 2, grid, grid, grid), 2)
        assert out.shape == (2, 1, grid, grid, grid)
        assert model.decoder.dense.out_features == 512 * (grid // 16) ** 3


def test_bad_input_shape_raises():
    model = tiny_model("vae")
    with pytest.raises(ModelInputError, match=r"\(B, 2, 16, 16, 16\)"):
        model.sample(torch.zeros(1, 1, GRID, GRID, GRID), 2)
    with pytest.raises(ModelInputError, match="num_samples"):
        model.sample(torch.zeros(1, 2, GRID, GRID, GRID), 0)


def _random_flow(dim: int = 6) -> RealNVP:
    torch.manual_seed(1)
    flow = RealNVP(dim, couplings=4, hidden=16, hidden_layers=2, batchnorm_every=2).double()
    with torch.no_grad():
        for p in flow.parameters():
            p.add_(0.3 * torch.randn_like(p))  # leave the identity initialisation
    flow.train()
    flow(torch.randn(64, dim, dtype=torch.float64) * 2 + 1)  # running statistics away from (0, 1)
    return flow.eval()


def test_flow_is_invertible():
    flow = _random_flow()
    x = torch.randn(10, 6, dtype=torch.float64)
    z, _ = flow(x)
    assert not torch.allclose(z, x)
    torch.testing.assert_close(flow.inverse(z), x, rtol=1e-9, atol=1e-9)


def test_flow_log_det_matches_autograd_jacobian():
    flow = _random_flow()
    for x in torch.randn(3, 6, dtype=torch.float64):
        jac = torch.autograd.functional.jacobian(lambda v: flow(v[None])[0][0], x)
        _, log_det = flow(x[None])
        assert math.isclose(float(log_det[0].detach()), float(torch.slogdet(jac).logabsdet), rel_tol=1e-9, abs_tol=1e-9)


def test_flow_has_batch_norm_between_every_other_coupling():
    flow = RealNVP(24)
    kinds = [type(layer).__name__ for layer in flow.layers]
    assert kinds.count("AffineCoupling") == 8 and kinds.count("BatchNormBijection") == 3
    assert kinds[2] == kinds[5] == kinds[8] == "BatchNormBijection"


def _capture_decoder_input(model):
    seen = []
    handle = model.decoder.register_forward_pre_hook(lambda _m, args: seen.append(args[0].detach().clone()))
    return seen, handle


def test_training_feeds_flow_of_box_to_the_decoder():
    model = tiny_model("pssnet").train()
    opts = model.make_optimizers(1e-3)
    b = batch(4)
    seen, handle = _capture_decoder_input(model)
    model.training_step(b, opts, CPU)
    handle.remove()
    k = model.box_dim
    expected = model.embed_box(model.normalise_box(b["box"]))
    torch.testing.assert_close(seen[0][:, :k], expected)
    # The rest of the latent is the encoder's sample, not the box code.
    with torch.no_grad():
        mu, _ = model.encode(b["input"])
    assert not torch.allclose(seen[0][:, :k], mu[:, :k], atol=1e-3)
    # A different box changes the decoder input.
    b2 = dict(b, box=b["box"] + 3.0)
    seen2, handle = _capture_decoder_input(model)
    model.training_step(b2, opts, CPU)
    handle.remove()
    assert not torch.allclose(seen2[0][:, :k], seen[0][:, :k], atol=1e-2)


def test_sampling_uses_the_posterior_not_the_flow(monkeypatch):
    model = tiny_model("pssnet").eval()
    b = batch(1)
    called = []
    handle_flow = model.flow.register_forward_hook(lambda *a: called.append(1))
    seen: list[torch.Tensor] = []
    decode = model.decode_probabilities  # sampling's decoder call (the fused path runs no forward hook)
    monkeypatch.setattr(model, "decode_probabilities", lambda z: (seen.append(z), decode(z))[1])
    with torch.inference_mode():
        model.sample(b["input"], 6, generator=torch.Generator().manual_seed(3))
        mu, logvar = model.encode(b["input"])
    handle_flow.remove()
    assert not called, "sampling must not run the flow"
    eps = torch.randn(6, model.latent_dim, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(seen[0], mu + torch.exp(0.5 * logvar) * eps)


@pytest.mark.parametrize("name", ["pssnet", "vae", "vae_gan", "recgan"])
def test_losses_finite_and_decreasing_on_tiny_overfit(name):
    model = tiny_model(name).train()
    opts = model.make_optimizers(3e-3)
    b = batch(8)
    if name == "pssnet":
        model.pretrain(lambda size: iter([b["box"]] * 100), CPU)
    history = [model.training_step(b, opts, CPU) for _ in range(40)]
    for losses in history:
        assert all(math.isfinite(v) for v in losses.values()), losses
    first = np.mean([h["rec"] for h in history[:3]])
    last = np.mean([h["rec"] for h in history[-3:]])
    assert last < 0.7 * first, (first, last)
    expected = {"pssnet": {"loss", "rec", "kl", "flow", "flow_nll"}, "vae": {"loss", "rec", "kl"},
                "vae_gan": {"loss", "rec", "kl", "adv", "disc"}, "recgan": {"loss", "rec", "adv", "disc"}}
    assert set(history[0]) == expected[name]


def test_flow_pretraining_lowers_box_nll():
    model = tiny_model("pssnet", flow_pretrain_steps=60, flow_pretrain_batch=16, flow_pretrain_lr=1e-3)
    rng = np.random.default_rng(0)
    boxes = torch.from_numpy(np.stack([cuboid_sample(rng, GRID)["box"] for _ in range(64)]))
    with torch.no_grad():
        model.flow.train()
        before = float(model.flow_nll(model.normalise_box(boxes)))
    out = model.pretrain(lambda size: (boxes[torch.randperm(64)[:size]] for _ in iter(int, 1)), CPU)
    with torch.no_grad():
        after = float(model.flow_nll(model.normalise_box(boxes)))
    assert out["flow_pretrain_steps"] == 60
    assert after < before - 5.0, (before, after)


def test_recgan_sampling_is_deterministic_repetition():
    model = tiny_model("recgan").eval()
    with torch.inference_mode():
        out = model.sample(batch(1)["input"], 4, generator=torch.Generator().manual_seed(0))
    assert all(torch.equal(out[0], out[i]) for i in range(4))


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize(("block_cls", "torch_cls", "c_in", "c_out", "size"), [
    (BlockConv3d, torch.nn.Conv3d, 3, 5, 8),
    (BlockDeconv3d, torch.nn.ConvTranspose3d, 5, 3, 4),
    (BlockDeconv3d, torch.nn.ConvTranspose3d, 6, 1, 2),
])
def test_block_layers_equal_torch_layers_with_gradients(block_cls, torch_cls, c_in, c_out, size, channels_last):
    torch.manual_seed(0)
    block = block_cls(c_in, c_out)
    reference = torch_cls(c_in, c_out, kernel_size=2, stride=2)
    reference.load_state_dict(block.state_dict())  # same parameters and keys
    x = torch.randn(2, c_in, size, size + 2, size + 4)  # anisotropic: catches a swapped axis
    if channels_last:
        block, reference = (m.to(memory_format=torch.channels_last_3d) for m in (block, reference))
        x = x.contiguous(memory_format=torch.channels_last_3d)
    x_block, x_ref = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    y_block, y_ref = block(x_block), reference(x_ref)
    assert y_block.shape == y_ref.shape
    torch.testing.assert_close(y_block, y_ref, rtol=1e-5, atol=1e-5)
    weights = torch.randn_like(y_ref)
    (y_block * weights).sum().backward()
    (y_ref * weights).sum().backward()
    torch.testing.assert_close(x_block.grad, x_ref.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(block.weight.grad, reference.weight.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(block.bias.grad, reference.bias.grad, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize(("channels", "grid"), [([3, 5, 4], 16), ([4, 6], 12)])
def test_block_order_decoder_equals_torch_transposed_convolutions(channels, grid, channels_last):
    """The decoder runs its stages in block order and shuffles once; the reference is nn.ConvTranspose3d."""
    torch.manual_seed(0)
    decoder = Decoder3D(7, channels, grid)
    with torch.no_grad():  # biases off zero so that a misplaced one shows
        for p in decoder.parameters():
            p.normal_(0.0, 0.5)
    widths = list(reversed(channels))
    reference = torch.nn.Sequential()
    for i, (a, b) in enumerate(zip(widths, [*widths[1:], 1], strict=True)):
        layer = torch.nn.ConvTranspose3d(a, b, kernel_size=2, stride=2)
        layer.load_state_dict(decoder.deconv[2 * i].state_dict())
        reference.append(layer)
        if i < len(widths) - 1:
            reference.append(torch.nn.ReLU())
    if channels_last:
        decoder, reference = (m.to(memory_format=torch.channels_last_3d) for m in (decoder, reference))
    z = torch.randn(3, 7)
    z_block, z_ref = z.clone().requires_grad_(True), z.clone().requires_grad_(True)
    y_block = decoder(z_block)
    side = grid // 2 ** len(channels)
    y_ref = reference(torch.relu(decoder.dense(z_ref)).view(-1, channels[-1], side, side, side))
    assert y_block.shape == y_ref.shape == (3, 1, grid, grid, grid)
    torch.testing.assert_close(y_block, y_ref, rtol=1e-5, atol=1e-5)
    weights = torch.randn_like(y_ref)
    (y_block * weights).sum().backward()
    (y_ref * weights).sum().backward()
    torch.testing.assert_close(z_block.grad, z_ref.grad, rtol=1e-4, atol=1e-4)


def _torch_layer_chain(blocks: list[torch.nn.Module], cls: type) -> torch.nn.Sequential:
    """nn.Conv3d / nn.ConvTranspose3d (kernel 2, stride 2) copies of ``blocks`` with ReLU between them."""
    chain = torch.nn.Sequential()
    for i, block in enumerate(blocks):
        layer = cls(block.in_channels, block.out_channels, kernel_size=2, stride=2)
        layer.load_state_dict(block.state_dict())
        chain.append(layer)
        if i < len(blocks) - 1:
            chain.append(torch.nn.ReLU())
    return chain


@pytest.mark.parametrize("chunk_bytes", [None, 500])
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize(("channels", "grid", "batch_size"), [([3, 5, 4], 16, 1), ([4, 6], 12, 2)])
def test_fused_inference_equals_torch_layers(channels, grid, batch_size, channels_last, chunk_bytes, monkeypatch):
    """Without autograd on the CPU the encoder and ``Decoder3D.probabilities`` run fused oneDNN matmuls and one
    gather; the reference is a plain nn.Conv3d / nn.ConvTranspose3d chain on the same random weights. With a tiny
    chunk size the decoder's later stages run in many chunks of rows (and a shorter last one)."""
    if not torch.backends.mkldnn.is_available():
        pytest.skip("this torch build has no oneDNN: the fused path does not run")
    if chunk_bytes is not None:
        monkeypatch.setattr(networks, "_TAIL_CHUNK_BYTES", chunk_bytes)
    torch.manual_seed(0)
    encoder, decoder = Encoder3D(2, channels, grid, 14), Decoder3D(7, channels, grid)
    with torch.no_grad():  # biases off zero so that a misplaced one shows
        for p in [*encoder.parameters(), *decoder.parameters()]:
            p.normal_(0.0, 0.5)
    x = torch.rand(batch_size, 2, grid, grid, grid)
    z = torch.randn(3, 7)
    if channels_last:
        encoder, decoder = (m.to(memory_format=torch.channels_last_3d) for m in (encoder, decoder))
        x = x.contiguous(memory_format=torch.channels_last_3d)
    side = grid // 2 ** len(channels)

    def reference() -> tuple[torch.Tensor, torch.Tensor]:
        convs = _torch_layer_chain([m for m in encoder.conv if isinstance(m, BlockConv3d)], torch.nn.Conv3d)
        deconvs = _torch_layer_chain([m for m in decoder.deconv if isinstance(m, BlockDeconv3d)],
                                     torch.nn.ConvTranspose3d)
        h = torch.relu(decoder.dense(z)).view(-1, channels[-1], side, side, side)
        return encoder.dense(torch.relu(convs(x)).flatten(1)), torch.sigmoid(deconvs(h))

    for _ in range(2):  # the second round checks that the packed weights follow an in-place weight change
        with torch.no_grad():
            encoded_ref, probs_ref = reference()
        with torch.inference_mode():
            encoded, probs = encoder(x), decoder.probabilities(z)
        assert probs.shape == (3, 1, grid, grid, grid)
        torch.testing.assert_close(encoded, encoded_ref, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(probs, probs_ref, rtol=0, atol=1e-5)
        with torch.no_grad():
            for p in [*encoder.parameters(), *decoder.parameters()]:
                p.mul_(-0.9)


@pytest.mark.parametrize("kernel", ["onednn", "addmm"])
@pytest.mark.parametrize(("channels", "grid", "batch_size"), [([3, 5, 4], 16, 1), ([4, 6], 12, 2)])
def test_fused_bf16_inference_matches_fused_fp32(channels, grid, batch_size, kernel, monkeypatch):
    """Under CPU bf16 autocast without autograd, the encoder and ``Decoder3D.probabilities`` run the fused path with
    bf16 weights packed once: oneDNN's bf16 linear where this CPU has it, else torch.addmm on bf16 tensors
    (forced here on any CPU). Against the fused fp32 path at the same input and latents: occupancy agrees in
    >= 99.5 % of voxels, probabilities within 0.03, float32 probabilities; the encoder within 2 %."""
    if kernel == "onednn" and not networks.onednn_runs(torch.bfloat16):
        pytest.skip("oneDNN has no bf16 linear on this CPU (AVX2-only): this case runs on AVX-512 / AMX CPUs")
    if kernel == "addmm":
        monkeypatch.setattr(networks, "onednn_runs", lambda dtype: dtype == torch.float32)
    torch.manual_seed(0)
    encoder, decoder = Encoder3D(2, channels, grid, 14), Decoder3D(7, channels, grid)
    with torch.no_grad():
        for p in [*encoder.parameters(), *decoder.parameters()]:
            p.normal_(0.0, 0.3)
    encoder, decoder = (m.to(memory_format=torch.channels_last_3d) for m in (encoder, decoder))
    x = torch.rand(batch_size, 2, grid, grid, grid).contiguous(memory_format=torch.channels_last_3d)
    z = torch.randn(6, 7)
    with torch.inference_mode():
        encoded, probs = encoder(x), decoder.probabilities(z)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            encoded_bf16, probs_bf16 = encoder(x), decoder.probabilities(z)
    for module in (encoder, decoder):  # the fused bf16 path ran, with the kernel asked for
        assert {p.onednn for p in networks._PACKED[module][("forward", torch.bfloat16)][1]} == {kernel == "onednn"}
    assert encoded_bf16.dtype == torch.bfloat16 and probs_bf16.dtype == torch.float32
    assert (encoded_bf16.float() - encoded).abs().max() <= 0.02 * encoded.abs().max()
    occupied = probs > 0.5
    assert 0.02 < occupied.float().mean() < 0.98
    assert ((probs_bf16 > 0.5) == occupied).float().mean() >= 0.995
    assert (probs_bf16 - probs).abs().max() <= 0.03


def test_block_layers_reject_wrong_input():
    with pytest.raises(ValueError, match="expected"):
        BlockDeconv3d(4, 2)(torch.zeros(1, 3, 2, 2, 2))
    with pytest.raises(ValueError, match="even"):
        BlockConv3d(1, 2)(torch.zeros(1, 1, 3, 4, 4))


def test_weighted_bce_matches_formula():
    logits = torch.tensor([[-2.0, 0.5, 3.0]])
    target = torch.tensor([[1.0, 0.0, 1.0]])
    p = torch.sigmoid(logits)
    expected = -(0.85 * target * torch.log(p) + 0.15 * (1 - target) * torch.log(1 - p)).sum()
    torch.testing.assert_close(bce_sum(logits, target, pos_weight=0.85), expected)
    plain = torch.nn.functional.binary_cross_entropy_with_logits(logits, target, reduction="sum")
    torch.testing.assert_close(bce_sum(logits, target), plain)


def test_channels_last_bf16_matches_fp32_closely():
    model = tiny_model("vae").eval()
    x = batch(1)["input"]
    g = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    with torch.inference_mode():
        ref = model.sample(x, 4, generator=g())
        model.to_fast_layout()
        assert model.uses_channels_last()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            fast = model.sample(x, 4, generator=g())
    assert fast.dtype == torch.float32
    assert float((fast - ref).abs().max()) < 0.05


def test_box_temperature_scales_only_the_box_dims_of_the_posterior_noise(monkeypatch):
    model = tiny_model("pssnet").eval()
    x = batch(1)["input"]
    latents: list[torch.Tensor] = []
    decode = model.decode_probabilities
    monkeypatch.setattr(model, "decode_probabilities", lambda z: (latents.append(z.clone()), decode(z))[1])
    with torch.inference_mode():
        mu, _ = model.encode(x)
        for t in (1.0, 3.0):
            model.sample(x, 4, generator=torch.Generator().manual_seed(0), box_temperature=t)
    k = model.box_dim
    plain, hot = latents[0] - mu, latents[1] - mu
    assert torch.allclose(hot[:, :k], 3.0 * plain[:, :k], atol=1e-5)
    assert torch.equal(hot[:, k:], plain[:, k:])


@pytest.mark.parametrize("name,temperature", [("pssnet", 0.0), ("pssnet", math.inf), ("pssnet", 11.0),
                                              ("vae", 2.0), ("recgan", 2.0)])
def test_box_temperature_out_of_range_or_without_a_box_part_is_refused(name, temperature):
    model = tiny_model(name).eval()
    with pytest.raises(ModelInputError, match="box_temperature"):
        model.sample(torch.zeros(1, 2, GRID, GRID, GRID), 2, box_temperature=temperature)
