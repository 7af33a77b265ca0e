"""Models out as PyTorch files (``export_model``, DownloadModel with ``torchscript``): for every
reward architecture (windowed MLP, ValueFunction, MLP, conv encoder), a discriminator, an
Algorithm 2 reward and every native diffusion architecture (TemporalUnet, MLP, UNet2D), the
server's traced ``module.pt`` loads with ``torch.jit.load`` and gives Score and Gradient (rewards)
or the independent PyTorch reference net loaded from the exported safetensors (diffusion, 100
inputs) to 1e-5, on batch sizes other than the one it was traced with; a Diffuser-style value
guide runs on the exported reward; a TorchScript model is refused naming ``torchscript``."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import relreward
from relreward_dev import nets, reward_nets, unet2d
from conftest import tiny_trajectories

OPT = relreward.Optimization(steps=4, batch_size=8)


@pytest.fixture(scope="module")
def models(client, tiny):
    """Every architecture, trained a few steps: {label: model name}."""
    names = {"windowed_mlp": tiny.reward, "temporal_unet": tiny.base}
    jobs = []
    for arch, params in (("value_function", {"widths": [8, 32]}), ("mlp", {"hidden": [16]})):
        jobs.append(client.submit_job(relreward.RewardJob(
            output_model=f"export-{arch}", base_model=tiny.base, expert_model=tiny.expert, datasets=[tiny.dataset],
            architecture=(arch, params), seed=1, optimization=OPT)))
        names[arch] = f"export-{arch}"
    # Algorithm 2 (models only): rho sees its input standardised per step (step_norm tables).
    jobs.append(client.submit_job(relreward.RewardJob(
        output_model="export-algorithm2", base_model=tiny.base, expert_model=tiny.expert, num_chains=8,
        architecture=("mlp", {"hidden": [16]}), seed=2, optimization=OPT)))
    names["algorithm2"] = "export-algorithm2"
    client.upload_dataset("export-traj2", tiny_trajectories(seed=1))
    jobs.append(client.submit_job(relreward.DiscriminatorJob(
        output_model="export-disc", base_dataset=tiny.dataset, expert_dataset="export-traj2",
        diffusion_model=tiny.base, seed=3, optimization=OPT)))
    names["discriminator"] = "export-disc"

    # Images [1, 8, 8]: two UNet2D models, an MLP denoiser and a conv-encoder reward between
    # the UNets.
    rng = np.random.default_rng(0)
    client.upload_dataset("export-images", rng.uniform(0, 1, (32, 1, 8, 8)).astype(np.float32))
    unet = ("unet2d", {"block_out_channels": [8, 16], "layers_per_block": 1, "attention": True})
    for name, arch, seed in (("export-unet-a", unet, 4), ("export-unet-b", unet, 5),
                             ("export-mlp-denoiser", ("mlp", {"hidden": [32]}), 6)):
        jobs.append(client.submit_job(relreward.DiffusionJob(
            output_model=name, dataset="export-images", architecture=arch, n_timesteps=10, seed=seed,
            optimization=OPT)))
    for job in jobs[-3:]:
        assert client.wait_job(job.id).state == relreward.JobState.SUCCEEDED
    names.update(unet2d="export-unet-a", mlp_denoiser="export-mlp-denoiser")
    jobs.append(client.submit_job(relreward.RewardJob(
        output_model="export-conv", base_model="export-unet-a", expert_model="export-unet-b",
        datasets=["export-images"], architecture=("conv_encoder", {"widths": [8, 16]}), seed=7, optimization=OPT)))
    names["conv_encoder"] = "export-conv"
    for job in jobs:
        done = client.wait_job(job.id)
        assert done.state == relreward.JobState.SUCCEEDED, done
    return names


REWARDS = ("windowed_mlp", "value_function", "mlp", "conv_encoder", "discriminator", "algorithm2")


@pytest.mark.parametrize("label", REWARDS)
def test_exported_reward_gives_score_and_gradient(client, models, tmp_path, label):
    got = client.export_model(models[label], tmp_path / label)
    assert got.module == tmp_path / label / "module.pt"
    assert got.path.name == "weights.safetensors" and got.files[-1] == got.module
    rho = torch.jit.load(str(got.module))
    shape = got.model.item_shape
    T = got.model.n_timesteps
    rng = np.random.default_rng(1)
    # Raw units: inside the data's range for a fitted normalizer (the tiny sets lie in [-1, 1]).
    for batch in (1, 5, 17):
        x = rng.uniform(-0.9, 0.9, (batch, *shape)).astype(np.float32)
        t = rng.integers(0, T, batch)
        xt = torch.from_numpy(x).requires_grad_(True)
        values = rho(xt, torch.from_numpy(t))
        (grad,) = torch.autograd.grad(values.sum(), xt)
        served = client.gradient(models[label], x, t)
        np.testing.assert_allclose(values.detach().numpy(), client.score(models[label], x, t).rewards,
                                   rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(values.detach().numpy(), served.rewards, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(grad.numpy(), served.gradient, rtol=1e-5, atol=1e-5)

    if label == "algorithm2":  # the reference nets have no step tables; the module has them
        assert got.manifest["step_normalization"] is True
        assert [f.name for f in got.files] == ["weights.safetensors", "step_norm.safetensors", "module.pt"]
        return
    # The safetensors weights in the independent PyTorch net give Score in normalized units.
    net = reward_nets.build(got.manifest["architecture"], list(shape))
    net.load_state_dict(load_file(got.path), strict=True)
    x = rng.uniform(-1, 1, (6, *shape)).astype(np.float32)
    t = np.arange(6) % T
    with torch.no_grad():
        ours = net(torch.from_numpy(x), torch.from_numpy(t)).numpy()
    np.testing.assert_allclose(ours, client.score(models[label], x, t, units="normalized").rewards,
                               rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("label", ("temporal_unet", "mlp_denoiser", "unet2d"))
def test_exported_denoiser_equals_the_reference_net(client, models, tmp_path, label):
    got = client.export_model(models[label], tmp_path / label)
    module = torch.jit.load(str(got.module))
    man = got.manifest
    shape = list(got.model.item_shape)
    arch = man["architecture"]
    if arch["kind"] == "unet2d":
        c, h, w = shape
        ref = unet2d.build({"channels": c, "height": h, "width": w, **{k: v for k, v in arch.items() if k != "kind"}})

        def reference(x, t):
            return ref(x, t).sample
    else:
        ref = nets.build(arch, man["space"])
        reference = ref
    ref.load_state_dict(load_file(got.path), strict=True)
    ref.eval()
    rng = np.random.default_rng(2)
    # 100 inputs in normalized units, in batches of sizes the trace never saw.
    x = torch.from_numpy(rng.standard_normal((100, *shape)).astype(np.float32))
    t = torch.from_numpy(rng.integers(0, man["n_timesteps"], 100))
    with torch.no_grad():
        for lo, hi in ((0, 1), (1, 8), (8, 100)):
            np.testing.assert_allclose(module(x[lo:hi], t[lo:hi]).numpy(), reference(x[lo:hi], t[lo:hi]).numpy(),
                                       rtol=1e-5, atol=1e-5)


def test_a_value_guide_runs_on_the_exported_reward(client, models, tmp_path):
    """Diffuser's planner calls ``guide.gradients(x, cond, t)`` for (y, grad_x y) on its x_t in
    normalized units; the exported module takes raw units, so the adapter un-normalizes first
    (manifest's limits normalizer: x_raw = (x + 1) / 2 * (max - min) + min)."""
    got = client.export_model(tiny_reward := models["windowed_mlp"], tmp_path / "guide")
    rho = torch.jit.load(str(got.module))
    norm = got.manifest["normalizer"]
    assert norm["kind"] == "limits"
    lo, hi = torch.tensor(norm["min"]), torch.tensor(norm["max"])

    class ExportedValue(torch.nn.Module):  # Diffuser's value model signature: (x, cond, t)
        def forward(self, x, cond, t):
            return rho((x + 1) / 2 * (hi - lo) + lo, t)

    class ValueGuide(torch.nn.Module):  # Diffuser's guide contract: y and grad_x y, x detached
        def __init__(self, model):
            super().__init__()
            self.model = model

        def gradients(self, x, cond, t):
            x.requires_grad_()
            y = self.model(x, cond, t)
            (grad,) = torch.autograd.grad([y.sum()], [x])
            x.detach()
            return y, grad

    guide = ValueGuide(ExportedValue())
    x = torch.zeros(4, *got.model.item_shape)
    t = torch.full((4,), 2, dtype=torch.long)
    y, grad = guide.gradients(x, {0: x[:, 0]}, t)
    served = client.gradient(tiny_reward, x.detach().numpy(), t.numpy(), units="normalized")
    np.testing.assert_allclose(y.detach().numpy(), served.rewards, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(grad.numpy(), served.gradient, rtol=1e-5, atol=1e-5)


def test_async_export_and_refusals(client, models, server, tmp_path):
    async def fetch():
        async with relreward.AsyncClient(client.endpoint) as ac:
            return await ac.export_model(models["mlp"], tmp_path / "async")

    got = asyncio.run(fetch())
    assert got.module is not None and got.module.stat().st_size > 0
    assert client.download_model(models["mlp"], tmp_path / "plain").module is None

    with pytest.raises(relreward.NotFound, match="name"):
        client.export_model("no-such-model", tmp_path / "none")
    assert not (tmp_path / "none").exists() or not any((tmp_path / "none").iterdir())

    # A model stored as TorchScript: its module.pt is the export; exporting it is refused by name.
    class Eps(torch.nn.Module):
        def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return 0.1 * x

    path = tmp_path / "eps.pt"
    torch.jit.script(Eps()).save(str(path))
    client.upload_model(path, "export-ts", {"parametrization": "epsilon", "n_timesteps": 10,
                                            "schedule": {"kind": "cosine"}, "space": {"kind": "sample", "shape": [3]},
                                            "normalizer": {"kind": "identity"}})
    try:
        with pytest.raises(relreward.FailedPrecondition, match="torchscript"):
            client.export_model("export-ts", tmp_path / "ts")
        assert client.download_model("export-ts", tmp_path / "ts").module == tmp_path / "ts" / "module.pt"
    finally:
        client.delete_model("export-ts")


def test_cli_export_writes_the_same_files_and_module(client, models, server, tmp_path):
    """`relreward model export NAME --out DIR`: the weights, manifest and module.pt the Python
    client's export writes, and a module that gives Score; a second export into the same folder
    is refused unless --force; an unknown model is refused by name."""
    name = models["value_function"]
    out = tmp_path / "cli"
    report = server.cli_json("model", "export", name, "--out", str(out))
    assert report["model"]["name"] == name
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "module.pt", "weights.safetensors"]
    rho = torch.jit.load(str(out / "module.pt"))
    got = client.export_model(name, tmp_path / "py")
    shape, T = got.model.item_shape, got.model.n_timesteps
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.9, 0.9, (4, *shape)).astype(np.float32)
    t = rng.integers(0, T, 4)
    with torch.no_grad():
        values = rho(torch.from_numpy(x), torch.from_numpy(t)).numpy()
    np.testing.assert_allclose(values, client.score(name, x, t).rewards, rtol=1e-5, atol=1e-5)
    assert (out / "weights.safetensors").read_bytes() == got.path.read_bytes()

    again = server.cli("model", "export", name, "--out", str(out), check=False)
    assert again.returncode != 0 and "--force" in again.stderr, again.stderr
    server.cli("model", "export", name, "--out", str(out), "--force")
    missing = server.cli("model", "export", "no-such-model", "--out", str(tmp_path / "none"), check=False)
    assert missing.returncode != 0 and "no-such-model" in missing.stderr, missing.stderr
