"""Score, Gradient, GradientStream and Sample against the server, checked against the Rust CLI."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import relreward


def plans(tiny, b: int, seed: int = 0) -> np.ndarray:
    """Raw-unit plans [B, H, D] near the tiny dataset's range."""
    return np.random.default_rng(seed).uniform(-1, 1, (b, tiny.horizon, tiny.transition_dim)).astype(np.float32)


def test_score_matches_the_cli(client, server, tiny, tmp_path):
    x = plans(tiny, 5)
    np.savez(tmp_path / "x.npz", x=x)
    server.cli("score", "--model", tiny.reward, "--input", str(tmp_path / "x.npz"), "--t", "2", "--per-window",
               "--per-step", "--out", str(tmp_path / "s.npz"))
    cli = np.load(tmp_path / "s.npz")
    got = client.score(tiny.reward, x, t=2, per_window=True, per_step=True)
    assert got.rewards.dtype == np.float32 and got.rewards.shape == (5,)
    np.testing.assert_array_equal(got.rewards, cli["reward"])
    np.testing.assert_array_equal(got.per_window, cli["per_window"])
    assert got.per_window.shape == (5, tiny.horizon // 4) and got.per_step.shape == (5, tiny.horizon)
    assert client.score(tiny.reward, x).per_window is None


def test_gradient_matches_the_cli(client, server, tiny, tmp_path):
    x = plans(tiny, 4, seed=1)
    np.savez(tmp_path / "x.npz", x=x)
    server.cli("grad", "--model", tiny.reward, "--input", str(tmp_path / "x.npz"), "--t", "7", "--omega", "0.5",
               "--scale-by-posterior-variance-of", tiny.base, "--out", str(tmp_path / "g.npz"))
    cli = np.load(tmp_path / "g.npz")
    grad, rho = client.gradient(tiny.reward, x, t=7, omega=0.5, scale_by_posterior_variance_of=tiny.base)
    assert grad.shape == x.shape and grad.dtype == np.float32 and not grad.flags.writeable
    np.testing.assert_array_equal(grad, cli["grad_x"])
    np.testing.assert_array_equal(rho, cli["reward"])


def test_gradient_is_the_derivative_of_score(client, tiny):
    x = plans(tiny, 1, seed=2).astype(np.float64)
    g = client.gradient(tiny.reward, x, t=0).gradient.astype(np.float64)
    h = 1e-2
    direction = g / np.linalg.norm(g)
    up = client.score(tiny.reward, x + h * direction).rewards[0]
    down = client.score(tiny.reward, x - h * direction).rewards[0]
    assert (up - down) / (2 * h) == pytest.approx(np.linalg.norm(g), rel=0.1)


def test_per_item_t_and_units(client, tiny):
    x = plans(tiny, 3, seed=3)
    per_item = client.gradient(tiny.reward, x, t=[0, 5, 9])
    for i, t in enumerate([0, 5, 9]):
        one = client.gradient(tiny.reward, x[i:i + 1], t=t)
        np.testing.assert_allclose(per_item.gradient[i], one.gradient[0], rtol=1e-5, atol=1e-6)
    norm = client.gradient(tiny.reward, x, t=1, units="normalized")
    assert norm.gradient.shape == x.shape


def test_errors_carry_code_and_message(client, tiny):
    x = plans(tiny, 1)
    with pytest.raises(relreward.InvalidArgument) as e:
        client.gradient(tiny.reward, x, t=100)
    assert "t" in e.value.message and e.value.code.name == "INVALID_ARGUMENT"
    assert str(e.value).startswith("INVALID_ARGUMENT: ")
    with pytest.raises(relreward.NotFound):
        client.score("no-such-model", x)
    with pytest.raises(relreward.InvalidArgument):
        client.score(tiny.reward, np.zeros((1, 3, 3), np.float32))
    with pytest.raises(relreward.InvalidArgument, match="omega"):
        client.gradient(tiny.reward, x, t=0, omega=1e9)


def test_gradient_stream_in_order_pipelined_and_per_request_errors(client, tiny):
    x = plans(tiny, 2, seed=4)
    expected = [client.gradient(tiny.reward, x, t=t) for t in range(tiny.n_timesteps)]
    with client.gradient_stream(tiny.reward) as stream:
        for t in range(tiny.n_timesteps):
            g, rho = stream.gradient(x, t)
            np.testing.assert_array_equal(g, expected[t].gradient)
            np.testing.assert_array_equal(rho, expected[t].rewards)
        pending = [stream.submit(x, t) for t in range(tiny.n_timesteps)]  # all in flight
        for t, p in reversed(list(enumerate(pending))):
            # In flight together, they may share one batched forward pass: float32 rounding.
            np.testing.assert_allclose(p.result().gradient, expected[t].gradient, rtol=1e-5, atol=1e-8)
        bad = stream.submit(x, 100)
        good = stream.submit(x, 1, omega=2.0)
        with pytest.raises(relreward.InvalidArgument):
            bad.result()
        np.testing.assert_allclose(good.result().gradient, 2 * expected[1].gradient, rtol=1e-5, atol=1e-8)


def test_sample_matches_the_cli(client, server, tiny, tmp_path):
    server.cli("sample", "--base", tiny.base, "--reward", tiny.reward, "--scale", "0.1", "--n", "3", "--seed", "5",
               "--out", str(tmp_path / "s.npz"))
    cli = np.load(tmp_path / "s.npz")
    got = client.sample(tiny.base, reward_model=tiny.reward, omega=0.1, n=3, seed=5)
    assert got.x.shape == (3, tiny.horizon, tiny.transition_dim)
    np.testing.assert_array_equal(got.x, cli["x"])
    np.testing.assert_array_equal(got.x_normalized, cli["x_normalized"])
    np.testing.assert_allclose(got.rewards, cli["reward"], rtol=1e-6)
    plain = list(client.sample_iter(tiny.base, n=2, seed=1))
    assert sorted(s.index for s in plain) == [0, 1] and all(s.reward is None for s in plain)


def test_async_client(server, tiny):
    async def main():
        async with relreward.AsyncClient(server.addr) as ac:
            x = plans(tiny, 2, seed=8)
            g = await ac.gradient(tiny.reward, x, t=3)
            s = await ac.score(tiny.reward, x)
            async with ac.gradient_stream(tiny.reward) as stream:
                futures = [await stream.submit(x, t) for t in (3, 4)]
                first = await futures[0]
                await futures[1]
                with pytest.raises(relreward.InvalidArgument):
                    await stream.gradient(x, 100)
            assert (await ac.get_model(tiny.reward)).reward.n_timesteps == tiny.n_timesteps
            assert any(m.name == tiny.reward for m in await ac.list_models("reward"))
            with pytest.raises(relreward.NotFound):
                await ac.get_dataset("nope")
            batch = await ac.sample(tiny.base, n=2, seed=2)
            return g, s, first, batch

    g, s, first, batch = asyncio.run(main())
    np.testing.assert_allclose(g.gradient, first.gradient, rtol=1e-5, atol=1e-8)
    assert s.rewards.shape == (2,) and batch.x.shape[0] == 2
