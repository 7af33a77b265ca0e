"""relreward's seeded generator (server/src/engine/rng.rs) in Python, so that a test can replay a
server run's noise draw for draw: SplitMix64 states, 53-bit uniforms, Box-Muller pairs in float64
(both outputs used, an odd last value takes a whole pair), cast to float32.

Module map: ``RelrewardRng`` (``uniform``, ``randn``).
"""

from __future__ import annotations

import math

import numpy as np
import torch


class RelrewardRng:
    """The server's ``Rng`` seeded with ``seed``: the same stream of uniforms and normals."""

    MASK = (1 << 64) - 1
    GAMMA = 0x9E3779B97F4A7C15

    def __init__(self, seed: int) -> None:
        self.state = seed & self.MASK

    def next_u64(self) -> int:
        self.state = (self.state + self.GAMMA) & self.MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & self.MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & self.MASK
        return z ^ (z >> 31)

    def uniform(self) -> float:
        return (self.next_u64() >> 11) * (1.0 / (1 << 53))

    def randn(self, shape: tuple[int, ...]) -> torch.Tensor:
        n = math.prod(shape)
        out = np.empty(n, np.float32)
        for i in range(0, n, 2):
            r = math.sqrt(-2.0 * math.log(1.0 - self.uniform()))
            theta = math.tau * self.uniform()
            out[i] = r * math.cos(theta)
            if i + 1 < n:
                out[i + 1] = r * math.sin(theta)
        return torch.from_numpy(out.reshape(shape))
