"""3-D convolutional building blocks shared by the models (encoder, decoder, discriminator, U-Net)."""

from __future__ import annotations

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
        b, c_in, d, h, w = _check_5d(x, self.in_channels)
        if d % 2 or h % 2 or w % 2:
            raise ValueError(f"BlockConv3d needs even spatial sizes, got {tuple(x.shape[2:])}")
        blocks = (x.permute(0, 2, 3, 4, 1).reshape(b, d // 2, 2, h // 2, 2, w // 2, 2, c_in)
                  .permute(0, 1, 3, 5, 2, 4, 6, 7).reshape(-1, 8 * c_in))  # rows: [kd, kh, kw, C_in]
        weight = self.weight.permute(2, 3, 4, 1, 0).reshape(8 * c_in, self.out_channels)
        y = torch.addmm(self.bias, blocks, weight) if self.bias is not None else blocks @ weight
        return y.view(b, d // 2, h // 2, w // 2, self.out_channels).permute(0, 4, 1, 2, 3)  # channels_last_3d


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
        c_in, c_out = self.in_channels, self.out_channels
        # (C_in, C_out, 2, 2, 2) -> (C_in, [kd, kh, kw, C_out]): a free view for channels_last_3d weights.
        weight = self.weight.permute(0, 2, 3, 4, 1).reshape(c_in, 8 * c_out)
        y = torch.addmm(self.bias.repeat(8), rows, weight) if self.bias is not None else rows @ weight
        return y.view(-1, c_out)


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
        side = grid_size // 2 ** len(channels)
        self.dense = nn.Linear(width * side**3, out_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.dense(self.conv(x).flatten(1))


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
