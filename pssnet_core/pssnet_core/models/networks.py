"""3-D convolutional building blocks shared by the models (encoder, decoder, discriminator, U-Net)."""

from __future__ import annotations

import contextlib
import functools
import weakref
from collections.abc import Callable, Iterator
from typing import NamedTuple

import torch
from torch import nn


def to_memory_format(x: torch.Tensor, reference: nn.Module) -> torch.Tensor:
    """Puts a 5-D activation in the memory format of ``reference``'s first 5-D weight.

    Why: the dense -> reshape step produces a contiguous (NCDHW) tensor; with channels_last_3d weights the
    following conv is fastest (oneDNN, cuDNN) when its input is channels_last_3d too.
    """
    for p in reference.parameters():
        if p.ndim == 5:
            if p.is_contiguous(memory_format=torch.channels_last_3d) and not p.is_contiguous():
                return x.contiguous(memory_format=torch.channels_last_3d)
            return x
    return x


class BlockConv3d(nn.Conv3d):
    """Conv3d(kernel 2, stride 2, no padding) computed as one matrix product over 2x2x2 blocks.

    With kernel == stride the blocks do not overlap, so the layer is ``blocks(x) @ W``: each output voxel
    is its input block's 8 * C_in values times a (8 * C_in, C_out) matrix. Same parameters and state_dict
    keys as nn.Conv3d, so checkpoints are interchangeable.

    Why by hand: on this AVX2 CPU oneDNN runs the encoder's batch-1 convolutions at 2-5 GMAC/s, a third of
    the same work as one GEMM (``python benchmarks/inference_bench.py --layers``); torch has no such layer.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(in_channels, out_channels, kernel_size=2, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        blocks = self.blocks(x)
        weight = self.row_weight().t()
        y = torch.addmm(self.bias, blocks, weight) if self.bias is not None else blocks @ weight
        return self.to_grid(y, x)

    def blocks(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, D, H, W) -> (B * D/2 * H/2 * W/2, 8 * C_in): each output voxel's input block as one row,
        [kd, kh, kw, C_in]."""
        b, c_in, d, h, w = _check_5d(x, self.in_channels)
        if d % 2 or h % 2 or w % 2:
            raise ValueError(f"BlockConv3d needs even spatial sizes, got {tuple(x.shape[2:])}")
        return (x.permute(0, 2, 3, 4, 1).reshape(b, d // 2, 2, h // 2, 2, w // 2, 2, c_in)
                .permute(0, 1, 3, 5, 2, 4, 6, 7).reshape(-1, 8 * c_in))

    def row_weight(self) -> torch.Tensor:
        """(C_out, 8 * C_in), columns [kd, kh, kw, C_in]: a free view for channels_last_3d weights."""
        return self.weight.permute(0, 2, 3, 4, 1).reshape(self.out_channels, -1)

    def to_grid(self, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Output rows (one per output voxel) -> (B, C_out, D/2, H/2, W/2) in channels_last_3d memory."""
        b, _, d, h, w = x.shape
        return y.view(b, d // 2, h // 2, w // 2, self.out_channels).permute(0, 4, 1, 2, 3)


class BlockDeconv3d(nn.ConvTranspose3d):
    """ConvTranspose3d(kernel 2, stride 2, no padding) computed as one matrix product and a voxel shuffle.

    With kernel == stride every input voxel writes its own 2x2x2 output block, so the layer is exactly
    ``rows(x) @ W`` with W of shape (C_in, 8 * C_out), followed by a reshuffle of the 8 columns into the
    block. Same parameters and state_dict keys as nn.ConvTranspose3d, so checkpoints are interchangeable.

    Why by hand: oneDNN's deconvolution on this AVX2 CPU runs the decoder's last stage (64 -> 1 channels,
    16^3 -> 32^3, batch 20) at under 1 GMAC/s, 5-10x below the same work as one GEMM
    (``python benchmarks/inference_bench.py --layers``); torch has no such layer.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(in_channels, out_channels, kernel_size=2, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        b, c_in, d, h, w = _check_5d(x, self.in_channels)
        rows = self.block_rows(x.permute(0, 2, 3, 4, 1).reshape(-1, c_in))  # free for channels_last_3d input
        return blocks_to_grid(rows, b, (d, h, w), 1)  # NCDHW shape, channels_last_3d memory

    def block_rows(self, rows: torch.Tensor) -> torch.Tensor:
        """The layer on voxel rows (R, C_in) -> (8 R, C_out): each input row's 2x2x2 output block as 8
        consecutive rows in [kd, kh, kw] order ("block order"), no shuffle into spatial order."""
        weight = self.row_weight().t()
        y = torch.addmm(self.bias.repeat(8), rows, weight) if self.bias is not None else rows @ weight
        return y.view(-1, self.out_channels)

    def row_weight(self) -> torch.Tensor:
        """(8 * C_out, C_in), rows [kd, kh, kw, C_out]: the transpose of a free view for channels_last_3d
        weights."""
        return self.weight.permute(0, 2, 3, 4, 1).reshape(self.in_channels, -1).t()


def blocks_to_grid(rows: torch.Tensor, batch: int, size: tuple[int, int, int], stages: int) -> torch.Tensor:
    """Voxel rows in block order after ``stages`` kernel-2 stride-2 upsamplings -> (B, C, D, H, W) in
    channels_last_3d memory.

    ``rows`` is (B, d, h, w, [kd1, kh1, kw1], ..., [kd_s, kh_s, kw_s], C) flattened, (d, h, w) = ``size``;
    output depth index D = ((d * 2 + kd1) * 2 + kd2) ... and likewise for H and W. One copy for all stages.
    """
    c = rows.shape[-1]
    y = rows.view(batch, *size, *([2, 2, 2] * stages), c)
    # axis a (0 = D, 1 = H, 2 = W) of stage j sits at 1 + a + 3 j (j = 0: the coarse grid).
    spatial = [1 + a + 3 * j for a in range(3) for j in range(stages + 1)]
    y = y.permute(0, *spatial, y.ndim - 1).reshape(batch, *(n * 2**stages for n in size), c)
    return y.permute(0, 4, 1, 2, 3)


@functools.lru_cache(maxsize=8)
def grid_order(side: int, stages: int) -> torch.Tensor:
    """(N^3,) int64: for each voxel of one (N, N, N) grid in spatial order, its row in block order
    (see :func:`blocks_to_grid`), N = side * 2**stages."""
    rows = torch.arange((side * 2**stages) ** 3).view(-1, 1)
    return blocks_to_grid(rows, 1, (side,) * 3, stages).reshape(-1)


# ------------------------------------------------------------------------------ fused inference (oneDNN)
# Inference on the CPU runs every GEMM as one oneDNN matmul with its bias and activation fused in (torch's
# linear_pointwise op, the one torch.compile's CPU backend emits) on weights pre-packed once. Why: with
# addmm + ReLU, torch broadcasts the bias into the whole output before the GEMM and makes a second pass for
# the ReLU, and each such pass over the 21 MB 128 -> 64 output is a parallel region that, on a busy 2-core
# machine, waits for the slower thread (BENCHMARKS.md, "Inference"). The same path runs in bf16 (weights packed
# once in bf16, bf16 activations between stages) under CPU bf16 autocast: the autocast layers cast the weights and
# permute blocks on every call, and on AMX CPUs those copies took more time than the matmuls.


# Largest intermediate of one chunk of the decoder's later stages (see Decoder3D.probabilities): a few MB, about
# the share of this CPU's 32 MB L3 cache one stage's output can have while its input and weights are there too.
_TAIL_CHUNK_BYTES = 4 << 20

# In-place activations of the torch.addmm form of PackedLinear, by oneDNN post-op name.
_ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {"none": lambda y: y, "relu": torch.relu_}


class PackedLinear(NamedTuple):
    """y = activation(x @ weight.T + bias) on a weight packed once (see :func:`pack_linear`).

    ``onednn``: ``weight`` is in oneDNN's packed layout and one fused oneDNN matmul computes y; otherwise
    ``weight`` is the (K, N) transposed weight for torch.addmm and the activation is a second, in-place pass.
    """

    weight: torch.Tensor
    bias: torch.Tensor | None
    onednn: bool

    def __call__(self, x: torch.Tensor, activation: str = "none") -> torch.Tensor:
        if self.onednn:
            return torch.ops.mkldnn._linear_pointwise(x, self.weight, self.bias, activation, [], "")
        y = torch.addmm(self.bias, x, self.weight) if self.bias is not None else x @ self.weight
        return _ACTIVATIONS[activation](y)


def onednn_runs(dtype: torch.dtype) -> bool:
    """Whether oneDNN's linear runs ``dtype`` on this CPU: fp32 always; bf16 where it has AVX-512 (BW, VL, DQ) or
    AVX-NE-CONVERT, natively with AVX512-BF16 / AMX. On an AVX2-only CPU oneDNN has no bf16 linear at all."""
    return dtype == torch.float32 or bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def pack_linear(weight: torch.Tensor, bias: torch.Tensor | None, dtype: torch.dtype) -> PackedLinear:
    """An (N, K) weight and its bias as a :class:`PackedLinear` in ``dtype``: oneDNN's packed layout where oneDNN
    runs ``dtype``, else a bf16 weight for torch.addmm (bf16 emulated on an AVX2 CPU: slow but the same numbers,
    so the bf16 path can be tested there)."""
    w = weight.detach().to(dtype).contiguous()
    b = None if bias is None else bias.detach().to(dtype).contiguous()
    if w.device.type == "cpu" and onednn_runs(dtype):
        return PackedLinear(torch.ops.mkldnn._reorder_linear_weight(w), b, True)
    return PackedLinear(w.t(), b, False)


def fused_dtype(x: torch.Tensor) -> torch.dtype | None:
    """The dtype the fused inference path runs in for input ``x``, or None where it may not run.

    It runs without autograd on fp32 CPU tensors with oneDNN built in, when not traced (an ONNX export wants the
    plain GEMMs): in float32 outside autocast, in bfloat16 under CPU bf16 autocast (how ``Completer`` asks for
    bf16); under any other autocast it does not run.
    """
    if (torch.is_grad_enabled() or x.device.type != "cpu" or x.dtype != torch.float32
            or not torch.backends.mkldnn.is_available() or torch.jit.is_tracing()):
        return None
    if not torch.is_autocast_enabled("cpu"):
        return torch.float32
    return torch.bfloat16 if torch.get_autocast_dtype("cpu") == torch.bfloat16 else None


_PackCache = dict[tuple[str, torch.dtype], tuple[tuple[tuple[int, int], ...], list[PackedLinear]]]
_PACKED: weakref.WeakKeyDictionary[nn.Module, _PackCache] = weakref.WeakKeyDictionary()


def packed_linears(module: nn.Module, weights: Callable[[], list[tuple[torch.Tensor, torch.Tensor | None]]],
                   dtype: torch.dtype, purpose: str = "forward") -> list[PackedLinear]:
    """The ((N, K) weight, bias) pairs that ``weights()`` gives, packed in ``dtype``; cached per module, ``purpose``
    (one module may pack several sets) and dtype until any of its parameters changes (storage or in-place version:
    optimizer steps, load_state_dict, .to())."""
    key = tuple((p.data_ptr(), p._version) for p in module.parameters())
    per_set = _PACKED.setdefault(module, {})
    cached = per_set.get((purpose, dtype))
    if cached is None or cached[0] != key:
        cached = per_set[(purpose, dtype)] = (key, [pack_linear(w, b, dtype) for w, b in weights()])
    return cached[1]


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """torch on one thread inside the block (the OpenMP setting is per calling thread; MKL's is global)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _check_5d(x: torch.Tensor, channels: int) -> tuple[int, int, int, int, int]:
    if x.ndim != 5 or x.shape[1] != channels:
        raise ValueError(f"expected (B, {channels}, D, H, W), got {tuple(x.shape)}")
    return tuple(x.shape)  # type: ignore[return-value]


class Encoder3D(nn.Module):
    """The paper's encoder: stages of Conv3d(kernel 2, stride 2) + ReLU, then one dense layer.

    Args:
        in_channels: input channels (2: known occupied, known free).
        channels: channels per stage; each stage halves the grid.
        grid_size: input grid size N.
        out_features: size of the dense output (2 x latent for mean and log-variance).
    """

    def __init__(self, in_channels: int, channels: list[int], grid_size: int, out_features: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_channels
        for ch in channels:
            layers += [BlockConv3d(width, ch), nn.ReLU(inplace=True)]
            width = ch
        self.conv = nn.Sequential(*layers)
        self.side = grid_size // 2 ** len(channels)
        self.dense = nn.Linear(width * self.side**3, out_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        convs = [m for m in self.conv if not isinstance(m, nn.ReLU)]
        dtype = fused_dtype(x)
        if dtype is not None and all(isinstance(m, BlockConv3d) for m in convs):
            return self._fused_forward(x, convs, dtype)
        return self.dense(self.conv(x).flatten(1))

    def _fused_forward(self, x: torch.Tensor, convs: list[BlockConv3d], dtype: torch.dtype) -> torch.Tensor:
        """The same function without autograd: each stage one fused matmul (+ bias + ReLU) in ``dtype``; the
        output is in ``dtype`` too (as autocast's dense layer gives it)."""

        def weights() -> list[tuple[torch.Tensor, torch.Tensor | None]]:
            # The dense layer reads the last grid voxel-major ([voxel, C]), as the stages emit it.
            dense = self.dense.weight.view(self.dense.out_features, convs[-1].out_channels, self.side**3)
            return ([(m.row_weight(), m.bias) for m in convs]
                    + [(dense.transpose(1, 2).reshape(self.dense.out_features, -1), self.dense.bias)])

        *stages, dense = packed_linears(self, weights, dtype)
        x = x.to(dtype)
        for conv, stage in zip(convs, stages, strict=True):
            x = conv.to_grid(stage(conv.blocks(x), "relu"), x)
        return dense(x.permute(0, 2, 3, 4, 1).reshape(x.shape[0], -1))


class Decoder3D(nn.Module):
    """Mirror of :class:`Encoder3D`: dense (+ ReLU) to a (C, b, b, b) grid, ConvTranspose3d(2, 2) + ReLU
    stages, last stage to one channel of occupancy *logits* (sigmoid applied by the caller)."""

    def __init__(self, latent_dim: int, channels: list[int], grid_size: int) -> None:
        super().__init__()
        self.side = grid_size // 2 ** len(channels)
        self.top = channels[-1]
        self.dense = nn.Linear(latent_dim, self.top * self.side**3)
        ins = list(reversed(channels))
        outs = [*ins[1:], 1]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(ins, outs, strict=False)):
            layers.append(BlockDeconv3d(a, b))
            if i < len(outs) - 1:  # the last stage emits logits
                layers.append(nn.ReLU(inplace=True))
        self.deconv = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        # Every stage maps each voxel to its own 2x2x2 block, so the stages run on voxel rows in block order
        # and only the last output is shuffled into spatial order: one copy of the one-channel output
        # instead of one of every stage's output (see BENCHMARKS.md, "Inference").
        h = torch.relu(self.dense(z))
        rows = h.view(-1, self.top, self.side**3).transpose(1, 2).reshape(-1, self.top)  # [b, d, h, w] x C
        stages = 0
        for layer in self.deconv:
            if isinstance(layer, BlockDeconv3d):
                rows, stages = layer.block_rows(rows), stages + 1
            else:  # per-voxel (ReLU)
                rows = layer(rows)
        side = (self.side,) * 3
        return blocks_to_grid(rows, h.shape[0], side, stages)

    def block_order(self) -> torch.Tensor:
        """(N^3,) int64: for each voxel of the output grid in spatial order, its place in block order (the order
        :meth:`logits_and_pullback` gives logits in)."""
        return grid_order(self.side, len(self._stages()))

    def _stages(self) -> list[BlockDeconv3d]:
        return [m for m in self.deconv if isinstance(m, BlockDeconv3d)]

    def _row_weights(self) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
        """The dense layer and the stages as ((out, in) weight, bias) pairs on voxel rows. The dense layer's outputs
        are reordered from [C, voxel] to [voxel, C]: its (B, b^3 * C) output then is the first stage's voxel rows
        (B * b^3, C) without a transpose."""
        voxels = self.side**3
        dense = self.dense.weight.view(self.top, voxels, -1).transpose(0, 1).reshape(self.top * voxels, -1)
        bias = self.dense.bias.view(self.top, voxels).t().reshape(-1)
        return [(dense, bias)] + [(m.row_weight(), None if m.bias is None else m.bias.repeat(8))
                                  for m in self._stages()]

    def logits_and_pullback(self, z: torch.Tensor, dtype: torch.dtype
                            ) -> tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
        """(B, N^3) float32 occupancy logits of latents ``z`` in block order (:meth:`block_order`), and their
        pullback: a function from dL/dlogits (B, N^3, block order) to dL/dz (B, latent_dim), float32. Computed in
        ``dtype`` without autograd, the decoder's weights packed once as for :meth:`probabilities`; no weight
        gradients. For the checked sampler's refinement, which needs the latent's gradient of a loss on the
        logits. Why by hand: through autograd (under autocast) each step cast every weight, broadcast the biases
        into the outputs, ran separate ReLUs and copied views back; the forward here is the fused inference path
        (keeping each stage's output) and the backward two passes per stage: the transposed matmul and the ReLU's
        mask (BENCHMARKS.md, "The refinement's cost")."""
        stages = self._stages()
        forward = packed_linears(self, self._row_weights, dtype)
        backward = packed_linears(self, lambda: [(w.t(), None) for w, _ in self._row_weights()], dtype, "pullback")
        batch = z.shape[0]
        rows = forward[0](z.to(dtype), "relu").view(-1, self.top)
        kept = [rows]  # each ReLU's output: the dense layer's, then every stage's but the last
        for k, (stage, linear) in enumerate(zip(stages, forward[1:], strict=True)):
            last = k == len(stages) - 1
            rows = linear(rows, "none" if last else "relu").view(-1, stage.out_channels)
            if not last:
                kept.append(rows)
        logits = rows.view(batch, -1).float()

        def pullback(grad: torch.Tensor) -> torch.Tensor:
            g = grad.to(dtype).reshape(-1, 8 * stages[-1].out_channels)
            for k in reversed(range(len(stages))):
                g = torch.ops.aten.threshold_backward(backward[k + 1](g), kept[k], 0)  # at stage k's input
                g = g.view(batch, -1) if k == 0 else g.view(-1, 8 * stages[k - 1].out_channels)
            return backward[0](g).float()

        return logits, pullback

    def probabilities(self, z: torch.Tensor, spatial: bool = True) -> torch.Tensor:
        """sigmoid(self(z)), (B, 1, N, N, N) float32; with ``spatial`` False (B, N^3) in block order
        (:meth:`block_order`), for callers that read a few voxels of many grids. Where the fused path runs
        (``sample``'s case on the CPU, see :func:`fused_dtype`): each stage one fused matmul (+ bias + ReLU) in fp32
        or bf16, in block order, the stages after the first on chunks of rows; the sigmoid of the last stage's
        logits in fp32; one gather into spatial order."""
        layers = [m for m in self.deconv if not isinstance(m, nn.ReLU)]
        dtype = fused_dtype(z)
        if dtype is None or not all(isinstance(m, BlockDeconv3d) for m in layers):
            probs = torch.sigmoid(self(z).float())
            return probs if spatial else probs.view(z.shape[0], -1)[:, torch.argsort(self.block_order())]
        dense, *stages = packed_linears(self, self._row_weights, dtype)
        rows = dense(z.to(dtype), "relu").view(-1, self.top)
        # The first stage runs whole; the later ones chunk by chunk of its output rows (each row's outputs stay
        # consecutive in block order), so that a chunk's intermediates stay in cache where the whole ones would
        # go through memory (at 64^3 the 128 -> 64 output is 168 MB): 64^3 263 -> 200 ms, 32^3 the same
        # (BENCHMARKS.md, "Inference"). Chunking the first stage too re-reads its 4 MB of weights per chunk.
        head = min(1, len(layers) - 1)
        for layer, stage in zip(layers[:head], stages[:head], strict=True):
            rows = stage(rows, "relu").view(-1, layer.out_channels)
        tail, tail_stages = layers[head:], stages[head:]
        widest = max([8 ** (k + 1) * layer.out_channels * rows.element_size() for k, layer in enumerate(tail[:-1])],
                     default=1)
        chunk = max(1, _TAIL_CHUNK_BYTES // widest)
        grow = 8 ** len(tail)
        probs = torch.empty(rows.shape[0] * grow)  # one channel, float32: (B * N^3) in block order
        for start in range(0, rows.shape[0], chunk):
            part = rows[start:start + chunk]
            for layer, stage in zip(tail[:-1], tail_stages[:-1], strict=True):
                part = stage(part, "relu").view(-1, layer.out_channels)
            # Sigmoid in fp32 on the logits: a bf16 probability (8-bit mantissa) would round p = 0.5 + 1e-3 to 0.5,
            # where the logit's sign, and so the occupancy, is still exact.
            logits = tail_stages[-1](part).view(-1).float()
            torch.sigmoid(logits, out=probs[start * grow:start * grow + logits.shape[0]])
        probs = probs.view(z.shape[0], -1)
        if not spatial:
            return probs
        n = self.side * 2 ** len(layers)
        # A gather instead of blocks_to_grid's 3 * (stages + 1) + 2-dimensional permuted copy, which torch
        # walks two elements at a time (1.3 vs 16 ms median, 20 x 32^3).
        return probs.index_select(1, grid_order(self.side, len(layers))).view(-1, 1, n, n, n)


class Discriminator3D(nn.Module):
    """Conv3d(k4, s2, p1) + LeakyReLU stages, dense to one logit per input grid."""

    def __init__(self, in_channels: int, channels: list[int], grid_size: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_channels
        side = grid_size
        for ch in channels:
            layers += [nn.Conv3d(width, ch, kernel_size=4, stride=2, padding=1), nn.LeakyReLU(0.2, inplace=True)]
            width, side = ch, side // 2
        if side < 1:
            raise ValueError(f"too many discriminator stages ({len(channels)}) for grid {grid_size}")
        self.conv = nn.Sequential(*layers)
        self.dense = nn.Linear(width * side**3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.dense(self.conv(x).flatten(1)).squeeze(1)


class UNet3D(nn.Module):
    """3D-RecGAN++ generator without super-resolution: a U-Net with a dense bottleneck.

    Encoder: Conv3d(k4, s2, p1) + LeakyReLU(0.2) per stage. Bottleneck: flatten -> dense(code) + ReLU ->
    dense + ReLU -> reshape. Decoder: ConvTranspose3d(k4, s2, p1) whose input is the concatenation of the
    previous decoder output and the encoder output of the same size; ReLU, last stage to 1 logit channel.
    """

    def __init__(self, in_channels: int, channels: list[int], grid_size: int, bottleneck_dim: int) -> None:
        super().__init__()
        self.down = nn.ModuleList()
        width = in_channels
        for ch in channels:
            self.down.append(nn.Sequential(nn.Conv3d(width, ch, 4, 2, 1), nn.LeakyReLU(0.2, inplace=True)))
            width = ch
        self.side = grid_size // 2 ** len(channels)
        self.top = width
        flat = width * self.side**3
        self.fc = nn.Sequential(nn.Linear(flat, bottleneck_dim), nn.ReLU(inplace=True),
                                nn.Linear(bottleneck_dim, flat), nn.ReLU(inplace=True))
        self.up = nn.ModuleList()
        outs = [*reversed(channels[:-1]), 1]
        for i, (skip, out) in enumerate(zip(reversed(channels), outs, strict=False)):
            block: list[nn.Module] = [nn.ConvTranspose3d(width + skip, out, 4, 2, 1)]
            if i < len(outs) - 1:
                block.append(nn.ReLU(inplace=True))
            self.up.append(nn.Sequential(*block))
            width = out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for stage in self.down:
            x = stage(x)
            skips.append(x)
        h = self.fc(x.flatten(1)).view(-1, self.top, self.side, self.side, self.side)
        h = to_memory_format(h, self.up)
        for stage, skip in zip(self.up, reversed(skips), strict=False):
            h = stage(torch.cat([h, skip], dim=1))
        return h
