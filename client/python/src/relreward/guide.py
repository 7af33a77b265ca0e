"""A drop-in value guide for Diffuser-style planners, backed by a relreward reward model.

Diffuser's guided sampler (``n_step_guided_p_sample``) calls ``y, grad = guide.gradients(x,
cond, t)`` at every denoising step, with ``x`` the batch of noisy plans ``[B, H, D]`` in
normalized units (rows ``[action | observation]``) and ``t`` the step of each plan ``[B]``;
it then adds ``scale * grad`` to ``x``. :class:`RewardGuide` has that interface, so swapping a
trained ``ValueGuide(value_function)`` for a relreward reward is one line::

    guide = RewardGuide(relreward.Client("127.0.0.1:50051"), "maze-reward")

It keeps one GradientStream open (the request of every step goes over it), accepts numpy
arrays or torch tensors and returns the same kind (a torch tensor on the input's device and
dtype). Units are normalized on both sides, as in Diffuser. When the stream's call fails as a
whole (the server restarted, the connection dropped), that step raises the failure and the
guide drops the stream, so the next step opens a new one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from relreward import _tensor
from relreward.client import Client, GradientStream
from relreward.errors import RelrewardError


class RewardGuide:
    """``guide(x, cond, t)`` -> rho ``[B]``; ``guide.gradients(x, cond, t)`` -> ``(rho [B],
    grad_x rho [B, H, D])``, both in normalized units, from reward model ``model``.

    ``omega`` multiplies the gradient on the server (leave it unset when the sampler applies
    its own ``scale``); ``scale_by_posterior_variance_of`` names the base diffusion model whose
    posterior variance multiplies the gradient (then do not also set Diffuser's
    ``scale_grad_by_std``). ``cond`` is accepted and ignored (the planner inpaints it).
    """

    def __init__(self, client: Client, model: str, *, omega: float | None = None,
                 scale_by_posterior_variance_of: str | None = None) -> None:
        self.client = client
        self.model = model
        self.omega = omega
        self.scale_by_posterior_variance_of = scale_by_posterior_variance_of
        self._stream: GradientStream | None = None

    @property
    def stream(self) -> GradientStream:
        """The GradientStream the guide uses (opened on first use)."""
        if self._stream is None:
            self._stream = self.client.gradient_stream(
                self.model, omega=self.omega, units="normalized", gradient_units="normalized",
                scale_by_posterior_variance_of=self.scale_by_posterior_variance_of)
        return self._stream

    @staticmethod
    def _numpy(x: Any) -> np.ndarray:
        if _tensor.is_torch(x):
            return x.detach().to("cpu").float().numpy()
        return np.asarray(x)

    def gradients(self, x: Any, cond: Any = None, t: Any = 0, *args: Any) -> tuple[Any, Any]:
        """(rho ``[B]``, grad_x rho ``[B, H, D]``) at the noisy plans ``x`` ``[B, H, D]`` and
        steps ``t`` (an int or ``[B]``); torch in, torch out (on ``x``'s device and dtype).
        Both are writable arrays the caller owns (unlike the client's read-only views), so a
        sampler may edit them in place."""
        stream = self.stream
        try:
            result = stream.gradient(self._numpy(x), self._numpy(t).astype(np.int64).reshape(-1)
                                     if not isinstance(t, (int, np.integer)) else int(t))
        except RelrewardError:
            # A failure of the whole call stays with its stream (every later request on it
            # raises it): drop that stream so the next step opens a new one. A request refused
            # on its own (a bad t, a server's per-request error) leaves the stream as it is.
            if stream.failed is not None and self._stream is stream:
                self.close()
            raise
        # The client's arrays are read-only views of the response bytes; Diffuser's sampler edits
        # what the guide returns in place (``grad[t < t_stopgrad] = 0``), so hand out owned,
        # writable copies (torch.from_numpy also warns on a read-only array).
        rewards, gradient = result.rewards.copy(), result.gradient.copy()
        if _tensor.is_torch(x):
            import torch

            y = torch.from_numpy(rewards).to(device=x.device, dtype=x.dtype)
            grad = torch.from_numpy(gradient).to(device=x.device, dtype=x.dtype)
            return y, grad
        return rewards, gradient

    def __call__(self, x: Any, cond: Any = None, t: Any = 0, *args: Any) -> Any:
        """rho ``[B]`` at ``x`` and ``t`` (the value Diffuser's guide returns)."""
        return self.gradients(x, cond, t)[0]

    def close(self) -> None:
        """Closes the stream (a new one opens on the next call; the guide does this itself
        after the stream's call failed)."""
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def __enter__(self) -> "RewardGuide":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
