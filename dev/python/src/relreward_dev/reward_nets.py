"""Independent PyTorch reference for the relative reward networks (server/src/engine/nets/reward.rs).

The windowed MLP, Diffuser's ValueFunction, the strided 2D conv encoder and the flat MLP in
plain torch.nn modules, whose state-dict names are the contract with the Rust side. Module
map: ``time_mlp`` / ``mlp_layers`` (shared pieces), one class per architecture, ``build`` (a
network from a reward manifest's architecture and the item shape).
tests/python/reward_nets_reference.py drives it for server/tests/reward_nets_vs_pytorch.rs; the
reference gRPC servers (bench/reference/) and the locomotion probes use it as rho_theta.
"""

import torch
from torch import nn

from relreward_dev.nets import Downsample1d, ResidualTemporalBlock, SinusoidalPosEmb

MLP_TIME_DIM = 32


def time_mlp(dim):
    return nn.Sequential(SinusoidalPosEmb(dim), nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))


def mlp_layers(features, hidden):
    layers, width = [], features + MLP_TIME_DIM
    for h in hidden:
        layers += [nn.Linear(width, h), nn.Mish()]
        width = h
    layers.append(nn.Linear(width, 1))
    return nn.Sequential(*layers)


class WindowedMlp(nn.Module):
    def __init__(self, item_shape, window, hidden):
        super().__init__()
        self.horizon, self.transition_dim = item_shape
        self.window = window
        self.time_mlp = time_mlp(MLP_TIME_DIM)
        self.net = mlp_layers(window * self.transition_dim, hidden)

    def score(self, windows, time):
        """windows [B, N, h * D] -> [B, N]."""
        t = self.time_mlp(time)[:, None, :].expand(-1, windows.shape[1], -1)
        return self.net(torch.cat((windows, t), dim=-1)).squeeze(-1)

    def per_window(self, x, time):
        b = x.shape[0]
        return self.score(x.reshape(b, self.horizon // self.window, self.window * self.transition_dim), time)

    def per_step(self, x, time):
        b = x.shape[0]
        padded = torch.cat([x] + [x[:, -1:, :]] * (self.window - 1), dim=1)
        windows = torch.stack([padded[:, k : k + self.window, :] for k in range(self.horizon)], dim=1)
        return self.score(windows.reshape(b, self.horizon, self.window * self.transition_dim), time)

    def forward(self, x, time):
        return self.per_window(x, time).mean(dim=1)


class ValueFunction(nn.Module):
    """Diffuser's ValueFunction with widths = [dim * m for m in dim_mults]; fc from the actual
    length after the downsamplings (equal to Diffuser's bookkeeping on valid horizons)."""

    def __init__(self, item_shape, widths):
        super().__init__()
        horizon, transition_dim = item_shape
        time_dim = widths[0]
        dims = [transition_dim, *widths]
        self.time_mlp = time_mlp(time_dim)
        self.blocks = nn.ModuleList()
        for dim_in, dim_out in zip(dims[:-1], dims[1:]):
            self.blocks.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(dim_in, dim_out, embed_dim=time_dim),
                        ResidualTemporalBlock(dim_out, dim_out, embed_dim=time_dim),
                        Downsample1d(dim_out),
                    ]
                )
            )
        mid, mid2, mid3 = dims[-1], dims[-1] // 2, dims[-1] // 4
        self.mid_block1 = ResidualTemporalBlock(mid, mid2, embed_dim=time_dim)
        self.mid_down1 = Downsample1d(mid2)
        self.mid_block2 = ResidualTemporalBlock(mid2, mid3, embed_dim=time_dim)
        self.mid_down2 = Downsample1d(mid3)
        length = horizon
        for _ in range(len(widths) + 2):
            length = (length - 1) // 2 + 1  # Conv1d(k=3, s=2, p=1)
        fc = mid3 * length
        self.final_block = nn.Sequential(nn.Linear(fc + time_dim, fc // 2), nn.Mish(), nn.Linear(fc // 2, 1))

    def forward(self, x, time):
        x = x.permute(0, 2, 1)
        t = self.time_mlp(time)
        for resnet, resnet2, downsample in self.blocks:
            x = downsample(resnet2(resnet(x, t), t))
        x = self.mid_down1(self.mid_block1(x, t))
        x = self.mid_down2(self.mid_block2(x, t))
        x = x.reshape(len(x), -1)
        return self.final_block(torch.cat([x, t], dim=-1)).squeeze(-1)


class EncoderBlock(nn.Module):
    def __init__(self, dim_in, dim_out, time_dim):
        super().__init__()
        self.conv = nn.Conv2d(dim_in, dim_out, 3, stride=2, padding=1)
        self.norm = nn.GroupNorm(8, dim_out)
        self.time_mlp = nn.Sequential(nn.Mish(), nn.Linear(time_dim, dim_out))

    def forward(self, x, t):
        h = nn.functional.mish(self.norm(self.conv(x)))
        return h + self.time_mlp(t)[:, :, None, None]


class ConvEncoder(nn.Module):
    def __init__(self, item_shape, widths):
        super().__init__()
        channels = item_shape[0]
        time_dim = widths[0]
        dims = [channels, *widths]
        self.time_mlp = time_mlp(time_dim)
        self.blocks = nn.ModuleList(EncoderBlock(a, b, time_dim) for a, b in zip(dims[:-1], dims[1:]))
        last = widths[-1]
        self.final_block = nn.Sequential(nn.Linear(last + time_dim, last // 2), nn.Mish(), nn.Linear(last // 2, 1))

    def forward(self, x, time):
        t = self.time_mlp(time)
        for block in self.blocks:
            x = block(x, t)
        pooled = x.mean(dim=(2, 3))
        return self.final_block(torch.cat([pooled, t], dim=-1)).squeeze(-1)


class Mlp(nn.Module):
    def __init__(self, item_shape, hidden):
        super().__init__()
        features = 1
        for d in item_shape:
            features *= d
        self.time_mlp = time_mlp(MLP_TIME_DIM)
        self.net = mlp_layers(features, hidden)

    def forward(self, x, time):
        flat = x.reshape(x.shape[0], -1)
        return self.net(torch.cat((flat, self.time_mlp(time)), dim=-1)).squeeze(-1)


def build(architecture, item_shape):
    kind = architecture["kind"]
    if kind == "windowed_mlp":
        return WindowedMlp(item_shape, architecture["window"], architecture["hidden"])
    if kind == "value_function":
        return ValueFunction(item_shape, architecture["widths"])
    if kind == "conv_encoder":
        return ConvEncoder(item_shape, architecture["widths"])
    if kind == "mlp":
        return Mlp(item_shape, architecture["hidden"])
    raise ValueError(f"unknown reward architecture {kind}")
