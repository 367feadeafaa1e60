"""RealNVP normalizing flow over the 24-D box (Dinh et al. 2017), written here in plain PyTorch.

Why not a library: zuko 1.6 (installable from PyPI) has RealNVP couplings but no batch-norm bijection,
and the paper puts batch norm between every other coupling; normflows has one but pulls extra
dependencies. Neither is on the GPU training machine, which has only torch/numpy/scipy. The layers below
are ~100 lines, and the tests check invertibility and the log-determinant against autograd Jacobians.

Convention: ``forward(x) -> (z, log|det dz/dx|)`` maps data (normalised boxes) to the base space
N(0, I); ``inverse(z)`` maps back.
"""

from __future__ import annotations

import math

import torch
from torch import nn

LOG_2PI = math.log(2.0 * math.pi)


def log_prob_from(z: torch.Tensor, log_det: torch.Tensor) -> torch.Tensor:
    """log p(x) from the flow's ``forward(x) = (z, log_det)``, standard-normal base: (B,)."""
    return -0.5 * (z.pow(2).sum(-1) + z.shape[-1] * LOG_2PI) + log_det


class AffineCoupling(nn.Module):
    """z_b = x_b * exp(s(x_a)) + t(x_a) on the dims where ``mask`` is 0; dims where it is 1 pass through."""

    def __init__(self, mask: torch.Tensor, hidden: int, hidden_layers: int) -> None:
        super().__init__()
        dim = int(mask.numel())
        keep = mask.bool()
        # Index buffers instead of boolean masks: boolean indexing forces a device-host sync on CUDA.
        self.register_buffer("idx_a", torch.nonzero(keep).flatten(), persistent=False)
        self.register_buffer("idx_b", torch.nonzero(~keep).flatten(), persistent=False)
        self.register_buffer("inv_perm", torch.argsort(torch.cat([self.idx_a, self.idx_b])), persistent=False)
        self.n_cond = int(keep.sum())
        layers: list[nn.Module] = []
        width = self.n_cond
        for _ in range(hidden_layers):
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        out = nn.Linear(width, 2 * (dim - self.n_cond))
        # Zero-initialised last layer: every coupling starts as the identity, which keeps early training stable.
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
        layers.append(out)
        self.net = nn.Sequential(*layers)
        self.scale_limit = nn.Parameter(torch.ones(dim - self.n_cond))

    def _params(self, x_a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, t = self.net(x_a).chunk(2, dim=-1)
        # Soft-bounded log-scale: tanh keeps exp(s) finite even when the net misbehaves.
        return self.scale_limit * torch.tanh(s), t

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x_a, x_b = x.index_select(1, self.idx_a), x.index_select(1, self.idx_b)
        s, t = self._params(x_a)
        z = torch.cat([x_a, x_b * torch.exp(s) + t], dim=1).index_select(1, self.inv_perm)
        return z, s.sum(dim=-1)

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        z_a, z_b = z.index_select(1, self.idx_a), z.index_select(1, self.idx_b)
        s, t = self._params(z_a)
        return torch.cat([z_a, (z_b - t) * torch.exp(-s)], dim=1).index_select(1, self.inv_perm)


class BatchNormBijection(nn.Module):
    """Batch normalisation as an invertible layer (RealNVP, sec. 3.7): batch statistics while training,
    running averages in eval mode; learnable log-scale and shift."""

    def __init__(self, dim: int, momentum: float = 0.05, eps: float = 1e-5) -> None:
        super().__init__()
        self.momentum = momentum
        self.eps = eps
        self.log_gamma = nn.Parameter(torch.zeros(dim))
        self.beta = nn.Parameter(torch.zeros(dim))
        self.register_buffer("running_mean", torch.zeros(dim))
        self.register_buffer("running_var", torch.ones(dim))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.training:
            if x.shape[0] < 2:
                raise ValueError("BatchNormBijection needs a batch of at least 2 in training mode")
            mean, var = x.mean(0), x.var(0, unbiased=False)
            with torch.no_grad():
                self.running_mean.lerp_(mean.detach(), self.momentum)
                self.running_var.lerp_(var.detach(), self.momentum)
        else:
            mean, var = self.running_mean, self.running_var
        x_hat = (x - mean) / torch.sqrt(var + self.eps)
        z = x_hat * torch.exp(self.log_gamma) + self.beta
        log_det = (self.log_gamma - 0.5 * torch.log(var + self.eps)).sum().expand(x.shape[0])
        return z, log_det

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        # Inversion uses the running statistics: it is only meaningful in eval mode.
        x_hat = (z - self.beta) * torch.exp(-self.log_gamma)
        return x_hat * torch.sqrt(self.running_var + self.eps) + self.running_mean


class RealNVP(nn.Module):
    """Stack of affine couplings with alternating masks and a batch-norm bijection after every
    ``batchnorm_every`` couplings (not after the last one).

    Args:
        dim: data dimension (24 for boxes).
        couplings: number of coupling layers.
        hidden: hidden width of each coupling network.
        hidden_layers: hidden layers of each coupling network.
        batchnorm_every: insert a batch norm after every this many couplings; 0 disables it.
    """

    def __init__(self, dim: int, couplings: int = 8, hidden: int = 512, hidden_layers: int = 2,
                 batchnorm_every: int = 2) -> None:
        super().__init__()
        if dim < 2:
            raise ValueError(f"RealNVP needs dim >= 2, got {dim}")
        self.dim = dim
        # Alternate which half of the dims (even / odd indices) is transformed.
        even = (torch.arange(dim) % 2 == 0).float()
        layers: list[nn.Module] = []
        for i in range(couplings):
            layers.append(AffineCoupling(even if i % 2 == 0 else 1.0 - even, hidden, hidden_layers))
            if batchnorm_every and (i + 1) % batchnorm_every == 0 and i + 1 < couplings:
                layers.append(BatchNormBijection(dim))
        self.layers = nn.ModuleList(layers)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Data -> base space; returns ``(z, log|det J|)`` with shapes (B, dim) and (B,)."""
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"RealNVP expects (B, {self.dim}), got {tuple(x.shape)}")
        log_det = x.new_zeros(x.shape[0])
        for layer in self.layers:
            x, ld = layer(x)
            log_det = log_det + ld
        return x, log_det

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        """Base space -> data (use in eval mode: batch norms invert with their running statistics)."""
        for layer in reversed(self.layers):
            z = layer.inverse(z)
        return z

    @torch.no_grad()
    def sample(self, num: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Draws ``num`` data samples (eval-mode statistics)."""
        z = torch.randn(num, self.dim, generator=generator).to(next(self.parameters()).device)
        return self.inverse(z)
