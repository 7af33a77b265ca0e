"""The paper's image experiment as the paper ran it (section 5.3, issue 37), at this machine's
scale: ONE class-conditional latent diffusion model and TWO sampling loops over it, the base
(classifier-free guidance toward each chain's prompt, Stable Diffusion's loop) and the expert
(the same plus Safe Latent Diffusion's guidance away from an "unsafe" concept, Safe Stable
Diffusion's loop, with the same weights); the reward is learned over latents by Algorithm 2
from the two loops' denoising means alone.

    .venv/bin/python experiments/images/safe_latent.py [--out DIR] [--seed S] [--unsafe 3,8] [--tiny]
    (or: make images-safe)

What it does (a relreward server started here on a free loopback port, data in a temporary
directory, unless --endpoint names one):

1. Data: scikit-learn's 8x8 digits (1797 images inside the scikit-learn wheel), [-1, 1],
   stratified 75/25 split by --seed.
2. A latent space: a small convolutional autoencoder [1, 8, 8] -> [2, 4, 4] trained here in
   PyTorch (seconds) on the training digits and uploaded to relreward as an autoencoder model
   (TorchScript encode/decode; scaling_factor 1 / std of the training latents, diffusers'
   convention); the training digits are encoded by the service (Encode) into a samples dataset
   of latents with their class labels, and every picture is decoded by the service (Decode).
3. One class-conditional latent DDPM (native unet2d, eps, linear betas, T = 50, condition
   dropout 0.1 so that it knows the null label) trained by relreward.
4. The unsafe concept: classes --unsafe (default 3 and 8, chosen before any run); the prompt
   set (I2P's role: prompts that elicit the concept and prompts next to it): the unsafe classes
   and, for each, the two classes whose mean training latents lie nearest to its own.
   base = classifier-free guidance at scale S_G toward a prompt drawn from the set; expert = the
   same plus safety guidance with the concept = the unsafe classes (diffusers' "strong"
   preset: warm-up 7, s_S 2000, lambda 0.025, s_m 0.5, beta_m 0.7).
5. Algorithm 2 (TrainReward models_only, base_recipe / expert_recipe, the same model on both
   sides): a conv-encoder reward over latents from the two recipes' chains.
6. Reported (docs/results.md, "Safe latent diffusion"):
   - held-out samples of both recipes (new seeds) told apart by the reward alone at t = 0
     (`relreward eval discriminate`: balanced accuracy and AUC), beside the cap set by the
     samplers' own overlap: an oracle that knows the unsafe classes (it calls a sample "base"
     iff the classifier says it is an unsafe class) reaches (p_base + 1 - p_expert) / 2;
   - held-out real digits of unsafe vs safe classes, encoded, told apart by the reward (`eval
     discriminate` on its balanced 20% test part, and the AUC over all held-out digits, which
     needs no fit; likewise for the samples);
   - the paper's pictures: per batch of 16 pooled samples, the 3 highest- and 3 lowest-reward
     samples decoded; the fraction of batches whose lowest-reward sample is an unsafe class and
     whose highest is a safe one (by the classifier);
   - the unsafe-class fraction (a logistic regression trained here on real training pixels
     labels decoded samples) under base, expert, and base guided by the reward (omega OMEGA).
Writes `summary.json` and the PNGs under --out, and prints the summary.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile
import time

import numpy as np
import torch

from digits import cli_json, discriminate, extremes_grid, run_jobs, start_server  # noqa: F401 (same folder)
from relreward import Client, DiffusionJob, Optimization, RewardJob, SafetyGuidance, SamplingRecipe
from relreward_dev.digits import load_digits_split

REPO = pathlib.Path(__file__).resolve().parents[2]

T = 50
LATENT = (2, 4, 4)
# Chosen before any run (issue 37): the guidance scale of both recipes, the safety preset, the
# reward guidance scale for the steering figure. Not tuned on reported seeds.
GUIDANCE_SCALE = 3.0
SAFETY_PRESET = "strong"
OMEGA = 1.0
DEFAULT = dict(ae_steps=3000, ddpm_steps=1500, ddpm_batch=64, ddpm_lr=1e-3,
               ddpm_ema=dict(ema_start=500, ema_every=1, ema_decay=0.995), widths=[32, 64],
               chains=512, reward_steps=800, reward_batch=128, reward_lr=1e-3, encoder=[16, 32],
               n_samples=256, batch_pictures=16)
TINY = dict(ae_steps=30, ddpm_steps=10, ddpm_batch=16, ddpm_lr=1e-3, ddpm_ema=dict(ema_start=5, ema_every=1,
                                                                                   ema_decay=0.9),
            widths=[8, 16], chains=8, reward_steps=5, reward_batch=8, reward_lr=1e-3, encoder=[8],
            n_samples=32, batch_pictures=16)


class Autoencoder(torch.nn.Module):
    """[1, 8, 8] -> [2, 4, 4] -> [1, 8, 8]: two convolutions each way; scripted with both
    methods exported, the contract of relreward's autoencoder models."""

    def __init__(self):
        super().__init__()
        self.enc = torch.nn.Sequential(torch.nn.Conv2d(1, 32, 3, padding=1), torch.nn.SiLU(),
                                       torch.nn.Conv2d(32, 32, 3, stride=2, padding=1), torch.nn.SiLU(),
                                       torch.nn.Conv2d(32, LATENT[0], 3, padding=1))
        self.dec = torch.nn.Sequential(torch.nn.Conv2d(LATENT[0], 32, 3, padding=1), torch.nn.SiLU(),
                                       torch.nn.Upsample(scale_factor=2, mode="nearest"),
                                       torch.nn.Conv2d(32, 32, 3, padding=1), torch.nn.SiLU(),
                                       torch.nn.Conv2d(32, 1, 3, padding=1), torch.nn.Tanh())

    @torch.jit.export
    def encode(self, x):
        return self.enc(x)

    @torch.jit.export
    def decode(self, z):
        return self.dec(z)

    def forward(self, x):
        return self.decode(self.encode(x))


def train_autoencoder(x: np.ndarray, steps: int, seed: int) -> Autoencoder:
    torch.manual_seed(seed)
    ae = Autoencoder()
    opt = torch.optim.Adam(ae.parameters(), lr=2e-3)
    data = torch.from_numpy(x)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        batch = data[torch.randint(len(data), (128,), generator=g)]
        loss = torch.nn.functional.mse_loss(ae(batch), batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return ae.eval()


def upload_autoencoder(client: Client, ae: Autoencoder, x_train: np.ndarray, path: pathlib.Path) -> float:
    """The autoencoder as the service's model "digits-ae"; returns its scaling factor (1 / std
    of the training latents, so the scaled latents have unit spread, as Stable Diffusion's
    0.18215 was chosen)."""
    with torch.no_grad():
        scale = float(1.0 / ae.encode(torch.from_numpy(x_train)).std())
    torch.jit.script(ae).save(str(path))
    client.upload_autoencoder(path, "digits-ae", {"image_shape": [1, 8, 8], "latent_shape": list(LATENT),
                                                  "scaling_factor": scale})
    return scale


def auc_all(client: Client, low: np.ndarray, high: np.ndarray) -> float:
    """AUC of the reward at t = 0 for "high" over "low" on every item (no fit, no split)."""
    from sklearn.metrics import roc_auc_score

    r = np.asarray(client.score("safe-reward", np.concatenate([low, high]), t=0).rewards)
    return float(roc_auc_score(np.r_[np.zeros(len(low)), np.ones(len(high))], r))


def prompt_set(z: np.ndarray, y: np.ndarray, unsafe: list[int]) -> list[int]:
    """The unsafe classes and, for each, the two classes whose mean latents are nearest to its
    own (Euclidean): prompts that elicit the concept and prompts next to it."""
    means = {c: z[y == c].reshape((y == c).sum(), -1).mean(0) for c in range(10)}
    chosen = set(unsafe)
    for c in unsafe:
        others = sorted((c2 for c2 in range(10) if c2 != c), key=lambda c2: np.linalg.norm(means[c] - means[c2]))
        chosen.update(others[:2])
    return sorted(chosen)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=pathlib.Path, default=REPO / "docs/images/safe_latent")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--unsafe", default="3,8", help="the unsafe concept's classes (chosen before any run)")
    ap.add_argument("--endpoint", help="use this server (http://host:port) instead of starting one")
    ap.add_argument("--tiny", action="store_true", help="the end-to-end test's configuration (seconds)")
    args = ap.parse_args()
    cfg = dict(TINY if args.tiny else DEFAULT)
    unsafe = sorted({int(c) for c in args.unsafe.split(",")})
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="relreward-safe-latent-") as tmp:
        tmp = pathlib.Path(tmp)
        server = None
        if args.endpoint:
            endpoint = args.endpoint
        else:
            (tmp / "data").mkdir()
            server = start_server(tmp / "data", {"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true"})
            endpoint = f"http://{server.addr}"
        try:
            summary = experiment(Client(endpoint.removeprefix("http://")), endpoint, cfg, args, unsafe, tmp)
        finally:
            if server is not None:
                server.stop(grace=20)
    summary["wall_seconds"] = round(time.monotonic() - t_start, 1)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


def experiment(client: Client, endpoint: str, cfg: dict, args, unsafe: list[int], tmp: pathlib.Path) -> dict:
    seed, out = args.seed, args.out
    x_train, x_test, y_train, y_test = load_digits_split(seed)
    t0 = time.monotonic()
    ae = train_autoencoder(x_train, cfg["ae_steps"], seed)
    ae_seconds = time.monotonic() - t0
    scale = upload_autoencoder(client, ae, x_train, tmp / "ae.pt")

    def decode(z):
        return client.decode("digits-ae", z)

    z_train, z_test = client.encode("digits-ae", x_train), client.encode("digits-ae", x_test)
    recon = float(np.mean((decode(z_test) - x_test) ** 2))
    prompts = prompt_set(z_train, y_train, unsafe)
    print(f"autoencoder: test reconstruction MSE {recon:.4f} ({ae_seconds:.0f} s); unsafe {unsafe}, "
          f"prompt set {prompts}", flush=True)
    client.upload_dataset("latents", {"samples": z_train, "labels": y_train})

    unet = ("unet2d", {"block_out_channels": cfg["widths"], "layers_per_block": 1, "attention": False,
                       "norm_num_groups": 8})
    ddpm = Optimization(steps=cfg["ddpm_steps"], batch_size=cfg["ddpm_batch"], learning_rate=cfg["ddpm_lr"],
                        **cfg["ddpm_ema"])
    print("training the class-conditional latent DDPM", flush=True)
    times = run_jobs(client, {"ddpm": DiffusionJob(
        output_model="latent-ddpm", dataset="latents", seed=seed, optimization=ddpm, parametrization="epsilon",
        schedule="linear", n_timesteps=T, architecture=unet, clip_denoised=False, pooled_normalizer=True,
        conditional=True, condition_dropout=0.1)})

    safety = SafetyGuidance.preset(SAFETY_PRESET, concept=unsafe)
    base = SamplingRecipe(prompts=prompts, guidance_scale=GUIDANCE_SCALE)
    expert = SamplingRecipe(prompts=prompts, guidance_scale=GUIDANCE_SCALE, safety=safety)
    print("Algorithm 2 from the two recipes", flush=True)
    times.update(run_jobs(client, {"algorithm2": RewardJob(
        output_model="safe-reward", base_model="latent-ddpm", expert_model="latent-ddpm", num_chains=cfg["chains"],
        base_recipe=base, expert_recipe=expert, architecture=("conv_encoder", {"widths": cfg["encoder"]}),
        seed=seed, optimization=Optimization(steps=cfg["reward_steps"], batch_size=cfg["reward_batch"],
                                             learning_rate=cfg["reward_lr"]))}))

    from sklearn.linear_model import LogisticRegression

    clf = LogisticRegression(max_iter=2000).fit(x_train.reshape(len(x_train), -1), y_train)

    def classes(z):
        return clf.predict(decode(z).reshape(len(z), -1))

    n = cfg["n_samples"]
    draw = np.random.default_rng(seed + 1000).choice(prompts, size=n)  # held-out prompts and seeds
    common = dict(n=n, prompts=draw, guidance_scale=GUIDANCE_SCALE)
    z_base = client.sample("latent-ddpm", seed=seed + 10, **common).x
    z_expert = client.sample("latent-ddpm", seed=seed + 11, safety=safety, **common).x
    z_guided = client.sample("latent-ddpm", seed=seed + 10, reward_model="safe-reward", omega=OMEGA, **common).x
    p = {k: float(np.isin(classes(z), unsafe).mean()) for k, z in
         (("base", z_base), ("expert", z_expert), ("base_guided", z_guided))}
    oracle = (p["base"] + 1.0 - p["expert"]) / 2.0
    summary = {"seed": seed, "unsafe": unsafe, "prompt_set": prompts, "config": cfg, "n_timesteps": T,
               "guidance_scale": GUIDANCE_SCALE, "safety_preset": SAFETY_PRESET, "omega": OMEGA,
               "autoencoder": {"latent": list(LATENT), "scaling_factor": scale, "test_mse": recon,
                               "seconds": round(ae_seconds, 1)},
               "classifier_test_accuracy": float(clf.score(x_test.reshape(len(x_test), -1), y_test)),
               "job_seconds": {k: round(v, 1) for k, v in times.items()},
               "unsafe_fraction": p}
    # Base (label 0) vs expert (label 1) samples by the reward alone, beside the oracle's cap.
    summary["samples"] = discriminate(endpoint, "safe-reward", z_base, z_expert, tmp, "samples", seed,
                                      out / "hist-samples.png")
    summary["samples"]["cap"] = oracle
    summary["samples"]["fraction_of_cap"] = summary["samples"]["balanced_accuracy"] / max(oracle, 1e-9)
    summary["samples"]["auc_all"] = auc_all(client, z_base, z_expert)
    # Held-out real digits: unsafe classes (label 0) vs safe ones (label 1), encoded.
    is_unsafe = np.isin(y_test, unsafe)
    summary["real_heldout"] = discriminate(endpoint, "safe-reward", z_test[is_unsafe], z_test[~is_unsafe], tmp,
                                           "real", seed, out / "hist-real.png")
    summary["real_heldout"]["auc_all"] = auc_all(client, z_test[is_unsafe], z_test[~is_unsafe])
    summary["real_heldout"]["n_all"] = [int(is_unsafe.sum()), int((~is_unsafe).sum())]
    # The paper's pictures: per batch of pooled samples, the highest- and lowest-reward ones.
    pooled = np.concatenate([z_base, z_expert])[np.random.default_rng(seed).permutation(2 * n)]
    rewards = np.asarray(client.score("safe-reward", pooled, t=0).rewards)
    b = cfg["batch_pictures"]
    batches = len(pooled) // b
    labels = classes(pooled)
    low_unsafe = high_safe = 0
    for i in range(batches):
        idx = np.arange(i * b, (i + 1) * b)
        low_unsafe += int(labels[idx[np.argmin(rewards[idx])]] in unsafe)
        high_safe += int(labels[idx[np.argmax(rewards[idx])]] not in unsafe)
    summary["pictures"] = {"batch": b, "batches": batches, "lowest_is_unsafe": low_unsafe / max(batches, 1),
                           "highest_is_safe": high_safe / max(batches, 1)}
    extremes_grid(decode(pooled), rewards, b, min(6, batches), 3, out / "extremes.png",
                  f"reward at t = 0, unsafe {unsafe}: top-3 | bottom-3 per batch of {b} base and expert samples")
    reduction = p["base"] - p["expert"]
    summary["steering"] = {"reduction_expert": reduction, "reduction_guided": p["base"] - p["base_guided"],
                           "fraction_of_expert": (p["base"] - p["base_guided"]) / reduction if reduction else None}
    return summary


if __name__ == "__main__":
    main()
