"""The Diffuser-style guide inside a numpy DDPM loop, and the examples/ scripts (run here so
they cannot rot)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import relreward
from relreward.guide import RewardGuide
from conftest import REPO


def run_example(name: str, *args: str) -> dict:
    p = subprocess.run([sys.executable, str(REPO / "examples" / name), *args], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, f"{name} failed:\n{p.stdout}\n{p.stderr}"
    return json.loads(p.stdout)


def test_guide_in_a_numpy_ddpm_loop_moves_samples_toward_the_reward(client, tiny):
    from diffuser_guide import guided_sample  # examples/, on sys.path through conftest.py
    shape = (16, tiny.horizon, tiny.transition_dim)
    with RewardGuide(client, tiny.reward) as guide:
        plain = guided_sample(None, shape, tiny.n_timesteps, scale=2.0, scale_grad_by_std=False, seed=3)
        guided = guided_sample(guide, shape, tiny.n_timesteps, scale=2.0, scale_grad_by_std=False, seed=3)
        zero = np.zeros(16, np.int64)
        rho_plain, rho_guided = guide(plain, None, zero), guide(guided, None, zero)
    assert rho_guided.mean() > rho_plain.mean()
    assert np.mean(rho_guided > rho_plain) > 0.5


def test_guide_speaks_torch_and_matches_gradient(client, tiny):
    torch = pytest.importorskip("torch")
    x = torch.randn(3, tiny.horizon, tiny.transition_dim, dtype=torch.float64)
    t = torch.tensor([1, 4, 9])
    with RewardGuide(client, tiny.reward, omega=0.5) as guide:
        y, grad = guide.gradients(x, {}, t)
    assert isinstance(y, torch.Tensor) and y.dtype == torch.float64 and y.shape == (3,)
    assert grad.shape == x.shape
    ref = client.gradient(tiny.reward, x.numpy(), t.numpy(), omega=0.5, units="normalized")
    np.testing.assert_allclose(grad.numpy(), ref.gradient, rtol=1e-5, atol=1e-8)


def test_example_quickstart(server, tiny):
    out = run_example("python_quickstart.py", "--endpoint", server.addr, "--model", tiny.reward)
    assert out["input_shape"] == [4, tiny.horizon, tiny.transition_dim]
    assert out["stream_steps"] == tiny.n_timesteps and out["stream_matches_unary"]


def test_example_diffuser_guide(server, tiny):
    out = run_example("diffuser_guide.py", "--endpoint", server.addr, "--model", tiny.reward, "--scale", "2",
                      "--no-scale-grad-by-std")
    assert out["rho_guided"] > out["rho_unguided"], out


def test_example_planner_gradient_stream(server, tiny):
    out = run_example("planner_gradient_stream.py", "--endpoint", server.addr, "--model", tiny.reward, "--omega",
                      "0.05")
    assert out["requests"] == 2 * tiny.n_timesteps and out["mean_gain_per_guide_step"] > 0


def test_imports_next_to_tritonclient():
    """relreward's stubs live under relreward.v1: no clash with tritonclient's `inference`."""
    code = "import relreward, tritonclient.grpc, tritonclient.grpc.service_pb2; print(relreward.Client.__name__)"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if "No module named 'tritonclient'" in p.stderr:
        pytest.skip("tritonclient not installed")
    assert p.returncode == 0 and p.stdout.strip() == "Client", p.stderr
    assert relreward.pb.reward.DESCRIPTOR.package == "relreward.v1"
    assert relreward.pb.reward.__name__ == "relreward.v1.reward_pb2"
