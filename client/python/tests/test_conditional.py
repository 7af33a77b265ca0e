"""Conditional denoisers and sampling recipes (issue 37 items 1 and 2).

A class-conditional diffusers ``UNet2DModel`` (``num_class_embeds``, the last label the null
one) and an embedding-conditional one (``class_embed_type="identity"``) with perturbed random
weights are imported with ``relreward model import --null-class``; relreward's Sample with
prompts, classifier-free guidance and Safe Latent Diffusion's guidance is replayed here in
float64 with diffusers' own UNet and schedulers and the formulas written out below from the
papers (Ho & Salimans; Schramowski et al. 2023, section 3), on relreward's noise
(``relreward_dev.rng``). Bar: 1e-5 per step, as test_ddim.py's.

Then: the same weights uploaded as a TorchScript module called ``forward(x, t, cond)`` sample
what the native import samples; a labelled samples dataset trains a class-conditional unet2d
with condition dropout (TrainDiffusion ``conditional``), whose manifest carries the null label;
and every conditioning field is refused by name where it does not apply.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
from diffusers import DDIMScheduler, DDPMScheduler, UNet2DModel  # noqa: E402
from diffusers.schedulers import scheduling_ddpm  # noqa: E402

from relreward import DiffusionJob, Optimization, SafetyGuidance  # noqa: E402
from relreward.errors import InvalidArgument, InvalidInput  # noqa: E402
from relreward_dev.rng import RelrewardRng  # noqa: E402
from relreward_dev.unet2d import float64_tables  # noqa: E402

T = 20
SHAPE = (2, 8, 8)
N = 2
CLASSES = 4  # labels 0..3, 3 the null label
TEMB = 32  # 4 * block_out_channels[0]: the identity embedding's width


def perturbed_unet(**conditioning) -> UNet2DModel:
    torch.manual_seed(21)
    unet = UNet2DModel(sample_size=8, in_channels=2, out_channels=2, block_out_channels=(8, 16), layers_per_block=1,
                       down_block_types=("DownBlock2D",) * 2, up_block_types=("UpBlock2D",) * 2, add_attention=False,
                       norm_num_groups=4, **conditioning)
    g = torch.Generator().manual_seed(22)
    with torch.no_grad():
        for p in unet.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.2)
    return unet.eval()


def scheduler() -> DDPMScheduler:
    return DDPMScheduler(num_train_timesteps=T, beta_schedule="linear", beta_start=0.001, beta_end=0.2,
                         prediction_type="epsilon", clip_sample=False)


@pytest.fixture(scope="module")
def models(server, tmp_path_factory):
    d = tmp_path_factory.mktemp("conditional")
    out = {}
    for name, conditioning, extra in (("cond-labels", {"num_class_embeds": CLASSES}, ["--null-class", "3"]),
                                      ("cond-no-null", {"num_class_embeds": CLASSES}, []),
                                      ("cond-embed", {"class_embed_type": "identity"}, []),
                                      ("cond-none", {}, [])):
        unet = perturbed_unet(**conditioning)
        folder = d / name
        unet.save_pretrained(folder)
        scheduler().save_pretrained(folder / "scheduler")
        server.cli("model", "import", str(folder), "--out", str(d / f"{name}.safetensors"), "--name", name, *extra)
        out[name] = unet
    return out


class Recipe:
    """The prediction of a recipe, written from the papers (not from the server's code): eps(c),
    eps(null) and the concept's mean eps, combined in float64."""

    def __init__(self, unet, prompts, null, scale, safety=None):
        self.unet, self.prompts, self.null, self.scale, self.safety = unet, prompts, null, scale, safety
        self.nu = None
        self.step = 0

    def eps(self, x, t, cond):
        with torch.no_grad():
            return self.unet(x.float(), torch.full((x.shape[0],), t), class_labels=cond).sample.double()

    def __call__(self, x, t):
        e_c, e_0 = self.eps(x, t, self.prompts), self.eps(x, t, self.null)
        guidance = e_c - e_0
        if self.safety is not None:
            s = self.safety
            e_s = torch.stack([self.eps(x, t, self.concept(c, x.shape[0])) for c in s["concept"]]).mean(0)
            diff = e_c - e_s
            mu = torch.where(diff < s["threshold"], torch.clamp(s["scale"] * diff.abs(), max=1.0),
                             torch.zeros_like(diff))
            gamma = mu * (e_s - e_0)
            if self.nu is not None:
                gamma = gamma + s["momentum_scale"] * self.nu
            self.nu = (s["momentum_beta"] * self.nu if self.nu is not None else 0) + (1 - s["momentum_beta"]) * gamma
            if self.step >= s["warmup"]:
                guidance = guidance - gamma
        self.step += 1
        return e_0 + self.scale * guidance

    @staticmethod
    def concept(c, n):
        return torch.full((n,), c) if np.isscalar(c) else torch.as_tensor(c).float().expand(n, -1)


def ddim_replay(recipe, seed, steps):
    sched = float64_tables(DDIMScheduler.from_config(scheduler().config, timestep_spacing="trailing"))
    sched.set_timesteps(steps)
    x = RelrewardRng(seed).randn((N, *SHAPE)).double()
    for t in sched.timesteps:
        x = sched.step(recipe(x, int(t)), int(t), x, eta=0.0).prev_sample
    return x.numpy()


def ddpm_replay(recipe, seed, monkeypatch):
    sched = float64_tables(DDPMScheduler.from_config(scheduler().config))
    sched.set_timesteps(T)
    rng = RelrewardRng(seed)
    x = rng.randn((N, *SHAPE)).double()
    monkeypatch.setattr(scheduling_ddpm, "randn_tensor", lambda shape, **kw: rng.randn(tuple(shape)).double())
    for t in sched.timesteps:
        x = sched.step(recipe(x, int(t)), int(t), x).prev_sample
    return x.numpy()


def assert_close(got, want, what, steps):
    err = np.abs(got.astype(np.float64) - want) / np.maximum(1.0, np.abs(want))
    assert err.max() < 1e-5 * steps, f"{what}: max relative difference {err.max():.3g}"


LABELS = torch.tensor([0, 1])
NULL = torch.tensor([3, 3])


def test_the_import_carries_the_conditioning(client, models):
    assert client.get_model("cond-labels").manifest.conditioning == {"kind": "labels", "num_classes": 4,
                                                                     "null_class": 3}
    assert client.get_model("cond-no-null").manifest.conditioning == {"kind": "labels", "num_classes": 4}
    assert client.get_model("cond-embed").manifest.conditioning == {"kind": "embedding", "dim": TEMB}


def test_conditional_sampling_equals_the_models_own_prediction(client, models):
    """guidance_scale unset: the conditional model alone, one label per sample."""
    unet = models["cond-labels"]
    got = client.sample("cond-labels", n=N, seed=4, sampler="ddim", steps=5, timestep_spacing="trailing", prompts=[0, 1]).x_normalized
    want = ddim_replay(Recipe(unet, LABELS, NULL, 1.0), 4, 5)
    assert_close(got, want, "conditional", 5)


@pytest.mark.parametrize("scale", [0.0, 3.0])
def test_classifier_free_guidance_equals_ho_and_salimans(client, models, scale):
    unet = models["cond-labels"]
    got = client.sample("cond-labels", n=N, seed=6, sampler="ddim", steps=5, timestep_spacing="trailing", prompts=[0, 1],
                        guidance_scale=scale).x_normalized
    assert_close(got, ddim_replay(Recipe(unet, LABELS, NULL, scale), 6, 5), f"CFG {scale}", 5)


@pytest.mark.parametrize("concept", [[2], [2, 1]])
def test_safety_guidance_equals_the_papers_equations(client, models, concept):
    unet = models["cond-labels"]
    safety = {"concept": concept, "scale": 5.0, "warmup": 2, "threshold": 0.0, "momentum_scale": 0.5,
              "momentum_beta": 0.7}
    sld = SafetyGuidance(concept, scale=5.0, warmup_steps=2, threshold=0.0, momentum_scale=0.5, momentum_beta=0.7)
    got = client.sample("cond-labels", n=N, seed=7, sampler="ddim", steps=6, timestep_spacing="trailing", prompts=[0, 1], guidance_scale=2.5,
                        safety=sld).x_normalized
    assert_close(got, ddim_replay(Recipe(unet, LABELS, NULL, 2.5, safety), 7, 6), f"SLD {concept}", 6)
    # It acts: without the safety term the samples differ.
    plain = client.sample("cond-labels", n=N, seed=7, sampler="ddim", steps=6, timestep_spacing="trailing", prompts=[0, 1],
                          guidance_scale=2.5).x_normalized
    assert np.abs(plain - got).max() > 1e-3


def test_ddpm_with_guidance_replays_with_the_servers_noise(client, models, monkeypatch):
    unet = models["cond-labels"]
    got = client.sample("cond-labels", n=N, seed=8, prompts=2, guidance_scale=2.0).x_normalized
    want = ddpm_replay(Recipe(unet, torch.tensor([2, 2]), NULL, 2.0), 8, monkeypatch)
    assert_close(got, want, "DDPM + CFG", T)


def test_embedding_conditioning_with_guidance(client, models):
    unet = models["cond-embed"]
    emb = np.random.default_rng(3).standard_normal((N, TEMB)).astype(np.float32)
    got = client.sample("cond-embed", n=N, seed=9, sampler="ddim", steps=4, timestep_spacing="trailing", prompts=emb,
                        guidance_scale=1.5).x_normalized
    recipe = Recipe(unet, torch.from_numpy(emb), torch.zeros(N, TEMB), 1.5)
    assert_close(got, ddim_replay(recipe, 9, 4), "embeddings + CFG", 4)


def test_a_conditional_torchscript_upload_samples_as_the_native_import(client, models, tmp_path):
    unet = models["cond-labels"]

    class Wrapped(torch.nn.Module):
        def __init__(self, unet):
            super().__init__()
            self.unet = unet

        def forward(self, x, t, cond):
            return self.unet(x, t, class_labels=cond).sample

    x, t, c = torch.zeros(3, *SHAPE), torch.tensor([0, 5, 19]), torch.tensor([0, 1, 3])
    module = torch.jit.trace(Wrapped(unet), (x, t, c), check_trace=False)
    path = tmp_path / "cond.pt"
    module.save(str(path))
    manifest = dict(client.get_model("cond-labels").manifest.as_dict())
    del manifest["architecture"]
    client.upload_model(path, "cond-ts", manifest)
    kw = dict(n=N, seed=10, sampler="ddim", steps=4, timestep_spacing="trailing", prompts=[1, 0], guidance_scale=2.0,
              safety=SafetyGuidance.preset("medium", 2))
    np.testing.assert_allclose(client.sample("cond-ts", **kw).x_normalized,
                               client.sample("cond-labels", **kw).x_normalized, atol=1e-4)


def test_conditioning_is_refused_by_name(client, models):
    with pytest.raises(InvalidArgument, match=r"prompts: missing; model 'cond-labels' is conditional"):
        client.sample("cond-labels", n=1)
    with pytest.raises(InvalidArgument, match=r"prompts\.labels\[1\]: 7 is outside the labels 0\.\.4 of model 'cond-labels'"):
        client.sample("cond-labels", n=2, prompts=[0, 7])
    with pytest.raises(InvalidArgument, match=r"prompts: 3 conditions for n = 2"):
        client.sample("cond-labels", n=2, prompts=[0, 1, 2])
    with pytest.raises(InvalidArgument, match=r"prompts\.embeddings: model .cond-labels. takes class labels"):
        client.sample("cond-labels", n=1, prompts=np.zeros(4, np.float32))
    # Checked before one prompt is repeated n times (here 10000 x 4 MB).
    with pytest.raises(InvalidArgument, match=r"prompts\.embeddings: model .cond-labels. takes class labels"):
        client.sample("cond-labels", n=10_000, prompts=np.zeros(1_000_000, np.float32))
    with pytest.raises(InvalidArgument, match=r"prompts\.embeddings: width 5, but model .cond-embed. takes embeddings of width 32"):
        client.sample("cond-embed", n=1, prompts=np.zeros(5, np.float32))
    with pytest.raises(InvalidArgument, match=r"guidance_scale: 2 needs the unconditional prediction"):
        client.sample("cond-no-null", n=1, prompts=0, guidance_scale=2.0)
    with pytest.raises(InvalidArgument, match=r"safety\.momentum_beta: 1 must be in \[0, 1\)"):
        client.sample("cond-labels", n=1, prompts=0, safety=SafetyGuidance(2, momentum_beta=1.0))
    with pytest.raises(InvalidArgument, match=r"safety\.concept\.labels\[0\]: 9"):
        client.sample("cond-labels", n=1, prompts=0, safety=SafetyGuidance(9))
    with pytest.raises(InvalidArgument, match=r"prompts: model 'cond-none' is unconditional"):
        client.sample("cond-none", n=1, prompts=0)
    with pytest.raises(InvalidArgument, match=r"guidance_scale: model 'cond-none' is unconditional"):
        client.sample("cond-none", n=1, guidance_scale=2.0)
    with pytest.raises(InvalidInput, match="safety preset 'loud'"):
        SafetyGuidance.preset("loud", 2)


@pytest.fixture(scope="module")
def labelled(client):
    """64 one-channel 8x8 items of four classes (a bright quadrant each), labels 0..3."""
    rng = np.random.default_rng(0)
    labels = np.arange(64) % 4
    x = rng.normal(0, 0.1, (64, 1, 8, 8)).astype(np.float32)
    for i, c in enumerate(labels):
        x[i, 0, (c // 2) * 4:(c // 2) * 4 + 4, (c % 2) * 4:(c % 2) * 4 + 4] += 1.0
    client.upload_dataset("cond-quadrants", {"samples": x, "labels": labels})
    client.upload_dataset("cond-unlabelled", x)
    return x, labels


def test_conditional_training_learns_the_null_label_and_samples(client, labelled):
    ds = client.get_dataset("cond-quadrants")
    assert [a.name for a in ds.arrays] == ["samples", "labels"]
    spec = DiffusionJob(output_model="cond-trained", dataset="cond-quadrants", conditional=True,
                        condition_dropout=0.2, n_timesteps=10, schedule="cosine",
                        architecture=("unet2d", {"block_out_channels": [8, 16], "attention": False,
                                                 "norm_num_groups": 4}),
                        optimization=Optimization(steps=3, batch_size=8, eval_every=3), seed=1)
    job = client.wait_job(client.submit_job(spec).id)
    assert job.state.name == "SUCCEEDED", job.error
    m = client.get_model("cond-trained")
    assert m.manifest.conditioning == {"kind": "labels", "num_classes": 5, "null_class": 4}
    assert client.get_job(job.id).spec.condition_dropout == pytest.approx(0.2)
    s = client.sample("cond-trained", n=4, seed=1, prompts=[0, 1, 2, 3], guidance_scale=2.0)
    assert s.x.shape == (4, 1, 8, 8) and np.isfinite(s.x).all()


def test_conditional_training_is_refused_by_name(client, labelled):
    arch = ("unet2d", {"block_out_channels": [8, 16], "attention": False, "norm_num_groups": 4})
    with pytest.raises(InvalidArgument, match=r"spec\.diffusion\.conditional: dataset 'cond-unlabelled' has no"):
        client.submit_job(DiffusionJob(output_model="x1", dataset="cond-unlabelled", conditional=True,
                                       architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.diffusion\.condition_dropout: applies to conditional"):
        client.submit_job(DiffusionJob(output_model="x2", dataset="cond-quadrants", condition_dropout=0.1,
                                       architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.diffusion\.condition_dropout: 1 must be in \[0, 1\)"):
        client.submit_job(DiffusionJob(output_model="x3", dataset="cond-quadrants", conditional=True,
                                       condition_dropout=1.0, architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.diffusion\.num_classes: 2, but dataset 'cond-quadrants'"):
        client.submit_job(DiffusionJob(output_model="x4", dataset="cond-quadrants", conditional=True,
                                       num_classes=2, architecture=arch))
    with pytest.raises(InvalidArgument, match=r"conditioning: the native mlp takes no condition"):
        client.submit_job(DiffusionJob(output_model="x5", dataset="cond-quadrants", conditional=True,
                                       architecture=("mlp", {"hidden": [16]})))


def test_labels_are_checked_at_upload(client):
    x = np.zeros((4, 1, 2, 2), np.float32)
    with pytest.raises(ValueError, match="labels have dtype float64"):
        client.upload_dataset("bad-labels", {"samples": x, "labels": np.zeros(4)})
    with pytest.raises(ValueError, match="labels hold -1"):
        client.upload_dataset("bad-labels", {"samples": x, "labels": np.array([0, -1, 0, 0])})
    with pytest.raises(ValueError, match=r"labels have shape \(3,\)"):
        client.upload_dataset("bad-labels", {"samples": x, "labels": np.array([0, 1, 0])})


def test_algorithm_2_extracts_a_reward_from_two_recipes_of_one_model(client, models):
    """Safe Latent Diffusion's setting: one conditional model, base = classifier-free guidance,
    expert = the same plus safety guidance away from label 2; the reward is learned from the two
    recipes' chains alone."""
    from relreward import RewardJob, SamplingRecipe
    base = SamplingRecipe(prompts=[0, 1, 2], guidance_scale=2.0)
    expert = SamplingRecipe(prompts=[0, 1, 2], guidance_scale=2.0, safety=SafetyGuidance.preset("strong", 2))
    spec = RewardJob(output_model="cond-rho", base_model="cond-labels", expert_model="cond-labels", num_chains=8,
                     base_recipe=base, expert_recipe=expert,
                     architecture=("conv_encoder", {"widths": [8, 16]}),
                     optimization=Optimization(steps=3, batch_size=8, eval_every=3), seed=2)
    job = client.wait_job(client.submit_job(spec).id)
    assert job.state.name == "SUCCEEDED", job.error
    stored = client.get_job(job.id).spec
    assert stored.expert_recipe.safety.warmup_steps == 7 and stored.base_recipe.prompts == [0, 1, 2]
    x = np.random.default_rng(1).standard_normal((3, *SHAPE)).astype(np.float32)
    assert np.isfinite(client.score("cond-rho", x, t=[0, 5, 19]).rewards).all()
    # Reward-guided sampling of the base recipe (classifier guidance on top of CFG).
    guided = client.sample("cond-labels", n=2, seed=3, prompts=[0, 1], guidance_scale=2.0,
                           reward_model="cond-rho", omega=0.1)
    assert guided.rewards.shape == (2,)


def test_recipes_are_refused_by_name(client, models):
    from relreward import RewardJob, SamplingRecipe
    arch = ("conv_encoder", {"widths": [8, 16]})
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.base_recipe: missing; model 'cond-labels' is conditional"):
        client.submit_job(RewardJob(output_model="r1", base_model="cond-labels", expert_model="cond-labels",
                                    architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.expert_recipe: model 'cond-none' is unconditional"):
        client.submit_job(RewardJob(output_model="r2", base_model="cond-none", expert_model="cond-none",
                                    expert_recipe=SamplingRecipe([0]), architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.base_recipe: applies to models_only"):
        client.submit_job(RewardJob(output_model="r3", base_model="cond-labels", expert_model="cond-labels",
                                    datasets=["cond-quadrants"], base_recipe=SamplingRecipe([0]),
                                    expert_recipe=SamplingRecipe([0]), architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.expert_recipe\.prompts\.labels\[0\]: 5 is outside"):
        client.submit_job(RewardJob(output_model="r4", base_model="cond-labels", expert_model="cond-labels",
                                    base_recipe=SamplingRecipe([0]), expert_recipe=SamplingRecipe([5]),
                                    architecture=arch))
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.base_recipe\.guidance_scale: 2 needs the unconditional"):
        client.submit_job(RewardJob(output_model="r5", base_model="cond-no-null", expert_model="cond-no-null",
                                    base_recipe=SamplingRecipe([0], guidance_scale=2.0),
                                    expert_recipe=SamplingRecipe([0]), architecture=arch))


def test_a_named_recipe_stands_for_its_model(client, server, models, tmp_path):
    """CreateRecipe (item 2): a named recipe samples bit for bit what the same recipe given inline
    samples (sample i under prompt i mod k), is a model of kind "recipe" everywhere (get, list,
    the CLI's JSON, download), pins its model (which cannot be deleted meanwhile) and refuses,
    naming the field, what cannot stand."""
    import json

    from relreward import SamplingRecipe
    from relreward.errors import AlreadyExists, FailedPrecondition, NotFound

    from test_results import _same_values

    safety = SafetyGuidance.preset("strong", 2)
    made = client.create_recipe("cond-safe", "cond-labels", SamplingRecipe([0, 1], guidance_scale=2.0, safety=safety),
                                description="CFG 2 away from label 2")
    assert (made.kind, made.format, made.parameter_count) == ("recipe", "recipe", 0)
    assert made.recipe.model == "cond-labels" and made.recipe.model_sha256 == client.get_model("cond-labels").sha256
    assert made.recipe.recipe.prompts == [0, 1] and made.recipe.recipe.guidance_scale == 2.0
    assert made.recipe.recipe.safety == SafetyGuidance.preset("strong", [2])
    assert client.get_model("cond-safe") == made
    assert "cond-safe" in [m.name for m in client.list_models("recipe")]
    assert "cond-safe" not in [m.name for m in client.list_models("diffusion")]
    assert not _same_values(made.as_dict(), server.cli_json("model", "show", "cond-safe"))

    kw = dict(n=3, seed=9, sampler="ddim", steps=5, timestep_spacing="trailing")
    named = client.sample("cond-safe", **kw)
    inline = client.sample("cond-labels", prompts=[0, 1, 0], guidance_scale=2.0, safety=safety, **kw)
    np.testing.assert_array_equal(named.x, inline.x)
    assert named.prompts.tolist() == [0, 1, 0] and inline.prompts.tolist() == [0, 1, 0]
    ddpm = dict(n=2, seed=3)
    np.testing.assert_array_equal(client.sample("cond-safe", **ddpm).x,
                                  client.sample("cond-labels", prompts=[0, 1], guidance_scale=2.0, safety=safety,
                                                **ddpm).x)
    # Embedding prompts cycle the same way.
    emb = np.random.default_rng(5).standard_normal((2, TEMB)).astype(np.float32)
    client.create_recipe("cond-embed-cfg", "cond-embed", SamplingRecipe(emb, guidance_scale=1.5))
    got = client.sample("cond-embed-cfg", **kw)
    want = client.sample("cond-embed", prompts=emb[[0, 1, 0]], guidance_scale=1.5, **kw)
    np.testing.assert_array_equal(got.x, want.x)
    np.testing.assert_array_equal(got.prompts, emb[[0, 1, 0]])

    # A prompt dataset: a samples dataset's labels, or its samples as embeddings.
    client.upload_dataset("cond-prompt-labels", {"samples": np.zeros((3, *SHAPE), np.float32),
                                                 "labels": np.array([1, 0, 1])})
    client.upload_dataset("cond-prompt-emb", emb)
    from_ds = client.create_recipe("cond-from-ds", "cond-labels", SamplingRecipe("cond-prompt-labels", 2.0))
    assert from_ds.recipe.recipe.prompts == [1, 0, 1] and from_ds.recipe.prompt_dataset == "cond-prompt-labels"
    emb_ds = client.create_recipe("cond-emb-ds", "cond-embed", SamplingRecipe("cond-prompt-emb", 1.5))
    np.testing.assert_array_equal(emb_ds.recipe.recipe.prompts, emb)
    np.testing.assert_array_equal(client.sample("cond-emb-ds", **kw).x, got.x)
    assert not _same_values(from_ds.as_dict(), server.cli_json("model", "show", "cond-from-ds"))
    with pytest.raises(NotFound, match=r"recipe\.prompts\.dataset: dataset 'cond-nope' not found"):
        client.create_recipe("r-x", "cond-labels", SamplingRecipe("cond-nope"))
    with pytest.raises(InvalidArgument, match=r"prompts\.dataset: a prompt dataset is read only where a recipe"):
        client.sample("cond-labels", prompts="cond-prompt-labels")

    downloaded = client.download_model("cond-safe", tmp_path / "recipe")
    assert downloaded.path.name == "recipe.json" and json.loads(downloaded.path.read_text()) == downloaded.manifest
    assert downloaded.manifest["model"] == "cond-labels"

    with pytest.raises(InvalidArgument, match=r"prompts: model 'cond-safe' is a recipe over 'cond-labels'"):
        client.sample("cond-safe", prompts=[0])
    with pytest.raises(InvalidArgument, match=r"guidance_scale: model 'cond-safe' is a recipe"):
        client.sample("cond-safe", guidance_scale=1.0)
    with pytest.raises(FailedPrecondition, match=r"name: model 'cond-labels' is sampled by recipe 'cond-"):
        client.delete_model("cond-labels")
    with pytest.raises(AlreadyExists, match=r"name: model 'cond-safe' already exists"):
        client.create_recipe("cond-safe", "cond-labels", SamplingRecipe([0]))
    with pytest.raises(NotFound, match=r"model: model 'cond-nope' not found"):
        client.create_recipe("r-x", "cond-nope", SamplingRecipe([0]))
    with pytest.raises(FailedPrecondition, match=r"model: 'cond-safe' is a sampling recipe"):
        client.create_recipe("r-x", "cond-safe", SamplingRecipe([0]))
    with pytest.raises(InvalidArgument, match=r"recipe: model 'cond-none' is unconditional"):
        client.create_recipe("r-x", "cond-none", SamplingRecipe([0]))
    with pytest.raises(InvalidArgument, match=r"recipe\.prompts\.labels\[1\]: 7 is outside the labels 0\.\.4"):
        client.create_recipe("r-x", "cond-labels", SamplingRecipe([0, 7]))
    with pytest.raises(InvalidArgument, match=r"recipe\.guidance_scale: 3 needs the unconditional prediction"):
        client.create_recipe("r-x", "cond-no-null", SamplingRecipe([0], guidance_scale=3.0))
    with pytest.raises(InvalidArgument, match=r"recipe\.safety\.momentum_beta: 1"):
        client.create_recipe("r-x", "cond-labels", SamplingRecipe([0], safety=SafetyGuidance(2, momentum_beta=1.0)))
    with pytest.raises(InvalidArgument, match=r"name: "):
        client.create_recipe("Bad Name", "cond-labels", SamplingRecipe([0]))
    with pytest.raises(InvalidInput, match=r"recipe: expected a relreward.SamplingRecipe"):
        client.create_recipe("r-x", "cond-labels", [0, 1])
    with pytest.raises(FailedPrecondition, match=r"model 'cond-safe' is a sampling recipe, not a reward"):
        client.score("cond-safe", np.zeros((1, *SHAPE), np.float32), t=0)
    assert "r-x" not in [m.name for m in client.list_models()]
    # The CLI registers the same recipe from flags.
    cli = server.cli_json("model", "recipe", "cond-safe-cli", "--model", "cond-labels", "--labels", "0,1",
                          "--guidance-scale", "2", "--safety-concept", "2", "--safety-preset", "strong")
    assert cli["recipe"] == made.as_dict()["recipe"]


def test_algorithm_2_through_named_recipes_equals_the_jobs_own(client, server, models):
    """A reward job naming recipes as base_model / expert_model runs the chains the same recipes
    given in the job run (same seed: the same reward, bit for bit), and the reward remembers how
    each side was sampled (Model.reward, OIP ModelConfig)."""
    from relreward import RewardJob, SamplingRecipe
    base = SamplingRecipe(prompts=[0, 1, 2], guidance_scale=2.0)
    expert = SamplingRecipe(prompts=[0, 1, 2], guidance_scale=2.0, safety=SafetyGuidance.preset("strong", 2))
    client.create_recipe("cond-cfg2", "cond-labels", base)
    client.create_recipe("cond-sld2", "cond-labels", expert)
    common = dict(num_chains=8, architecture=("conv_encoder", {"widths": [8, 16]}),
                  optimization=Optimization(steps=3, batch_size=8, eval_every=3), seed=4)
    jobs = [client.submit_job(RewardJob(output_model="rho-named", base_model="cond-cfg2", expert_model="cond-sld2",
                                        **common)),
            client.submit_job(RewardJob(output_model="rho-inline", base_model="cond-labels",
                                        expert_model="cond-labels", base_recipe=base, expert_recipe=expert, **common))]
    for job in jobs:
        job = client.wait_job(job.id)
        assert job.state.name == "SUCCEEDED", job.error
    x = np.random.default_rng(2).standard_normal((4, *SHAPE)).astype(np.float32)
    t = [0, 4, 11, 19]
    np.testing.assert_array_equal(client.score("rho-named", x, t=t).rewards, client.score("rho-inline", x, t=t).rewards)
    named, inline = client.get_model("rho-named").reward, client.get_model("rho-inline").reward
    assert (named.base_model, named.expert_model) == ("cond-cfg2", "cond-sld2")
    assert named.base_recipe == inline.base_recipe and named.expert_recipe == inline.expert_recipe
    assert named.expert_recipe.model == "cond-labels" and named.expert_recipe.recipe.safety.warmup_steps == 7
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.base_recipe: set, but base_model 'cond-cfg2' is a recipe"):
        client.submit_job(RewardJob(output_model="rho-x", base_model="cond-cfg2", expert_model="cond-sld2",
                                    base_recipe=base, **common))
    client.upload_dataset("cond-items", np.zeros((4, *SHAPE), np.float32))
    with pytest.raises(InvalidArgument, match=r"spec\.reward\.base_model \(recipe 'cond-cfg2'\): with_dataset"):
        client.submit_job(RewardJob(output_model="rho-x", base_model="cond-cfg2", expert_model="cond-sld2",
                                    datasets=["cond-items"], architecture=("conv_encoder", {"widths": [8, 16]})))
    # A job's prompt dataset is read at submission: the stored spec holds its labels.
    client.upload_dataset("cond-prompt-set", {"samples": np.zeros((2, *SHAPE), np.float32), "labels": np.array([2, 0])})
    pending = client.submit_job(RewardJob(output_model="rho-ds", base_model="cond-labels", expert_model="cond-sld2",
                                          base_recipe=SamplingRecipe("cond-prompt-set", 2.0),
                                          **{**common, "optimization": Optimization(steps=100000, batch_size=8)}))
    assert client.get_job(pending.id).spec.base_recipe.prompts == [2, 0]
    client.cancel_job(pending.id)
    grpcclient = pytest.importorskip("tritonclient.grpc")
    with grpcclient.InferenceServerClient(server.addr) as oip:
        params = oip.get_model_config("rho-named").config.parameters
    assert params["base_model"].string_value == "cond-cfg2"
    import json
    recipe = json.loads(params["expert_recipe"].string_value)
    assert recipe["model"] == "cond-labels" and recipe["recipe"]["safety"]["warmup_steps"] == 7


def test_samples_and_their_labels_upload_alike_from_the_cli_and_the_package(server, client, tmp_path):
    """An .npz of latents and class labels, as `relreward encode` writes one: the samples array is
    the only one besides `labels`, and the labels travel with it (int16 sent as int64), from the
    CLI as from the package: the same stored arrays, the same digest."""
    path = tmp_path / "latents.npz"
    x = np.random.default_rng(3).standard_normal((6, 1, 2, 2)).astype(np.float32)
    np.savez(path, x=x, labels=np.array([0, 2, 1, 1, 0, 3], np.int16))
    py = client.upload_dataset("labelled-py", path, kind="samples")
    server.cli("dataset", "upload", str(path), "--name", "labelled-cli")
    cli = client.get_dataset("labelled-cli")
    assert py.sha256 == cli.sha256
    for d in (py, cli):
        arrays = {a.name: (a.dtype, list(a.shape)) for a in d.arrays}
        assert arrays == {"samples": ("float32", [6, 1, 2, 2]), "labels": ("int64", [6])}, arrays
