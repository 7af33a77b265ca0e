"""Independent PyTorch reference for the native denoisers (server/src/engine/nets/).

Diffuser's TemporalUnet (without attention) and the service's MLP denoiser in plain torch.nn
modules, whose state-dict names are the contract with the Rust side (relreward's weights load
here with ``load_state_dict(strict=True)`` and PyTorch's there). Module map: Diffuser's
building blocks (also used by ``reward_nets``), the two networks, ``item_shape`` (a manifest
space's item shape) and ``build`` (a network from a manifest's architecture and space).
tests/python/nets_reference.py drives it for server/tests/nets_vs_pytorch.rs.
"""

import math

import numpy as np
import torch
from torch import nn

# ---------------------------------------------------------------------------------------------
# Diffuser's building blocks


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.dim = dim

    def forward(self, t):
        half = self.dim // 2
        step = math.log(10000) / (half - 1)
        freqs = torch.exp(torch.arange(half, device=t.device) * -step)
        angles = t[:, None] * freqs[None, :]
        return torch.cat((angles.sin(), angles.cos()), dim=-1)


class AddUnitAxis(nn.Module):
    """[batch, channels, horizon] -> [batch, channels, 1, horizon] (Diffuser's Rearrange)."""

    def forward(self, x):
        return x.unsqueeze(2)


class DropUnitAxis(nn.Module):
    def forward(self, x):
        return x.squeeze(2)


class TrailingAxis(nn.Module):
    """[batch, channels] -> [batch, channels, 1], to broadcast over the horizon."""

    def forward(self, x):
        return x.unsqueeze(-1)


class Conv1dBlock(nn.Module):
    def __init__(self, in_channels, out_channels, kernel_size, n_groups=8):
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            AddUnitAxis(),
            nn.GroupNorm(n_groups, out_channels),
            DropUnitAxis(),
            nn.Mish(),
        )

    def forward(self, x):
        return self.block(x)


class ResidualTemporalBlock(nn.Module):
    def __init__(self, in_channels, out_channels, embed_dim, kernel_size=5):
        super().__init__()
        self.blocks = nn.ModuleList(
            [
                Conv1dBlock(in_channels, out_channels, kernel_size),
                Conv1dBlock(out_channels, out_channels, kernel_size),
            ]
        )
        self.time_mlp = nn.Sequential(nn.Mish(), nn.Linear(embed_dim, out_channels), TrailingAxis())
        if in_channels != out_channels:
            self.residual_conv = nn.Conv1d(in_channels, out_channels, 1)
        else:
            self.residual_conv = nn.Identity()

    def forward(self, x, t):
        out = self.blocks[0](x) + self.time_mlp(t)
        out = self.blocks[1](out)
        return out + self.residual_conv(x)


class Downsample1d(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.conv = nn.Conv1d(dim, dim, 3, 2, 1)

    def forward(self, x):
        return self.conv(x)


class Upsample1d(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.conv = nn.ConvTranspose1d(dim, dim, 4, 2, 1)

    def forward(self, x):
        return self.conv(x)


# ---------------------------------------------------------------------------------------------
# Networks


class TemporalUnet(nn.Module):
    """Diffuser's TemporalUnet, attention slots as identities (index 2 of each level)."""

    def __init__(self, transition_dim, dim=32, dim_mults=(1, 2, 4, 8)):
        super().__init__()
        dims = [transition_dim] + [dim * m for m in dim_mults]
        in_out = list(zip(dims[:-1], dims[1:]))
        levels = len(in_out)

        self.time_mlp = nn.Sequential(
            SinusoidalPosEmb(dim),
            nn.Linear(dim, dim * 4),
            nn.Mish(),
            nn.Linear(dim * 4, dim),
        )

        self.downs = nn.ModuleList()
        for index, (dim_in, dim_out) in enumerate(in_out):
            last = index >= levels - 1
            self.downs.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(dim_in, dim_out, embed_dim=dim),
                        ResidualTemporalBlock(dim_out, dim_out, embed_dim=dim),
                        nn.Identity(),
                        nn.Identity() if last else Downsample1d(dim_out),
                    ]
                )
            )

        mid_dim = dims[-1]
        self.mid_block1 = ResidualTemporalBlock(mid_dim, mid_dim, embed_dim=dim)
        self.mid_block2 = ResidualTemporalBlock(mid_dim, mid_dim, embed_dim=dim)

        # As in Diffuser: the loop runs over levels - 1 pairs, so its `last` test never fires
        # and every up level upsamples.
        self.ups = nn.ModuleList()
        for index, (dim_in, dim_out) in enumerate(reversed(in_out[1:])):
            last = index >= levels - 1
            self.ups.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(dim_out * 2, dim_in, embed_dim=dim),
                        ResidualTemporalBlock(dim_in, dim_in, embed_dim=dim),
                        nn.Identity(),
                        nn.Identity() if last else Upsample1d(dim_in),
                    ]
                )
            )

        self.final_conv = nn.Sequential(
            Conv1dBlock(dims[1], dim, kernel_size=5),
            nn.Conv1d(dim, transition_dim, 1),
        )

    def forward(self, x, time):
        x = x.permute(0, 2, 1)
        t = self.time_mlp(time)
        skips = []
        for resnet, resnet2, attn, downsample in self.downs:
            x = resnet(x, t)
            x = resnet2(x, t)
            x = attn(x)
            skips.append(x)
            x = downsample(x)
        x = self.mid_block1(x, t)
        x = self.mid_block2(x, t)
        for resnet, resnet2, attn, upsample in self.ups:
            x = torch.cat((x, skips.pop()), dim=1)
            x = resnet(x, t)
            x = resnet2(x, t)
            x = attn(x)
            x = upsample(x)
        x = self.final_conv(x)
        return x.permute(0, 2, 1)


class MlpDenoiser(nn.Module):
    TIME_DIM = 32

    def __init__(self, shape, hidden):
        super().__init__()
        self.shape = tuple(shape)
        features = int(np.prod(shape))
        self.time_mlp = nn.Sequential(
            SinusoidalPosEmb(self.TIME_DIM),
            nn.Linear(self.TIME_DIM, 4 * self.TIME_DIM),
            nn.Mish(),
            nn.Linear(4 * self.TIME_DIM, self.TIME_DIM),
        )
        layers, width = [], features + self.TIME_DIM
        for h in hidden:
            layers += [nn.Linear(width, h), nn.Mish()]
            width = h
        layers.append(nn.Linear(width, features))
        self.net = nn.Sequential(*layers)

    def forward(self, x, time):
        flat = x.reshape(x.shape[0], -1)
        out = self.net(torch.cat((flat, self.time_mlp(time)), dim=1))
        return out.reshape(x.shape)


def item_shape(space):
    if space["kind"] == "trajectory":
        return [space["horizon"], space["action_dim"] + space["obs_dim"]]
    return list(space["shape"])


def build(architecture, space):
    shape = item_shape(space)
    if architecture["kind"] == "temporal_unet":
        return TemporalUnet(shape[1], dim=architecture["dim"], dim_mults=tuple(architecture["dim_mults"]))
    if architecture["kind"] == "mlp":
        return MlpDenoiser(shape, architecture["hidden"])
    raise ValueError(f"unknown architecture {architecture['kind']}")
