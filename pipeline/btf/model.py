"""The Neural BTF autoencoder (Rainer et al. 2019; PAPERS.md A).

Encoder: ``blocks`` x [conv1d (kernel 3, stride 1, padding 1) -> ReLU -> max-pool
(kernel 3, stride 3) -> batch-norm] over the 3 RGB channels of an ABRDF laid out along its
N directions, then a fully connected layer to an 8-dimensional latent. The paper gives the
block order but not the activation; a ReLU after each convolution is the usual choice.
ReLU and max-pool commute (the maximum of three values is monotone in each), so each block
pools first and applies the ReLU to a third as many values: the same values and gradients.
``Encoder.forward`` picks how the blocks run (see there); ``Encoder.reference`` is the plain
1-D form of the same layers.

Decoder: 12 -> 106 -> 106 -> 106 -> 3 with ReLU, fed the latent plus the light and view
directions in stereographic coordinates (eq. 7-9, :mod:`pipeline.btf.stereographic`). Its
24,383 float32 parameters are the 97,532 bytes of the paper's Table 1.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pipeline.btf.fast.encoder_step import encode_for_training
from pipeline.core.errors import ConfigError

LATENT_DIM = 8


class MaxPool3(nn.Module):
    """``nn.MaxPool1d(kernel_size=3, stride=3)`` as a maximum over the last axis of a
    (..., L // 3, 3) view: the same values and gradients (the first maximum of each triple
    gets the gradient). Faster than ``MaxPool1d``'s CPU kernel, which also
    computes the indices (docs/performance.md)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = x.shape[-1] // 3
        return x[..., : 3 * n].unflatten(-1, (n, 3)).max(-1).values


class Encoder(nn.Module):
    """ABRDF (batch, 3, N) -> latent (batch, 8)."""

    def __init__(
        self, n_directions: int, channels: Sequence[int] = (16, 32, 64), latent: int = LATENT_DIM
    ):
        super().__init__()
        channels = list(channels)
        length = n_directions // 3 ** len(channels)
        if length < 1:
            raise ConfigError(
                f"btf.network.encoder_channels has {len(channels)} blocks, each pooling by 3, but "
                f"an ABRDF has only N={n_directions} directions: use at most "
                f"{max(int(np.log(max(n_directions, 1)) / np.log(3)), 0)} blocks"
            )
        layers: list[nn.Module] = []
        previous = 3
        for width in channels:
            layers += [
                nn.Conv1d(previous, width, kernel_size=3, stride=1, padding=1),
                MaxPool3(),
                nn.ReLU(),
                nn.BatchNorm1d(width),
            ]
            previous = width
        self.features = nn.Sequential(*layers)
        self.fc = nn.Linear(previous * length, latent)

    def forward(self, abrdf: torch.Tensor) -> torch.Tensor:
        """ABRDFs (batch, 3, N) -> latents (batch, 8). Training on the CPU with gradients
        takes :func:`pipeline.btf.fast.encoder_step.encode_for_training` (the blocks chunk by
        chunk, forward and backward written out; faster, docs/performance.md); anything else
        :meth:`forward_layers`. Both compute :meth:`reference`'s function and gradients, up
        to rounding (``tests/test_encoder_speed.py``)."""
        if self.training and torch.is_grad_enabled() and abrdf.device.type == "cpu":
            blocks = list(self.features)
            return encode_for_training(blocks[0::4], blocks[3::4], self.fc, abrdf)
        return self.forward_layers(abrdf)

    def forward_layers(self, abrdf: torch.Tensor) -> torch.Tensor:
        """The blocks on (batch, C, 1, L) tensors, convolved and pooled in channels-last
        memory (which an input handed over as ``x.permute(0, 2, 1)`` already is): oneDNN's
        2-D convolution and torch's ``max_pool2d``, vectorized over the channels. Batch-norm
        runs on the plain layout: the channels-last one gave parameter gradients far from
        float64 in ``tests/test_btf_model.py``. :meth:`reference`'s values up to rounding,
        and faster (docs/performance.md)."""
        h = abrdf.unsqueeze(2)
        blocks = list(self.features)
        for conv, batch_norm in zip(blocks[0::4], blocks[3::4], strict=True):
            h = h.contiguous(memory_format=torch.channels_last)
            h = F.conv2d(h, conv.weight.unsqueeze(2), conv.bias, padding=(0, 1))
            h = F.max_pool2d(h, (1, 3), (1, 3)).relu()
            h = _batch_norm(batch_norm, h.contiguous())
        return self.fc(h.squeeze(2).flatten(1))  # the plain layout: flatten is a view

    def reference(self, abrdf: torch.Tensor) -> torch.Tensor:
        """The layers applied one after another to (batch, C, L) tensors."""
        return self.fc(self.features(abrdf).flatten(1))


def _batch_norm(module: nn.BatchNorm1d, x: torch.Tensor) -> torch.Tensor:
    """``module`` applied to a tensor of any layout with channels on axis 1, as
    ``nn.BatchNorm1d.forward`` would (which refuses 4-D input): in training, the batch
    statistics, the running averages' update and ``num_batches_tracked``."""
    factor = 0.0 if module.momentum is None else module.momentum
    if module.training and module.track_running_stats:
        module.num_batches_tracked.add_(1)
        if module.momentum is None:  # a cumulative moving average
            factor = 1.0 / float(module.num_batches_tracked)
    use_batch = module.training or module.running_mean is None
    track = not module.training or module.track_running_stats
    mean, var = (module.running_mean, module.running_var) if track else (None, None)
    return F.batch_norm(x, mean, var, module.weight, module.bias, use_batch, factor, module.eps)


class Decoder(nn.Module):
    """(latent 8 + light 2 + view 2) -> RGB, fully connected with ReLU."""

    def __init__(self, latent: int = LATENT_DIM, hidden: int = 106, layers: int = 3):
        super().__init__()
        sizes = [latent + 4] + [hidden] * layers
        modules: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:], strict=True):
            modules += [nn.Linear(a, b), nn.ReLU()]
        modules.append(nn.Linear(sizes[-1], 3))
        self.net = nn.Sequential(*modules)
        self.latent = latent

    def forward(self, latents: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """latents (q, 8), directions (q, 4) stereographic -> (q, 3)."""
        return self.net(torch.cat([latents, directions], dim=1))

    def decode_grid(self, latents: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """Decode every latent at every direction: (m, 8) x (n, 4) -> (m, n, 3).

        The first layer is split into its latent and direction parts so that each is
        multiplied once, not once per (texel, direction) pair.
        """
        first = self.net[0]
        w_latent, w_dir = first.weight[:, : self.latent], first.weight[:, self.latent :]
        hidden = (latents @ w_latent.T)[:, None, :] + (directions @ w_dir.T + first.bias)[None]
        out = self.net[1:](hidden.reshape(-1, hidden.shape[-1]))
        return out.reshape(latents.shape[0], directions.shape[0], 3)


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def load_decoder(path) -> Decoder:
    """A trained decoder from the ``decoder.pt`` state dict a train stage wrote, its latent
    size (``btf.network.latent``) read from the first layer's inputs (latent + 4)."""
    state = torch.load(path, weights_only=True)
    weights = [key for key in state if key.endswith(".weight")]
    hidden, inputs = state["net.0.weight"].shape
    decoder = Decoder(latent=inputs - 4, hidden=hidden, layers=len(weights) - 1)
    decoder.load_state_dict(state)
    return decoder.eval()
