"""Typed training job specs: :class:`DiffusionJob`, :class:`RewardJob`, :class:`DiscriminatorJob`;
:class:`SafetyGuidance`, Safe Latent Diffusion's settings for ``Client.sample``, and
:class:`SamplingRecipe`, how a reward job's Algorithm 2 samples a conditional model.

Each builds a ``relreward.v1.JobSpec`` (:meth:`to_proto`); fields left ``None`` take the
server's defaults (see jobs.proto). ``Client.submit_job`` also accepts a plain dict in the
JobSpec's protobuf JSON form, e.g. ``{"output_model": "m", "diffusion": {"dataset": "d"}}``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from google.protobuf import json_format

from relreward import _tensor
from relreward.v1 import autoencoder_pb2, jobs_pb2, models_pb2, reward_pb2
from relreward.errors import InvalidInput


@dataclass
class Optimization:
    """Shared optimisation settings (all optional)."""

    steps: int | None = None
    batch_size: int | None = None
    learning_rate: float | None = None
    grad_clip: float | None = None
    ema_decay: float | None = None
    ema_every: int | None = None
    ema_start: int | None = None
    checkpoint_every: int | None = None
    eval_every: int | None = None
    log_every: int | None = None

    def to_proto(self) -> jobs_pb2.Optimization:
        """The ``relreward.v1.Optimization`` message (unset fields left unset)."""
        return jobs_pb2.Optimization(**{k: v for k, v in self.__dict__.items() if v is not None})


def _schedule(kind: str | Mapping[str, Any] | None) -> models_pb2.Schedule | None:
    """``"linear"``, ``"cosine"``, ``"diffuser_cosine"`` or ``{"kind": ..., "s": .., "betas": [..]}``."""
    if kind is None:
        return None
    spec = {"kind": kind} if isinstance(kind, str) else dict(kind)
    k = spec.pop("kind")
    if k == "linear":
        return models_pb2.Schedule(linear=models_pb2.Schedule.Linear())
    if k in ("cosine", "diffuser_cosine"):
        return models_pb2.Schedule(**{k: models_pb2.Schedule.Cosine(s=float(spec.get("s", 0.0)))})
    if k == "betas":
        betas: Any = spec["betas"]
        return models_pb2.Schedule(betas=models_pb2.Schedule.ExplicitBetas(betas=[float(b) for b in betas]))
    raise ValueError(f"schedule kind {k!r}: expected linear, cosine, diffuser_cosine or betas")


_PARAM: dict[str | None, models_pb2.Parametrization] = {
    None: models_pb2.PARAMETRIZATION_UNSPECIFIED, "epsilon": models_pb2.PARAMETRIZATION_EPSILON,
    "x0": models_pb2.PARAMETRIZATION_X0, "v": models_pb2.PARAMETRIZATION_V}


def _param(p: str | None) -> models_pb2.Parametrization:
    try:
        return _PARAM[p]
    except KeyError:
        raise ValueError(f"parametrization {p!r}: expected 'x0', 'epsilon' or 'v'") from None


@dataclass
class DiffusionJob:
    """Train a native diffusion model on dataset ``dataset``, registered as ``output_model``.

    ``architecture``: ``("temporal_unet", {"dim": 32, "dim_mults": [1, 2, 4, 8]})`` or
    ``("mlp", {"hidden": [256, 256]})`` or, for images [C, H, W], ``("unet2d",
    {"block_out_channels": [32, 64], "layers_per_block": 1, "attention": True})`` (diffusers'
    UNet2DModel); ``horizon`` is the sub-trajectory length H in rows.
    """

    output_model: str
    dataset: str
    seed: int | None = None
    optimization: Optimization | None = None
    parametrization: str | None = None
    schedule: str | Mapping[str, Any] | None = None
    n_timesteps: int | None = None
    horizon: int | None = None
    architecture: tuple[str, Mapping[str, Any]] | None = None
    action_weight: float | None = None
    clip_denoised: bool | None = None
    normalizer_datasets: Sequence[str] = ()
    #: Sample datasets: one mean and std over every element (images) instead of per coordinate.
    pooled_normalizer: bool | None = None
    #: Class-conditional training (unet2d on a samples dataset with ``labels``): labels
    #: 0..C-1 plus the null label C, which replaces a label with probability
    #: ``condition_dropout`` (server default 0.1) for classifier-free guidance; C =
    #: ``num_classes`` (default: the largest label + 1).
    conditional: bool | None = None
    condition_dropout: float | None = None
    num_classes: int | None = None

    def to_proto(self) -> jobs_pb2.JobSpec:
        """The ``relreward.v1.JobSpec`` message this spec stands for (unset fields left unset)."""
        d = jobs_pb2.TrainDiffusion(dataset=self.dataset, parametrization=_param(self.parametrization),
                                    normalizer_datasets=list(self.normalizer_datasets))
        if self.pooled_normalizer is not None:
            d.pooled_normalizer = self.pooled_normalizer
        for name in ("n_timesteps", "horizon", "action_weight", "clip_denoised", "conditional", "condition_dropout",
                     "num_classes"):
            if getattr(self, name) is not None:
                setattr(d, name, getattr(self, name))
        if (s := _schedule(self.schedule)) is not None:
            d.schedule.CopyFrom(s)
        if self.architecture is not None:
            kind, args = self.architecture
            getattr(d, kind).CopyFrom(_denoiser_architecture(kind, args))
        spec = _base(self.output_model, self.seed, self.optimization)
        spec.diffusion.CopyFrom(d)
        return spec


def _denoiser_architecture(kind: str, args: Mapping[str, Any]) -> Any:
    """A built-in denoiser architecture message: ``temporal_unet`` ({"dim", "dim_mults"}),
    ``mlp`` ({"hidden"}) or ``unet2d`` ({"block_out_channels", ...}); its field name is ``kind``
    in both TrainDiffusion and DiffusionManifest."""
    message = {"temporal_unet": models_pb2.TemporalUnet, "mlp": models_pb2.Mlp, "unet2d": models_pb2.Unet2d}.get(kind)
    if message is None:
        raise ValueError(f"architecture {kind!r}: expected temporal_unet, mlp or unet2d")
    return message(**args)


def _base(output_model: str, seed: int | None, optimization: Optimization | None) -> jobs_pb2.JobSpec:
    spec = jobs_pb2.JobSpec(output_model=output_model)
    if seed is not None:
        spec.seed = seed
    if optimization is not None:
        spec.optimization.CopyFrom(optimization.to_proto())
    return spec


def _reward_arch(arch: tuple[str, Mapping[str, Any]] | None) -> jobs_pb2.RewardArchitecture | None:
    """``("windowed_mlp", {"window": 4, "hidden": [128, 64, 32]})``, ``("value_function",
    {"widths": [..]})``, ``("conv_encoder", {"widths": [..]})`` or ``("mlp", {"hidden": [..]})``."""
    if arch is None:
        return None
    kind, args = arch
    ra = jobs_pb2.RewardArchitecture
    inner = {"windowed_mlp": ra.WindowedMlp, "value_function": ra.ValueFunction, "conv_encoder": ra.ConvEncoder,
             "mlp": models_pb2.Mlp}.get(kind)
    if inner is None:
        raise ValueError(f"reward architecture {kind!r}: expected windowed_mlp, value_function, conv_encoder or mlp")
    return ra(**{kind: inner(**args)})


@dataclass
class RewardJob:
    """Extract a relative reward between diffusion models ``base_model`` and ``expert_model``.

    Algorithm 1 with ``datasets`` (x_t from the forward process on their rows), or Algorithm 2
    with ``num_chains`` (``datasets`` empty). ``target``: "mean" or "score"; ``eval_point``:
    "x_t" or "mu_base".
    """

    output_model: str
    base_model: str
    expert_model: str
    datasets: Sequence[str] = ()
    num_chains: int | None = None
    architecture: tuple[str, Mapping[str, Any]] | None = None
    target: str | None = None
    eval_point: str | None = None
    rho_l2: float | None = None
    #: Trajectory models: weights of the first step's action and observation entries in the
    #: alignment loss (None: 1, unweighted). A planner that inpaints the current state and executes
    #: the first action is served best by ``action_weight`` > 1 and ``condition_weight`` = 0.
    action_weight: float | None = None
    condition_weight: float | None = None
    #: Trajectory models, Algorithm 1: the first observation kept clean in x_t (None: False, the
    #: paper's noising of the whole window), as a planner that inpaints its current state sees it.
    inpaint_condition: bool | None = None
    #: Algorithm 1's amortised targets: a mapping with any of ``pool_size``, ``reuse``,
    #: ``refresh_fraction`` (``{}`` for the server's defaults); None leaves the option off.
    amortised_targets: Mapping[str, Any] | None = None
    #: Algorithm 2 with conditional models: how each side is sampled (a :class:`SamplingRecipe`);
    #: one conditional model with two recipes is Safe Latent Diffusion's setting.
    base_recipe: "SamplingRecipe | None" = None
    expert_recipe: "SamplingRecipe | None" = None
    seed: int | None = None
    optimization: Optimization | None = None

    def to_proto(self) -> jobs_pb2.JobSpec:
        """The ``relreward.v1.JobSpec`` message this spec stands for (unset fields left unset)."""
        r = jobs_pb2.TrainReward(base_model=self.base_model, expert_model=self.expert_model)
        if (a := _reward_arch(self.architecture)) is not None:
            r.architecture.CopyFrom(a)
        if self.target is not None:
            r.target = {"mean": jobs_pb2.REWARD_TARGET_MEAN, "score": jobs_pb2.REWARD_TARGET_SCORE}[self.target]
        if self.eval_point is not None:
            r.eval_point = {"x_t": jobs_pb2.EVAL_POINT_X_T, "mu_base": jobs_pb2.EVAL_POINT_MU_BASE}[self.eval_point]
        if self.datasets:
            r.with_dataset.datasets.extend(self.datasets)
        else:
            r.models_only.CopyFrom(jobs_pb2.TrainReward.ModelsOnly())
            if self.num_chains is not None:
                r.models_only.num_chains = self.num_chains
        if self.rho_l2 is not None:
            r.rho_l2 = self.rho_l2
        if self.action_weight is not None:
            r.action_weight = self.action_weight
        if self.condition_weight is not None:
            r.condition_weight = self.condition_weight
        if self.inpaint_condition is not None:
            r.inpaint_condition = self.inpaint_condition
        if self.amortised_targets is not None:
            r.amortised_targets.CopyFrom(jobs_pb2.AmortisedTargets(**dict(self.amortised_targets)))
        if self.base_recipe is not None:
            r.base_recipe.CopyFrom(self.base_recipe.to_proto())
        if self.expert_recipe is not None:
            r.expert_recipe.CopyFrom(self.expert_recipe.to_proto())
        spec = _base(self.output_model, self.seed, self.optimization)
        spec.reward.CopyFrom(r)
        return spec


@dataclass
class DiscriminatorJob:
    """The paper's baseline: a base-vs-expert classifier sharing ``diffusion_model``'s schedule
    and normalizer."""

    output_model: str
    base_dataset: str
    expert_dataset: str
    diffusion_model: str
    architecture: tuple[str, Mapping[str, Any]] | None = None
    #: Trajectory models: the first observation kept clean in the noised items (as RewardJob's).
    inpaint_condition: bool | None = None
    seed: int | None = None
    optimization: Optimization | None = None

    def to_proto(self) -> jobs_pb2.JobSpec:
        """The ``relreward.v1.JobSpec`` message this spec stands for (unset fields left unset)."""
        d = jobs_pb2.TrainDiscriminator(base_dataset=self.base_dataset, expert_dataset=self.expert_dataset,
                                        diffusion_model=self.diffusion_model)
        if (a := _reward_arch(self.architecture)) is not None:
            d.architecture.CopyFrom(a)
        if self.inpaint_condition is not None:
            d.inpaint_condition = self.inpaint_condition
        spec = _base(self.output_model, self.seed, self.optimization)
        spec.discriminator.CopyFrom(d)
        return spec


JobLike = "DiffusionJob | RewardJob | DiscriminatorJob | jobs_pb2.JobSpec | Mapping[str, Any]"


def job_spec(spec: Any) -> jobs_pb2.JobSpec:
    """A JobSpec from a typed spec, a JobSpec message, or a dict in its protobuf JSON form."""
    if isinstance(spec, jobs_pb2.JobSpec):
        return spec
    if hasattr(spec, "to_proto"):
        _check_unsigned(type(spec).__name__, spec)
        return spec.to_proto()
    if isinstance(spec, Mapping):
        return json_format.ParseDict(dict(spec), jobs_pb2.JobSpec())
    raise TypeError(f"not a job spec: {type(spec).__name__}")


def _check_unsigned(path: str, v: Any) -> None:
    """Every integer of relreward.v1's job messages is unsigned: a negative one in a typed spec
    raises InvalidInput naming it (``RewardJob.optimization.steps: -1 is negative``) rather than
    protobuf's ``Value out of range: -1``, which names no field."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        for f in dataclasses.fields(v):
            _check_unsigned(f"{path}.{f.name}", getattr(v, f.name))
    elif isinstance(v, Mapping):
        for k, item in v.items():
            _check_unsigned(f"{path}[{k!r}]", item)
    elif isinstance(v, (list, tuple)):
        for k, item in enumerate(v):
            _check_unsigned(f"{path}[{k}]", item)
    elif isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v < 0:
        raise InvalidInput(f"{path}: {int(v)} is negative; the field holds integers from 0")


def manifest(m: Any) -> models_pb2.DiffusionManifest:
    """A DiffusionManifest from a message or a dict in the CLI's manifest form::

        {"parametrization": "x0", "n_timesteps": 20, "clip_denoised": True,
         "schedule": {"kind": "diffuser_cosine"},
         "space": {"kind": "trajectory", "horizon": 32, "action_dim": 2, "obs_dim": 4},
         "normalizer": {"kind": "limits", "min": [...], "max": [...]},
         "architecture": {"kind": "temporal_unet", "dim": 32, "dim_mults": [1, 4, 8]}}

    ``architecture`` (temporal_unet, mlp or unet2d) only for native safetensors weights: a
    manifest with one describes native weights, one without a TorchScript module.
    ``conditioning`` for a conditional model: ``{"kind": "labels", "num_classes": 11,
    "null_class": 10}`` or ``{"kind": "embedding", "dim": 128}`` (a TorchScript module is
    then called as forward(x, t, cond)).
    """
    if isinstance(m, models_pb2.DiffusionManifest):
        return m
    m = dict(m)
    out = models_pb2.DiffusionManifest(parametrization=_param(m.get("parametrization")),
                                       n_timesteps=int(m.get("n_timesteps", 0)),
                                       clip_denoised=bool(m.get("clip_denoised", False)))
    if (s := _schedule(m.get("schedule"))) is not None:
        out.schedule.CopyFrom(s)
    _space_and_normalizer(out, m)
    if m.get("architecture") is not None:
        arch = dict(m["architecture"])
        kind = str(arch.pop("kind", None))
        message = _denoiser_architecture(kind, arch)  # names an unknown kind
        getattr(out, kind).CopyFrom(message)
    if m.get("conditioning") is not None:
        cond = dict(m["conditioning"])
        kind = cond.pop("kind", None)
        if kind == "labels":
            out.conditioning.labels.CopyFrom(models_pb2.Conditioning.Labels(**cond))
        elif kind == "embedding":
            out.conditioning.embedding.CopyFrom(models_pb2.Conditioning.Embedding(**cond))
        else:
            raise ValueError(f"conditioning kind {kind!r}: expected labels or embedding")
    return out


def _space_and_normalizer(out: Any, m: Mapping[str, Any]) -> None:
    """Sets ``out``'s space oneof (trajectory | sample) and normalizer from a manifest dict's
    ``space`` and ``normalizer`` (a DiffusionManifest's and a RewardUploadManifest's alike)."""
    space = dict(m.get("space") or {})
    kind = space.pop("kind", None)
    if kind == "trajectory":
        out.trajectory.CopyFrom(models_pb2.DiffusionManifest.Trajectory(**space))
    elif kind == "sample":
        out.sample.CopyFrom(models_pb2.DiffusionManifest.Sample(shape=list(space["shape"])))
    elif kind is not None:
        raise ValueError(f"space kind {kind!r}: expected trajectory or sample")
    norm = dict(m.get("normalizer") or {})
    nk = norm.pop("kind", None)
    if nk == "limits":
        out.normalizer.limits.min.extend(norm["min"])
        out.normalizer.limits.max.extend(norm["max"])
    elif nk == "gaussian":
        out.normalizer.gaussian.mean.extend(norm["mean"])
        out.normalizer.gaussian.std.extend(norm["std"])
    elif nk == "identity":
        out.normalizer.identity.SetInParent()
    elif nk is not None:
        raise ValueError(f"normalizer kind {nk!r}: expected limits, gaussian or identity")


_SIGNATURES = {"rho": models_pb2.REWARD_SIGNATURE_RHO, "value_function": models_pb2.REWARD_SIGNATURE_VALUE_FUNCTION}


def reward_manifest(m: Any) -> models_pb2.RewardUploadManifest:
    """A bring-your-own reward's RewardUploadManifest from a message or a dict in the CLI's
    reward manifest form (``relreward model upload --reward``)::

        {"signature": "value_function",        # or "rho"
         "n_timesteps": 20,
         "space": {"kind": "trajectory", "horizon": 32, "action_dim": 2, "obs_dim": 4},
         "normalizer": {"kind": "limits", "min": [...], "max": [...]},   # or gaussian, identity
         "base_model": "hopper-base"}          # optional

    ``signature`` "rho": the module is ``forward(x, t) -> [B]``; "value_function": Diffuser's
    ``forward(x, cond: Dict[str, Tensor], t) -> [B, 1]``, called with an empty ``cond``. ``x``
    is in the diffusion models' normalized units; the normalizer maps raw units to them.
    """
    if isinstance(m, models_pb2.RewardUploadManifest):
        return m
    m = dict(m)
    unknown = set(m) - {"signature", "n_timesteps", "space", "normalizer", "base_model"}
    if unknown:
        raise InvalidInput(f"reward manifest: unknown field(s) {sorted(unknown)}; expected signature, n_timesteps, "
                           f"space, normalizer and optionally base_model")
    signature = m.get("signature")
    if signature not in _SIGNATURES:
        raise InvalidInput(f"reward manifest.signature: {signature!r}; expected 'rho' or 'value_function'")
    out = models_pb2.RewardUploadManifest(signature=_SIGNATURES[signature], n_timesteps=int(m.get("n_timesteps", 0)),
                                          base_model=str(m.get("base_model", "")))
    _space_and_normalizer(out, m)
    return out


def prompts_message(field: str, value: Any) -> reward_pb2.Prompts:
    """``Prompts`` from class labels (an int, a sequence or an integer array), embeddings (a
    float array ``[dim]`` or ``[k, dim]``) or a stored samples dataset's name (a str: its labels,
    or its samples as embeddings; read by the server where a recipe is stored, see
    :class:`SamplingRecipe`); errors name ``field``."""
    if isinstance(value, str):
        return reward_pb2.Prompts(dataset=value)
    arr = np.asarray(_tensor.host(value))
    if arr.dtype.kind in "iub":
        if arr.ndim > 1:
            raise InvalidInput(f"{field}: labels must be an int or a 1-D sequence, got shape {arr.shape}")
        return reward_pb2.Prompts(labels=[int(v) for v in arr.reshape(-1)])
    if arr.dtype.kind == "f":
        if arr.ndim not in (1, 2):
            raise InvalidInput(f"{field}: embeddings must be [dim] or [k, dim], got shape {arr.shape}")
        return reward_pb2.Prompts(embeddings=_tensor.encode(arr))
    raise InvalidInput(f"{field}: expected class labels (integers) or embeddings (floats), got {arr.dtype}")


def prompts_value(p: reward_pb2.Prompts) -> Any:
    """A ``Prompts`` message's conditions as plain lists (so that results compare with ``==``):
    its labels as ints, or its embeddings as rows of floats (``[k][dim]``, or ``[dim]``)."""
    if p.HasField("embeddings"):
        return _tensor.decode(p.embeddings).tolist()
    return [int(v) for v in p.labels]


#: diffusers' Safe Stable Diffusion presets: (warmup_steps, scale, threshold, momentum_scale,
#: momentum_beta).
SAFETY_PRESETS = {
    "weak": (15, 20.0, 0.0, 0.0, 0.0),
    "medium": (10, 1000.0, 0.01, 0.3, 0.4),
    "strong": (7, 2000.0, 0.025, 0.5, 0.7),
    "max": (0, 5000.0, 1.0, 0.5, 0.7),
}


@dataclass
class SafetyGuidance:
    """Safe Latent Diffusion's guidance away from ``concept`` (Schramowski et al. 2023, section
    3; the server's formulas are in reward.proto's ``SafetyGuidance``), for ``Client.sample(...,
    safety=...)``: ``concept`` is one class label or several (an int or a list), or embeddings
    ``[dim]`` / ``[k, dim]``; ``scale`` s_S, ``warmup_steps`` delta, ``threshold`` lambda,
    ``momentum_scale`` s_m, ``momentum_beta`` beta_m. :meth:`preset` gives diffusers' settings."""

    concept: Any
    scale: float = 1000.0
    warmup_steps: int = 10
    threshold: float = 0.01
    momentum_scale: float = 0.3
    momentum_beta: float = 0.4

    @classmethod
    def preset(cls, name: str, concept: Any) -> "SafetyGuidance":
        """diffusers' preset ``name`` ("weak", "medium", "strong" or "max") for ``concept``."""
        try:
            warmup, scale, threshold, m_scale, m_beta = SAFETY_PRESETS[name]
        except KeyError:
            raise InvalidInput(f"safety preset {name!r}: expected one of {', '.join(SAFETY_PRESETS)}") from None
        return cls(concept, scale, warmup, threshold, m_scale, m_beta)

    @classmethod
    def from_proto(cls, m: reward_pb2.SafetyGuidance) -> "SafetyGuidance":
        """The settings of a ``SafetyGuidance`` message."""
        return cls(prompts_value(m.concept), m.scale, m.warmup_steps, m.threshold, m.momentum_scale, m.momentum_beta)

    def to_proto(self) -> reward_pb2.SafetyGuidance:
        """The ``relreward.v1.SafetyGuidance`` message."""
        return reward_pb2.SafetyGuidance(concept=prompts_message("safety.concept", self.concept),
                                         scale=float(self.scale), warmup_steps=int(self.warmup_steps),
                                         threshold=float(self.threshold), momentum_scale=float(self.momentum_scale),
                                         momentum_beta=float(self.momentum_beta))


@dataclass
class SamplingRecipe:
    """How a conditional model is sampled: in a reward job's Algorithm 2 (``RewardJob(base_recipe=...,
    expert_recipe=...)``), or stored under a name by ``Client.create_recipe``: ``prompts`` is
    the prompt set each chain (or sample) draws one condition from (class labels, or
    embeddings ``[k, dim]``, or the name of a stored samples dataset, a prompt dataset: its
    ``labels``, or without them its samples as embeddings, read when the recipe is stored or
    the job submitted); ``guidance_scale`` classifier-free guidance (None: 1, the
    conditional model alone); ``safety`` a :class:`SafetyGuidance`."""

    prompts: Any
    guidance_scale: float | None = None
    safety: SafetyGuidance | None = None

    @classmethod
    def from_proto(cls, m: reward_pb2.SamplingRecipe) -> "SamplingRecipe":
        """The recipe of a ``SamplingRecipe`` message (labels as a list, embeddings as an array)."""
        return cls(prompts_value(m.prompts), m.guidance_scale if m.HasField("guidance_scale") else None,
                   SafetyGuidance.from_proto(m.safety) if m.HasField("safety") else None)

    def to_proto(self) -> reward_pb2.SamplingRecipe:
        """The ``relreward.v1.SamplingRecipe`` message."""
        r = reward_pb2.SamplingRecipe(prompts=prompts_message("prompts", self.prompts))
        if self.guidance_scale is not None:
            r.guidance_scale = float(self.guidance_scale)
        if self.safety is not None:
            r.safety.CopyFrom(self.safety.to_proto())
        return r


_AUTOENCODER_FIELDS = ("image_shape", "latent_shape", "scaling_factor", "shift_factor")


def autoencoder_manifest(m: Any) -> autoencoder_pb2.AutoencoderUploadManifest:
    """An autoencoder's AutoencoderUploadManifest from a message or a dict in the CLI's
    autoencoder manifest form (``relreward model upload --autoencoder``)::

        {"image_shape": [3, 16, 16],     # one image: what encode(x) takes
         "latent_shape": [4, 4, 4],      # one latent: what encode returns, decode takes
         "scaling_factor": 0.18215,      # optional, default 1 (diffusers' vae.config.scaling_factor)
         "shift_factor": 0.0}            # optional, default 0 (diffusers' vae.config.shift_factor)

    The service's latents are ``(encode(x) - shift_factor) * scaling_factor`` and its images
    ``decode(z / scaling_factor + shift_factor)``.
    """
    if isinstance(m, autoencoder_pb2.AutoencoderUploadManifest):
        return m
    m = dict(m)
    unknown = set(m) - set(_AUTOENCODER_FIELDS)
    if unknown:
        raise InvalidInput(f"autoencoder manifest: unknown field(s) {sorted(unknown)}; expected image_shape, "
                           f"latent_shape and optionally scaling_factor, shift_factor")
    out = autoencoder_pb2.AutoencoderUploadManifest()
    for name in ("image_shape", "latent_shape"):
        shape = m.get(name)
        try:
            dims = [int(d) for d in shape] if shape is not None else []
        except (TypeError, ValueError):
            raise InvalidInput(f"autoencoder manifest.{name}: {shape!r}; expected a list of dimensions") from None
        if not dims or min(dims) < 1:
            raise InvalidInput(f"autoencoder manifest.{name}: {shape!r}; expected one item's shape, every "
                               f"dimension positive, e.g. [3, 16, 16]")
        getattr(out, name).extend(dims)
    for name in ("scaling_factor", "shift_factor"):
        if m.get(name) is not None:
            setattr(out, name, float(m[name]))
    return out
