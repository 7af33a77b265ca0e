"""DDIM and v-prediction against diffusers' own schedulers on the same model (issue 37 item 4).

A small UNet2DModel with random weights is saved by diffusers' save_pretrained with a
DDPMScheduler config (epsilon, sample or v_prediction) and imported with `relreward model
import`, as tests/python/diffusers_folder.py does for the import's own check. relreward's Sample
(DDIM with eta 0 and eta > 0, several spacings; DDPM for the v model) is then replayed in
diffusers: DDIMScheduler.from_config / DDPMScheduler on the same config, the same starting x_T and
the same per-step noise. Both come from relreward's seeded generator (SplitMix64 and Box-Muller,
server/src/engine/rng.rs), which `relreward_dev.rng.RelrewardRng` reproduces bit for bit, so a seed fixes
every draw on both sides. Bar: 1e-5 per step (relative where values exceed 1): a one-step run
(trailing spacing, one step from T - 1, for each parametrization) to 1e-5, a k-step run to
k * 1e-5 (float32 rounding accumulates along the trajectory; see `assert_close`).

diffusers' schedulers keep alphas_cumprod in float32, which loses digits in 1 - abar; relreward
derives its tables in float64, so the replay runs diffusers' step on float64 tables (from the
same float32 betas), as diffusers_folder.py's `mean64` does.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")
from diffusers import DDIMScheduler, DDPMScheduler, UNet2DModel  # noqa: E402
from diffusers.schedulers import scheduling_ddpm  # noqa: E402

from relreward.errors import InvalidArgument, InvalidInput  # noqa: E402
from relreward_dev.rng import RelrewardRng  # noqa: E402
from relreward_dev.unet2d import float64_tables  # noqa: E402

T = 20
SHAPE = (2, 8, 8)
N = 2


def perturbed_unet() -> UNet2DModel:
    torch.manual_seed(11)
    unet = UNet2DModel(sample_size=8, in_channels=2, out_channels=2, block_out_channels=(8, 16), layers_per_block=1,
                       down_block_types=("DownBlock2D",) * 2, up_block_types=("UpBlock2D",) * 2, add_attention=False,
                       norm_num_groups=4)
    g = torch.Generator().manual_seed(12)
    with torch.no_grad():
        for p in unet.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.2)
    return unet.eval()


def ddpm_config(prediction_type: str, clip: bool) -> DDPMScheduler:
    # A linear schedule ending at abar_{T-1} ~ 0.13: every step's x0 <-> eps conversion is well
    # conditioned, so 1e-5 measures the step, not a division by sqrt(abar) ~ 0.
    return DDPMScheduler(num_train_timesteps=T, beta_schedule="linear", beta_start=0.001, beta_end=0.2,
                         prediction_type=prediction_type, clip_sample=clip)


@pytest.fixture(scope="module")
def models(server, tmp_path_factory):
    """name -> (unet, DDPMScheduler) for the same weights under each parametrization."""
    d = tmp_path_factory.mktemp("ddim")
    unet = perturbed_unet()
    out = {}
    for name, prediction, clip in (("ddim-eps", "epsilon", False), ("ddim-eps-clip", "epsilon", True),
                                   ("ddim-x0", "sample", True), ("ddim-v", "v_prediction", False)):
        folder = d / name
        sched = ddpm_config(prediction, clip)
        unet.save_pretrained(folder)
        sched.save_pretrained(folder / "scheduler")
        server.cli("model", "import", str(folder), "--out", str(d / f"{name}.safetensors"), "--name", name)
        out[name] = (unet, sched)
    return out


def ddim_replay(unet, ddpm, seed, steps, eta, spacing, alpha_to_one):
    sched = float64_tables(DDIMScheduler.from_config(ddpm.config, timestep_spacing=spacing,
                                                     set_alpha_to_one=alpha_to_one))
    sched.set_timesteps(steps)
    rng = RelrewardRng(seed)
    x = rng.randn((N, *SHAPE)).double()
    for t in sched.timesteps:
        t = int(t)
        with torch.no_grad():
            pred = unet(x.float(), torch.full((N,), t)).sample.double()
        prev = t - T // steps
        a, ap = float(sched.alphas_cumprod[t]), (float(sched.alphas_cumprod[prev]) if prev >= 0
                                                  else float(sched.final_alpha_cumprod))
        sigma = eta * math.sqrt((1 - ap) / (1 - a) * (1 - a / ap))
        noise = rng.randn((N, *SHAPE)).double() if sigma > 0 else None
        x = sched.step(pred, t, x, eta=eta, variance_noise=noise).prev_sample
    return x.numpy()


def ddpm_replay(unet, ddpm, seed, monkeypatch):
    sched = float64_tables(DDPMScheduler.from_config(ddpm.config))
    sched.set_timesteps(T)
    rng = RelrewardRng(seed)
    x = rng.randn((N, *SHAPE)).double()
    # DDPMScheduler.step draws its noise (t > 0) from randn_tensor: hand it relreward's draws.
    monkeypatch.setattr(scheduling_ddpm, "randn_tensor", lambda shape, **kw: rng.randn(tuple(shape)).double())
    for t in sched.timesteps:
        with torch.no_grad():
            pred = unet(x.float(), torch.full((N,), int(t))).sample.double()
        x = sched.step(pred, int(t), x).prev_sample
    return x.numpy()


def assert_close(got, want, what, steps=1):
    """1e-5 per step: relreward steps in float32 (on float64 tables), the replay in float64, so
    a run of k steps may drift up to k float32 roundings of each step (1.6e-5 after 10 steps
    here); one-step runs are held to 1e-5 itself."""
    err = np.abs(got.astype(np.float64) - want) / np.maximum(1.0, np.abs(want))
    assert err.max() < 1e-5 * steps, \
        f"{what}: max relative difference {err.max():.3g} (|x| up to {np.abs(want).max():.3g})"


def test_the_generator_port_matches_the_server(client, models):
    # One leading step is t = 0 -> the end: the output is x0(x_T, 0), within a few percent of
    # x_T itself, so a port that drew other noise could not pass.
    unet, ddpm = models["ddim-eps"]
    got = client.sample("ddim-eps", n=N, seed=5, sampler="ddim", steps=1).x_normalized
    assert_close(got, ddim_replay(unet, ddpm, 5, 1, 0.0, "leading", True), "one leading step")


@pytest.mark.parametrize("name,steps,eta,spacing,alpha_to_one", [
    ("ddim-eps", 5, 0.0, "leading", True),
    ("ddim-eps", 1, 0.0, "trailing", True),
    ("ddim-eps", 4, 0.5, "trailing", True),
    ("ddim-eps-clip", 3, 1.0, "linspace", False),
    ("ddim-eps-clip", 10, 0.0, "trailing", True),
    ("ddim-x0", 6, 0.0, "linspace", True),
    ("ddim-x0", 1, 0.0, "trailing", True),
    ("ddim-x0", 7, 0.3, "leading", False),
    ("ddim-v", 5, 0.0, "leading", True),
    ("ddim-v", 1, 0.0, "trailing", True),
    ("ddim-v", 20, 0.8, "trailing", True),
])
def test_ddim_equals_diffusers(client, models, name, steps, eta, spacing, alpha_to_one):
    unet, ddpm = models[name]
    got = client.sample(name, n=N, seed=3, sampler="ddim", steps=steps, eta=eta, timestep_spacing=spacing,
                        set_alpha_to_one=alpha_to_one).x_normalized
    want = ddim_replay(unet, ddpm, 3, steps, eta, spacing, alpha_to_one)
    assert_close(got, want, f"{name} {steps} {spacing} steps, eta {eta}", steps)


def test_ddpm_on_a_v_model_equals_diffusers(client, models, monkeypatch):
    unet, ddpm = models["ddim-v"]
    got = client.sample("ddim-v", n=N, seed=8).x_normalized
    assert_close(got, ddpm_replay(unet, ddpm, 8, monkeypatch), "DDPM, v_prediction", T)


def test_default_sampler_is_unchanged_ddpm(client, models, monkeypatch):
    unet, ddpm = models["ddim-eps-clip"]
    got = client.sample("ddim-eps-clip", n=N, seed=9).x_normalized
    assert_close(got, ddpm_replay(unet, ddpm, 9, monkeypatch), "DDPM, epsilon", T)


def test_ddim_options_are_checked_naming_the_field(client, models):
    with pytest.raises(InvalidArgument, match=r"ddim\.n_steps: 21"):
        client.sample("ddim-eps", sampler="ddim", steps=T + 1)
    with pytest.raises(InvalidArgument, match=r"ddim\.eta: 1\.5"):
        client.sample("ddim-eps", sampler="ddim", eta=1.5)
    with pytest.raises(InvalidInput, match="timestep_spacing 'karras'"):
        client.sample("ddim-eps", sampler="ddim", timestep_spacing="karras")
    with pytest.raises(InvalidInput, match="sampler 'dpm'"):
        client.sample("ddim-eps", sampler="dpm")
    with pytest.raises(InvalidInput, match="eta: only applies to sampler='ddim'"):
        client.sample("ddim-eps", eta=0.5)


def test_the_cli_samples_with_ddim_as_the_client_does(server, client, models, tmp_path):
    out = tmp_path / "ddim.npz"
    server.cli("sample", "--base", "ddim-v", "--sampler", "ddim", "--steps", "4", "--eta", "0.5",
               "--timestep-spacing", "linspace", "--n", str(N), "--seed", "4", "--out", str(out))
    want = client.sample("ddim-v", n=N, seed=4, sampler="ddim", steps=4, eta=0.5,
                         timestep_spacing="linspace").x_normalized
    np.testing.assert_array_equal(np.load(out)["x_normalized"], want)
    p = server.cli("sample", "--base", "ddim-v", "--eta", "0.5", check=False)
    assert p.returncode != 0 and "--eta only applies to DDIM: add --sampler ddim" in p.stderr, p.stderr
