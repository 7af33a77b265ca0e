"""Bring-your-own rewards (UploadModel with ``header.reward``, ``Client.upload_reward``): a
scripted rho(x, t) and a module of Diffuser's ValueFunction signature ``forward(x, cond, t) ->
[B, 1]``, uploaded as TorchScript, give Score and Gradient equal to PyTorch running the same
module in-process (1e-5; in normalized units and in raw units through the manifest's
normalizer), stream through GradientStream, guide Sample and answer OIP's infer; a native
reward exported (``export_model``) and uploaded back as a BYO reward scores the same; hostile or
mismatched uploads are refused by name and leave nothing stored."""

from __future__ import annotations

from typing import Dict

import numpy as np
import pytest
import torch
from torch import nn

import relreward
from relreward.v1 import models_pb2
from conftest import start_server


class Rho(nn.Module):
    """rho(x, t) -> [B]: an MLP over the flattened item with a time embedding."""

    def __init__(self, features: int):
        super().__init__()
        self.inp = nn.Linear(features, 16)
        self.time = nn.Linear(1, 16)
        self.out = nn.Linear(16, 1)

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        h = torch.tanh(self.inp(x.flatten(1)) + self.time(t.float().unsqueeze(1) / 10))
        return self.out(h).squeeze(1)


class ValueFunction(nn.Module):
    """A small module of Diffuser's ValueFunction signature and form: a 1D convolution over the
    horizon with a time MLP, flattened into a final MLP over [features, time] -> [B, 1]."""

    def __init__(self, horizon: int, transition: int, dim: int = 8):
        super().__init__()
        self.time_mlp = nn.Sequential(nn.Linear(1, dim), nn.Mish(), nn.Linear(dim, dim))
        self.conv = nn.Conv1d(transition, dim, 3, padding=1)
        self.final = nn.Sequential(nn.Linear(dim * horizon + dim, dim), nn.Mish(), nn.Linear(dim, 1))

    def forward(self, x: torch.Tensor, cond: Dict[str, torch.Tensor], time: torch.Tensor) -> torch.Tensor:
        x = x.transpose(1, 2)  # einops 'b h t -> b t h'
        t = self.time_mlp(time.float().unsqueeze(1))
        h = nn.functional.mish(self.conv(x) + t.unsqueeze(2))
        return self.final(torch.cat([h.flatten(1), t], dim=-1))


def save(module: nn.Module, path) -> str:
    torch.manual_seed(0)
    torch.jit.script(module).save(str(path))
    return str(path)


def base_manifest(client, tiny) -> models_pb2.DiffusionManifest:
    return client.get_model(tiny.base).manifest.to_proto()


def reward_manifest(client, tiny, kind: str, **changes) -> models_pb2.RewardUploadManifest:
    """A RewardUploadManifest of signature ``kind`` with the base model's space, T and
    normalizer; ``changes`` set fields of the message afterwards."""
    m = base_manifest(client, tiny)
    out = models_pb2.RewardUploadManifest(
        signature={"rho": models_pb2.REWARD_SIGNATURE_RHO,
                   "value_function": models_pb2.REWARD_SIGNATURE_VALUE_FUNCTION}[kind],
        trajectory=m.trajectory, normalizer=m.normalizer, n_timesteps=m.n_timesteps, base_model=tiny.base)
    for k, v in changes.items():
        setattr(out, k, v)
    return out


def affine(normalizer: models_pb2.Normalizer) -> tuple[np.ndarray, np.ndarray]:
    """(scale, offset) with x_norm = scale * x_raw + offset, per coordinate."""
    kind = normalizer.WhichOneof("kind")
    if kind == "limits":
        lo, hi = np.array(normalizer.limits.min), np.array(normalizer.limits.max)
        scale = 2 / (hi - lo)
        return scale, -lo * scale - 1
    if kind == "gaussian":
        mean, std = np.array(normalizer.gaussian.mean), np.array(normalizer.gaussian.std)
        return 1 / std, -mean / std
    return np.ones(1), np.zeros(1)


def in_process(module, signature: str, x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(reward [B], grad_x) of the module in PyTorch, x in normalized units."""
    xt = torch.from_numpy(x).requires_grad_(True)
    tt = torch.from_numpy(t.astype(np.int64))
    y = module(xt, tt) if signature == "rho" else module(xt, {}, tt).squeeze(-1)
    (grad,) = torch.autograd.grad(y.sum(), xt)
    return y.detach().numpy(), grad.numpy()


@pytest.fixture(scope="module")
def byo(client, tiny, tmp_path_factory):
    """Both signatures uploaded: {signature: (model name, the module as loaded in PyTorch)}."""
    d = tmp_path_factory.mktemp("byo")
    out = {}
    for signature, module in (("rho", Rho(tiny.horizon * tiny.transition_dim)),
                              ("value_function", ValueFunction(tiny.horizon, tiny.transition_dim))):
        path = save(module, d / f"{signature}.pt")
        name = f"byo-{signature.replace('_', '-')}"
        model = client.upload_reward(path, name, reward_manifest(client, tiny, signature), description="byo")
        assert (model.kind, model.format) == ("reward", "torchscript")
        assert model.reward.architecture == f"torchscript({signature})"
        out[signature] = (name, torch.jit.load(path))
    return out


@pytest.mark.parametrize("signature", ["rho", "value_function"])
def test_score_and_gradient_equal_pytorch_in_both_units(client, tiny, byo, signature):
    name, module = byo[signature]
    info = client.get_model(name)
    assert list(info.item_shape) == [tiny.horizon, tiny.transition_dim] and info.n_timesteps == tiny.n_timesteps
    scale, offset = affine(base_manifest(client, tiny).normalizer)
    rng = np.random.default_rng(1)
    for batch in (1, 5, 17):
        t = rng.integers(0, tiny.n_timesteps, batch)
        x = rng.uniform(-1, 1, (batch, tiny.horizon, tiny.transition_dim)).astype(np.float32)
        want, want_grad = in_process(module, signature, x, t)
        np.testing.assert_allclose(client.score(name, x, t, units="normalized").rewards, want, rtol=1e-5, atol=1e-5)
        got = client.gradient(name, x, t, units="normalized")
        np.testing.assert_allclose(got.rewards, want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(got.gradient, want_grad, rtol=1e-5, atol=1e-5)
        # Raw units: the manifest's normalizer maps them in, its Jacobian maps the gradient out.
        raw = ((x - offset) / scale).astype(np.float32)
        x_norm = (raw.astype(np.float64) * scale + offset).astype(np.float32)
        want, want_grad = in_process(module, signature, x_norm, t)
        np.testing.assert_allclose(client.score(name, raw, t).rewards, want, rtol=1e-5, atol=1e-5)
        got = client.gradient(name, raw, t)
        np.testing.assert_allclose(got.rewards, want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(got.gradient, want_grad * scale, rtol=1e-5, atol=1e-5)


def test_listed_downloaded_and_described_as_uploaded(client, tiny, byo, tmp_path):
    name, _ = byo["value_function"]
    model = client.get_model(name)
    assert (model.kind, model.format, model.reward.base_model) == ("reward", "torchscript", tiny.base)
    assert name in [m.name for m in client.list_models("reward")]
    got = client.download_model(name, tmp_path / "dl")
    assert [f.name for f in got.files] == ["module.pt"]
    assert got.manifest["architecture"] == {"kind": "torchscript", "signature": "value_function"}
    assert got.manifest["objective"] == {"kind": "uploaded"} and got.manifest["base_model"] == tiny.base
    with pytest.raises(relreward.FailedPrecondition, match="torchscript"):
        client.export_model(name, tmp_path / "export")


def test_gradient_stream_guided_sample_and_async(client, server, tiny, byo):
    name, module = byo["value_function"]
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, (3, tiny.horizon, tiny.transition_dim)).astype(np.float32)
    with client.gradient_stream(name, units="normalized") as stream:
        for t in range(tiny.n_timesteps):
            g, rho = stream.gradient(x, t)
            want, want_grad = in_process(module, "value_function", x, np.full(3, t))
            np.testing.assert_allclose(rho, want, rtol=1e-5, atol=1e-5)
            np.testing.assert_allclose(g, want_grad, rtol=1e-5, atol=1e-5)
    expected = [client.gradient(name, x, t=t) for t in range(tiny.n_timesteps)]
    with client.gradient_stream(name) as stream:
        pending = [stream.submit(x, t) for t in range(tiny.n_timesteps)]  # in flight together
        for t, p in enumerate(pending):
            np.testing.assert_allclose(p.result().gradient, expected[t].gradient, rtol=1e-5, atol=1e-6)
    guided = client.sample(tiny.base, reward_model=name, omega=0.1, n=3, seed=5)
    plain = client.sample(tiny.base, n=3, seed=5)
    assert guided.x.shape == (3, tiny.horizon, tiny.transition_dim) and np.isfinite(guided.x).all()
    assert guided.rewards is not None and not np.array_equal(guided.x, plain.x), "guidance moved the samples"

    async def run():
        async with relreward.AsyncClient(server.addr) as ac:
            return await ac.score(name, x, 0)

    import asyncio
    np.testing.assert_allclose(asyncio.run(run()).rewards, client.score(name, x, 0).rewards, rtol=0, atol=0)


def test_oip_infer_reward_and_gradient(server, client, tiny, byo):
    grpcclient = pytest.importorskip("tritonclient.grpc")
    name, _ = byo["rho"]
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (4, tiny.horizon, tiny.transition_dim)).astype(np.float32)
    t = np.array([0, 3, 5, 9], np.int64)
    with grpcclient.InferenceServerClient(server.addr) as oip:
        assert oip.is_model_ready(name)
        inputs = [grpcclient.InferInput("x", list(x.shape), "FP32"), grpcclient.InferInput("t", [4], "INT64")]
        inputs[0].set_data_from_numpy(x)
        inputs[1].set_data_from_numpy(t)
        outputs = [grpcclient.InferRequestedOutput("reward"), grpcclient.InferRequestedOutput("grad_x")]
        result = oip.infer(name, inputs, outputs=outputs)
    served = client.gradient(name, x, t)
    np.testing.assert_array_equal(result.as_numpy("reward"), served.rewards)
    np.testing.assert_array_equal(result.as_numpy("grad_x"), served.gradient)


def test_an_exported_native_reward_uploaded_back_scores_the_same(client, tiny, tmp_path):
    """export_model's module.pt takes raw units (the normalizer inside): uploaded as a BYO rho
    with the identity normalizer, raw Score and Gradient equal the native reward's."""
    got = client.export_model(tiny.reward, tmp_path / "export")
    manifest = reward_manifest(client, tiny, "rho", base_model="")
    manifest.normalizer.Clear()
    manifest.normalizer.identity.SetInParent()
    client.upload_reward(got.module, "byo-roundtrip", manifest)
    rng = np.random.default_rng(4)
    x = rng.uniform(-0.9, 0.9, (6, tiny.horizon, tiny.transition_dim)).astype(np.float32)
    t = np.arange(6) % tiny.n_timesteps
    np.testing.assert_allclose(client.score("byo-roundtrip", x, t).rewards, client.score(tiny.reward, x, t).rewards,
                               rtol=1e-5, atol=1e-5)
    ours, native = client.gradient("byo-roundtrip", x, t), client.gradient(tiny.reward, x, t)
    np.testing.assert_allclose(ours.gradient, native.gradient, rtol=1e-5, atol=1e-5)


class WrongShape(nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.flatten(1)[:, :2]


class NonFinite(nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.flatten(1).sum(1) / 0.0 * 0.0


class FixedItem(nn.Module):
    """Written for items [8, 5]: raises on any other item shape."""

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.reshape(x.shape[0], 8, 5).sum(dim=(1, 2))


class Raises(nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        raise RuntimeError("deliberate failure: this reward always raises")


class Detached(nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.detach().flatten(1).sum(1)


def test_hostile_and_mismatched_uploads_are_refused_by_name(client, tiny, tmp_path):
    before = sorted(m.name for m in client.list_models())
    cases = [
        (WrongShape(), "rho", {}, relreward.InvalidArgument, "returned shape [2, 2]"),
        (NonFinite(), "rho", {}, relreward.InvalidArgument, "NaN or infinite"),
        (FixedItem(), "rho", {}, relreward.InvalidArgument, "raised"),
        (Raises(), "rho", {}, relreward.InvalidArgument, "deliberate failure: this reward always raises"),
        (Detached(), "rho", {}, relreward.InvalidArgument, "does not depend differentiably on x"),
        # A rho module declared as a value function: called with three arguments, it raises.
        (Rho(tiny.horizon * tiny.transition_dim), "value_function", {}, relreward.InvalidArgument,
         "forward(x, cond, t)"),
        (Rho(tiny.horizon * tiny.transition_dim), "rho", {"n_timesteps": tiny.n_timesteps + 1},
         relreward.InvalidArgument, "header.reward.n_timesteps"),
        (Rho(tiny.horizon * tiny.transition_dim), "rho", {"base_model": "no-such-model"}, relreward.NotFound,
         "header.reward.base_model"),
        (Rho(tiny.horizon * tiny.transition_dim), "rho", {"signature": 0}, relreward.InvalidArgument,
         "header.reward.signature"),
    ]
    for i, (module, signature, changes, error, message) in enumerate(cases):
        path = save(module, tmp_path / f"bad{i}.pt")
        with pytest.raises(error) as e:
            client.upload_reward(path, f"bad-{i}", reward_manifest(client, tiny, signature, **changes))
        assert message in e.value.message, (i, e.value.message)
        assert "Exception raised from" not in e.value.message and str(tmp_path) not in e.value.message
    with pytest.raises(relreward.InvalidInput, match="signature"):
        client.upload_reward(tmp_path / "bad0.pt", "bad-dict", {"signature": "q", "n_timesteps": 10})
    assert sorted(m.name for m in client.list_models()) == before, "nothing was stored"


def test_uploads_are_off_unless_enabled(tmp_path, tiny):
    server = start_server(tmp_path / "data")
    try:
        with relreward.Client(server.addr) as c:
            path = save(Rho(tiny.horizon * tiny.transition_dim), tmp_path / "rho.pt")
            manifest = {"signature": "rho", "n_timesteps": tiny.n_timesteps,
                        "space": {"kind": "trajectory", "horizon": tiny.horizon, "action_dim": 2, "obs_dim": 2},
                        "normalizer": {"kind": "identity"}}
            with pytest.raises(relreward.FailedPrecondition, match="allow_torchscript_upload"):
                c.upload_reward(path, "byo", manifest)
            assert c.list_models() == []
    finally:
        server.stop()
