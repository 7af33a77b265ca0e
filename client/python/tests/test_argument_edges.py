"""The client at its edges: a RewardGuide that
recovers after its gradient stream fails (a server restart), ``n < 1`` and a mistyped
``units`` refused as InvalidInput naming the argument, no orphan future left by an
AsyncGradientStream request refused locally, ``env_weight`` of any real number type, a
non-string endpoint refused naming it, and torch tensors that require grad accepted as inputs.
(The relabelled Minari directory's ``dataset_id`` is in test_relabel.py.)

Tests that need no server use a port nothing listens on: the refusal must come before any
connection is tried."""

from __future__ import annotations

import asyncio
import gc
import socket
import time

import numpy as np
import pytest

import relreward
from relreward import _common
from relreward.guide import RewardGuide

from conftest import start_server


def dead_endpoint() -> str:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{s.getsockname()[1]}"


# ------------------------------------------------------------------------------------------
# The guide opens a new stream after its stream failed (it used to raise Unavailable forever).


HORIZON, WIDTH, T = 4, 3, 10


def byo_reward(path) -> str:
    """A scripted rho(x, t) -> [B] over items [HORIZON, WIDTH], saved at ``path``."""
    import torch

    class Rho(torch.nn.Module):
        def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return (x * x).flatten(1).sum(1) + t.float()

    torch.jit.script(Rho()).save(str(path))
    return str(path)


def test_guide_recovers_after_its_stream_failed_on_a_server_restart(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        listen = f"127.0.0.1:{s.getsockname()[1]}"
    env = {"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true"}
    servers = [start_server(tmp_path / "data", env=env, listen=listen)]
    try:
        with relreward.Client(listen) as client:
            client.upload_reward(byo_reward(tmp_path / "rho.pt"), "rho", {
                "signature": "rho", "n_timesteps": T, "normalizer": {"kind": "identity"},
                "space": {"kind": "trajectory", "horizon": HORIZON, "action_dim": 1, "obs_dim": WIDTH - 1}})
            x = np.ones((2, HORIZON, WIDTH), np.float32)
            with RewardGuide(client, "rho") as guide:
                y, grad = guide.gradients(x, None, 0)
                np.testing.assert_allclose(y, [12.0, 12.0])
                np.testing.assert_allclose(grad, 2 * x)
                servers[0].stop()  # SIGKILL: the stream's call fails
                with pytest.raises(relreward.RelrewardError):
                    guide.gradients(x, None, 0)  # the failed call itself raises
                servers.append(start_server(tmp_path / "data", env=env, listen=listen))
                # Each later call opens a new stream; the channel may need a moment to reconnect.
                deadline = time.monotonic() + 10
                while True:
                    try:
                        y, grad = guide.gradients(x, None, np.array([1, 2]))
                        break
                    except relreward.Unavailable:
                        if time.monotonic() > deadline:
                            raise
                        time.sleep(0.1)
                np.testing.assert_allclose(y, [13.0, 14.0])
                np.testing.assert_allclose(grad, 2 * x)
    finally:
        for s in servers:
            s.stop()


def test_guide_keeps_its_stream_after_a_request_refused_locally():
    with relreward.Client(dead_endpoint()) as client:
        guide = RewardGuide(client, "m")
        stream = guide.stream
        with pytest.raises(relreward.InvalidInput, match="t: -1 is negative"):
            guide.gradients(np.zeros((1, 4, 3), np.float32), None, -1)
        assert guide.stream is stream  # not a failure of the stream: nothing to reopen
        guide.close()


# ------------------------------------------------------------------------------------------
# n < 1 and a mistyped units are refused as InvalidInput naming the argument.


@pytest.mark.parametrize("n", [0, np.int64(0)])
def test_sample_refuses_n_below_one(n):
    with relreward.Client(dead_endpoint()) as client:
        with pytest.raises(relreward.InvalidInput, match="n: 0 is below 1"):
            client.sample("m", n=n)

    async def main():
        async with relreward.AsyncClient(dead_endpoint()) as ac:
            with pytest.raises(relreward.InvalidInput, match="n: 0 is below 1"):
                await ac.sample("m", n=n)

    asyncio.run(main())


def test_mistyped_units_are_invalid_input_naming_the_argument():
    x = np.zeros((1, 4, 3), np.float32)
    with relreward.Client(dead_endpoint()) as client:
        for call, says in ((lambda: client.score("m", x, units="Raw"), "units: 'Raw'"),
                           (lambda: client.gradient("m", x, 0, units="Normalized"), "units: 'Normalized'"),
                           (lambda: client.gradient("m", x, 0, gradient_units="row"), "gradient_units: 'row'"),
                           (lambda: client.gradient("m", x, 0, units=None), "units: None"),
                           (lambda: client.sample("m", units="RAW"), "units: 'RAW'")):
            with pytest.raises(relreward.InvalidInput, match=says) as e:
                call()
            assert "expected 'raw' or 'normalized'" in str(e.value)
        with client.gradient_stream("m", gradient_units="normalised") as stream:
            with pytest.raises(relreward.InvalidInput, match="gradient_units: 'normalised'"):
                stream.submit(x, 0)


# ------------------------------------------------------------------------------------------
# An AsyncGradientStream request refused locally leaves no future behind.


def test_async_stream_refusal_leaves_no_orphan_future():
    seen: list[dict] = []

    async def main():
        asyncio.get_running_loop().set_exception_handler(lambda _loop, context: seen.append(context))
        async with relreward.AsyncClient(dead_endpoint()) as ac:
            async with ac.gradient_stream("m") as stream:
                for kwargs in ({"t": -1}, {"t": 0, "units": "Raw"}):
                    with pytest.raises(relreward.InvalidInput):
                        await stream.submit(np.zeros((1, 4, 3), np.float32), **kwargs)
                assert stream._pending == {}
                await asyncio.sleep(0.2)  # the reader finds the endpoint dead meanwhile
            del stream
        gc.collect()
        await asyncio.sleep(0)

    asyncio.run(main())
    assert [c.get("message") for c in seen] == []


# ------------------------------------------------------------------------------------------
# env_weight of any real number type; a non-string endpoint named.


def test_env_weight_takes_any_real_number():
    from relreward.rl import _weight

    for ok, value in ((np.float32(0.5), 0.5), (np.float64(0.25), 0.25), (np.int64(2), 2.0), (1, 1.0), (0.5, 0.5)):
        got = _weight(ok)
        assert type(got) is float and got == value
    for bad in (float("nan"), np.float32("inf"), -np.inf, True, np.bool_(True), "0.5", None, 1j):
        with pytest.raises(relreward.InvalidInput, match="env_weight: "):
            _weight(bad)


@pytest.mark.parametrize("endpoint", [None, 50051, b"127.0.0.1:50051", ""])
def test_a_non_string_endpoint_is_refused_naming_it(endpoint):
    with pytest.raises(relreward.InvalidInput, match="endpoint: "):
        relreward.Client(endpoint)  # type: ignore[arg-type]
    with pytest.raises(relreward.InvalidInput, match="endpoint: "):
        relreward.AsyncClient(endpoint)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------
# Torch tensors that require grad are inputs as any other array-like.


def test_request_builders_take_tensors_that_require_grad():
    import torch

    x = torch.arange(24, dtype=torch.float32).reshape(2, 4, 3).requires_grad_(True)
    expect = x.detach().numpy()
    req = _common.score_request("m", x, 0, "raw", False, False)
    np.testing.assert_array_equal(np.frombuffer(req.x.data, np.float32).reshape(2, 4, 3), expect)
    req = _common.gradient_request("m", x * 2, 0, None, "raw", "raw", None)
    np.testing.assert_array_equal(np.frombuffer(req.x.data, np.float32).reshape(2, 4, 3), 2 * expect)
    state = torch.ones(3, requires_grad=True)
    req = _common.sample_request("m", None, 0.0, 1, None, None, None, False, {0: state}, "raw", 0)
    assert np.frombuffer(req.conditions[0].state.data, np.float32).tolist() == [1.0, 1.0, 1.0]
    # Prompt embeddings and images for an autoencoder go through the same conversion.
    from relreward import _tensor
    from relreward.specs import prompts_message
    assert np.frombuffer(prompts_message("prompts", state * 2).embeddings.data, np.float32).tolist() == [2.0] * 3
    np.testing.assert_array_equal(_tensor.as_f32(x), expect)
    # And a dataset dict of tensors.
    from relreward.datasets import trajectories
    arrays = dict(trajectories({"observations": x.reshape(8, 3), "actions": torch.zeros(8, 1)}).arrays)
    np.testing.assert_array_equal(arrays["observations"], expect.reshape(8, 3))


def test_score_and_gradient_take_tensors_that_require_grad(client, tiny):
    import torch

    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, tiny.horizon, tiny.transition_dim)).astype(np.float32)
    xt = torch.from_numpy(x.copy()).requires_grad_(True)
    np.testing.assert_allclose(client.score(tiny.reward, xt, 1).rewards, client.score(tiny.reward, x, 1).rewards,
                               rtol=1e-6)
    got, want = client.gradient(tiny.reward, xt, 1), client.gradient(tiny.reward, x, 1)
    np.testing.assert_allclose(got.gradient, want.gradient, rtol=1e-6, atol=1e-7)
    with client.gradient_stream(tiny.reward) as stream:
        np.testing.assert_allclose(stream.gradient(xt, 1).rewards, want.rewards, rtol=1e-6)
