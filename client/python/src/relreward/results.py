"""What the client's methods return: the package's own types, never protobuf messages.

As qdrant-client does, every public method of :class:`relreward.Client` and
:class:`relreward.AsyncClient` answers with dataclasses of this module (numpy arrays inside
the rewards' results). Their field names and values are the ones the ``relreward`` CLI prints
with ``--json``: ``relreward model show NAME --json`` and ``client.get_model(NAME).as_dict()``
agree key for key (times aside, which the CLI truncates). A job's spec is the exception: it
comes back as the typed spec it stands for (:class:`relreward.DiffusionJob`, ...), which
``submit_job`` takes back. Enumerations are lowercase strings as the CLI
writes them (``model.kind == "reward"``); a job's state is one :class:`JobState` everywhere
(``get_job``, ``list_jobs``, ``wait_job`` and every event of ``watch_job``).

Each top-level result keeps the message it was read from as ``.proto`` (left out of ``==``
and the repr), for a caller that needs a field this package does not map yet.

- datasets: :class:`Dataset` (:class:`ArrayInfo`, :class:`ArrayStats`, :class:`EpisodeInfo`)
- models: :class:`Model` (:class:`Manifest` with :class:`Schedule`, :class:`Space` and
  :class:`Normalizer`; :class:`RewardInfo`; :class:`AutoencoderInfo`; :class:`Provenance`);
  ``model.item_shape`` and
  ``model.n_timesteps`` say what a model takes, whatever its kind
- jobs: :class:`Job`, :class:`JobState`, :class:`JobEvent`
- rewards: :class:`ScoreResult`, :class:`GradientResult`, :class:`Sample`, :class:`SampleBatch`
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Iterator, Mapping

import numpy as np

from relreward import _tensor, specs
from relreward.v1 import datasets_pb2, jobs_pb2, models_pb2, tensor_pb2

#: The cosine schedules' offset s when the wire says 0 (unset), as the server and the CLI
#: apply it (proto/src/schema/manifest.rs DEFAULT_COSINE_S).
DEFAULT_COSINE_S = 0.008


# --------------------------------------------------------------------------------------------
# Helpers: enum names, times, plain values


def _enum_name(enum_type: Any, value: int, prefix: str) -> str:
    """``MODEL_KIND_REWARD`` -> ``"reward"``: the CLI's spelling of a wire enum value
    ("unspecified" for 0 and for a number this package's stubs do not know)."""
    try:
        return enum_type.Name(value).removeprefix(prefix).lower()
    except ValueError:
        return "unspecified"


def _time(message: Any, name: str) -> _dt.datetime | None:
    """A Timestamp field as an aware UTC datetime, or None when unset."""
    return getattr(message, name).ToDatetime(tzinfo=_dt.timezone.utc) if message.HasField(name) else None


def _optional(message: Any, name: str) -> Any:
    """An ``optional`` scalar field's value, or None when unset."""
    return getattr(message, name) if message.HasField(name) else None


def _floats(values: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _ints(values: Any) -> tuple[int, ...]:
    return tuple(int(v) for v in values)


def _short(values: tuple[float, ...] | None) -> str:
    """A vector in a repr: every value up to 6, else the first and last three and the count."""
    if values is None:
        return "None"
    if len(values) <= 6:
        return repr(values)
    head = ", ".join(f"{v:.6g}" for v in values[:3])
    tail = ", ".join(f"{v:.6g}" for v in values[-3:])
    return f"({head}, ..., {tail}) [{len(values)} values]"


def _plain(value: Any) -> Any:
    """``value`` as plain JSON-like Python: results and specs as dicts (their ``_omit_none``
    fields left out when None, as the CLI leaves them out), tuples as lists, a
    :class:`JobState` as its string, times as RFC 3339 UTC strings."""
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, _dt.datetime):
        return value.astimezone(_dt.timezone.utc).isoformat().replace("+00:00", "Z")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        skip = getattr(value, "_omit_none", ())
        out = {}
        for f in dataclasses.fields(value):
            if f.name == "proto":
                continue
            v = getattr(value, f.name)
            if v is None and f.name in skip:
                continue
            out[f.name] = _plain(v)
        return out
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


class _Plain:
    """``as_dict()`` for the dataclasses of this module."""

    def as_dict(self) -> dict[str, Any]:
        """This result as plain Python values in the CLI's ``--json`` form (``json.dumps`` takes
        it; times are RFC 3339 UTC strings, tuples lists)."""
        return _plain(self)


# --------------------------------------------------------------------------------------------
# Datasets


@dataclass(frozen=True)
class ArrayStats(_Plain):
    """Per-coordinate statistics of a float array (the dataset's FULL view)."""

    min: tuple[float, ...]
    max: tuple[float, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]

    def __repr__(self) -> str:
        return (f"ArrayStats(min={_short(self.min)}, max={_short(self.max)}, mean={_short(self.mean)}, "
                f"std={_short(self.std)})")


@dataclass(frozen=True)
class ArrayInfo(_Plain):
    """One array of a dataset: ``dtype`` ("float32", "bool", ...), ``shape`` (rows first) and,
    in the FULL view (``get_dataset``) of a float array, its ``stats``."""

    name: str
    dtype: str
    shape: tuple[int, ...]
    stats: ArrayStats | None = None

    @classmethod
    def from_proto(cls, a: datasets_pb2.ArrayInfo) -> ArrayInfo:
        """The array of an ``ArrayInfo`` message."""
        s = a.stats
        stats = (ArrayStats(_floats(s.min), _floats(s.max), _floats(s.mean), _floats(s.std)) if a.HasField("stats")
                 else None)
        return cls(a.spec.name, _enum_name(tensor_pb2.Dtype, a.spec.dtype, "DTYPE_"), _ints(a.spec.shape), stats)


@dataclass(frozen=True)
class EpisodeInfo(_Plain):
    """How a trajectories dataset splits into episodes."""

    count: int
    min_length: int
    max_length: int
    mean_length: float


@dataclass(frozen=True)
class Dataset(_Plain):
    """A stored dataset, as ``relreward dataset show NAME --json`` prints it.

    ``kind``: "trajectories" or "samples"; ``num_rows``; ``sha256`` and ``size_bytes`` of the
    stored payload; ``created_at`` (UTC); ``episodes`` (trajectories); ``arrays`` in stored
    order, with per-coordinate ``stats`` from ``get_dataset`` (``list_datasets`` leaves them
    out). ``proto``: the ``Dataset`` message it was read from.
    """

    name: str
    kind: str
    num_rows: int
    sha256: str
    size_bytes: int
    created_at: _dt.datetime | None
    description: str
    episodes: EpisodeInfo | None
    arrays: tuple[ArrayInfo, ...]
    proto: datasets_pb2.Dataset | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_proto(cls, d: datasets_pb2.Dataset) -> Dataset:
        """The dataset of a ``Dataset`` message."""
        e = d.episodes
        episodes = EpisodeInfo(e.count, e.min_length, e.max_length, e.mean_length) if d.HasField("episodes") else None
        return cls(d.name, _enum_name(datasets_pb2.DatasetKind, d.kind, "DATASET_KIND_"), d.num_rows, d.sha256,
                   d.size_bytes, _time(d, "created_at"), d.description, episodes,
                   tuple(ArrayInfo.from_proto(a) for a in d.arrays), d)


# --------------------------------------------------------------------------------------------
# Models


@dataclass(frozen=True)
class Schedule(_Plain):
    """A DDPM noise schedule: ``kind`` "linear", "cosine", "diffuser_cosine" (with ``s``, the
    offset actually used: 0.008 when none was given) or "betas" (with ``betas``)."""

    _omit_none: ClassVar[tuple[str, ...]] = ("s", "betas")

    kind: str
    s: float | None = None
    betas: tuple[float, ...] | None = None

    def __repr__(self) -> str:
        extra = f", s={self.s}" if self.s is not None else ""
        extra += f", betas={_short(self.betas)}" if self.betas is not None else ""
        return f"Schedule(kind={self.kind!r}{extra})"

    @classmethod
    def from_proto(cls, s: models_pb2.Schedule) -> Schedule | None:
        """The schedule of a ``Schedule`` message (None when it sets no kind)."""
        kind = s.WhichOneof("kind")
        if kind in ("cosine", "diffuser_cosine"):
            offset = getattr(s, kind).s
            return cls(kind, s=offset if offset != 0 else DEFAULT_COSINE_S)
        if kind == "betas":
            return cls(kind, betas=_floats(s.betas.betas))
        return cls(kind) if kind is not None else None


@dataclass(frozen=True)
class Space(_Plain):
    """What a diffusion model generates: ``kind`` "trajectory" (``horizon`` rows of
    ``action_dim + obs_dim``) or "sample" (items of ``shape``); ``item_shape`` is either's
    shape of one item."""

    _omit_none: ClassVar[tuple[str, ...]] = ("horizon", "action_dim", "obs_dim", "shape")

    kind: str
    horizon: int | None = None
    action_dim: int | None = None
    obs_dim: int | None = None
    shape: tuple[int, ...] | None = None

    def __repr__(self) -> str:
        fields = [f"{n}={getattr(self, n)!r}" for n in ("kind", *self._omit_none) if getattr(self, n) is not None]
        return f"Space({', '.join(fields)})"

    @property
    def item_shape(self) -> tuple[int, ...]:
        """One item's shape: ``(horizon, action_dim + obs_dim)``, or the sample ``shape``."""
        if self.kind == "trajectory":
            return (int(self.horizon or 0), int(self.action_dim or 0) + int(self.obs_dim or 0))
        return tuple(self.shape or ())

    @classmethod
    def from_proto(cls, m: models_pb2.DiffusionManifest) -> Space | None:
        """The space of a ``DiffusionManifest`` message (None when it sets none)."""
        kind = m.WhichOneof("space")
        if kind == "trajectory":
            t = m.trajectory
            return cls(kind, horizon=t.horizon, action_dim=t.action_dim, obs_dim=t.obs_dim)
        if kind == "sample":
            return cls(kind, shape=_ints(m.sample.shape))
        return None


@dataclass(frozen=True)
class Normalizer(_Plain):
    """How raw units map to the model's: ``kind`` "limits" (``min``, ``max``: to [-1, 1]),
    "gaussian" (``mean``, ``std``) or "identity", per coordinate."""

    _omit_none: ClassVar[tuple[str, ...]] = ("min", "max", "mean", "std")

    kind: str
    min: tuple[float, ...] | None = None
    max: tuple[float, ...] | None = None
    mean: tuple[float, ...] | None = None
    std: tuple[float, ...] | None = None

    def __repr__(self) -> str:
        parts = [f"kind={self.kind!r}"] + [f"{n}={_short(getattr(self, n))}" for n in ("min", "max", "mean", "std")
                                            if getattr(self, n) is not None]
        return f"Normalizer({', '.join(parts)})"

    @classmethod
    def from_proto(cls, n: Any) -> Normalizer:
        """An absent normalizer means identity, as the CLI prints it."""
        kind = n.WhichOneof("kind")
        if kind == "limits":
            return cls(kind, min=_floats(n.limits.min), max=_floats(n.limits.max))
        if kind == "gaussian":
            return cls(kind, mean=_floats(n.gaussian.mean), std=_floats(n.gaussian.std))
        return cls("identity")


def _message_fields(message: Any) -> dict[str, Any]:
    """Every field of a small architecture message: repeated ones as lists, unset optional
    ones as None (the CLI's ``architecture_json``)."""
    out: dict[str, Any] = {}
    for f in message.DESCRIPTOR.fields:
        v = getattr(message, f.name)
        if f.is_repeated:
            out[f.name] = list(v)
        elif f.has_presence and not message.HasField(f.name):
            out[f.name] = None
        else:
            out[f.name] = v
    return out


@dataclass(frozen=True)
class Manifest(_Plain):
    """A diffusion model's manifest, the CLI's manifest-file form: ``parametrization`` ("x0",
    "epsilon" or None), ``schedule``, ``n_timesteps`` (T), ``clip_denoised``, ``space``,
    ``normalizer``, and for native weights ``architecture`` (``{"kind": "temporal_unet",
    "dim": 32, "dim_mults": [1, 4, 8]}``, ...; None for a TorchScript module), and for a
    conditional model ``conditioning`` (``{"kind": "labels", "num_classes": 11, "null_class":
    10}`` or ``{"kind": "embedding", "dim": 128}``; None for an unconditional one).

    ``upload_model`` takes one as its ``manifest`` (``dataclasses.replace`` makes a changed
    copy); ``as_dict()`` is the dict form it also takes."""

    _omit_none: ClassVar[tuple[str, ...]] = ("architecture", "conditioning")

    parametrization: str | None
    schedule: Schedule | None
    n_timesteps: int
    clip_denoised: bool
    space: Space | None
    normalizer: Normalizer
    architecture: Mapping[str, Any] | None = None
    conditioning: Mapping[str, Any] | None = None

    @classmethod
    def from_proto(cls, m: models_pb2.DiffusionManifest) -> Manifest:
        """The manifest of a ``DiffusionManifest`` message."""
        p = _enum_name(models_pb2.Parametrization, m.parametrization, "PARAMETRIZATION_")
        arch_kind = m.WhichOneof("architecture")
        arch = {"kind": arch_kind, **_message_fields(getattr(m, arch_kind))} if arch_kind else None
        cond = None
        if m.HasField("conditioning") and (kind := m.conditioning.WhichOneof("kind")):
            fields = _message_fields(getattr(m.conditioning, kind))
            cond = {"kind": kind, **{k: v for k, v in fields.items() if v is not None}}
        return cls(None if p == "unspecified" else p,
                   Schedule.from_proto(m.schedule) if m.HasField("schedule") else None,
                   m.n_timesteps, m.clip_denoised, Space.from_proto(m), Normalizer.from_proto(m.normalizer), arch,
                   cond)

    def to_proto(self) -> models_pb2.DiffusionManifest:
        """The ``DiffusionManifest`` message of these fields (what ``upload_model`` sends)."""
        return specs.manifest(self.as_dict())


@dataclass(frozen=True)
class RewardInfo(_Plain):
    """A reward's or discriminator's specifics: the models it was extracted from, its
    ``architecture`` in words and ``window`` (0: not windowed), the ``input_shape`` of one
    item (``[H, D]`` or the sample shape), ``n_timesteps`` (T: valid t are 0 .. T-1) and the
    ``normalizer`` its inputs go through."""

    base_model: str
    expert_model: str
    architecture: str
    window: int
    input_shape: tuple[int, ...]
    n_timesteps: int
    normalizer: Normalizer
    #: How each side was sampled when it was a sampling recipe (Algorithm 2 over a conditional
    #: model: a named recipe, or the job's own), else None.
    base_recipe: RecipeInfo | None = None
    expert_recipe: RecipeInfo | None = None


@dataclass(frozen=True)
class RecipeInfo(_Plain):
    """A sampling recipe bound to its model: the conditional diffusion ``model`` it samples (its
    sha256 ``model_sha256`` when the recipe was made), ``recipe``, a
    :class:`relreward.SamplingRecipe` (prompts, guidance_scale, safety), and the stored dataset
    its prompts were read from (``prompt_dataset``, None when given as values)."""

    model: str
    model_sha256: str
    recipe: specs.SamplingRecipe
    prompt_dataset: str | None = None

    @classmethod
    def from_proto(cls, m: models_pb2.RecipeInfo) -> RecipeInfo:
        """The recipe of a ``RecipeInfo`` message."""
        return cls(m.model, m.model_sha256, specs.SamplingRecipe.from_proto(m.recipe), m.prompt_dataset or None)


@dataclass(frozen=True)
class AutoencoderInfo(_Plain):
    """An autoencoder's contract: the shape of one image (what ``encode`` takes) and of one
    latent, and the latent scaling the service applies: latents are ``(encode(x) -
    shift_factor) * scaling_factor``, images ``decode(z / scaling_factor + shift_factor)``."""

    image_shape: tuple[int, ...]
    latent_shape: tuple[int, ...]
    scaling_factor: float
    shift_factor: float


@dataclass(frozen=True)
class Provenance(_Plain):
    """Where a model came from: ``source`` "uploaded", or "trained" by job ``job_id`` from
    ``datasets`` and ``models`` with ``final_loss``."""

    source: str
    job_id: str | None = None
    datasets: tuple[str, ...] = ()
    models: tuple[str, ...] = ()
    final_loss: float | None = None

    @classmethod
    def from_proto(cls, p: models_pb2.Provenance) -> Provenance | None:
        """The provenance of a ``Provenance`` message (None when it sets no source)."""
        if p.WhichOneof("source") == "trained":
            t = p.trained
            return cls("trained", t.job_id, tuple(t.datasets), tuple(t.models), t.final_loss)
        if p.WhichOneof("source") == "uploaded":
            return cls("uploaded")
        return None


@dataclass(frozen=True)
class Model(_Plain):
    """A stored model, as ``relreward model show NAME --json`` prints it.

    ``kind``: "diffusion", "reward", "discriminator", "autoencoder" or "recipe"; ``format``:
    "native" (built-in architecture, safetensors weights), "torchscript" or "recipe" (JSON);
    ``manifest`` for a diffusion model, ``reward`` for a reward or discriminator,
    ``autoencoder`` for an autoencoder, ``recipe`` (a :class:`RecipeInfo`) for a named sampling
    recipe (``Client.create_recipe``). ``item_shape`` and ``n_timesteps`` say what it
    takes whatever its kind: ``x`` is ``[B, *model.item_shape]`` and ``t`` in
    ``0 .. model.n_timesteps - 1``. ``proto``: the ``Model`` message it was read from.
    """

    name: str
    kind: str
    format: str
    parameter_count: int
    sha256: str
    size_bytes: int
    created_at: _dt.datetime | None
    description: str
    provenance: Provenance | None
    manifest: Manifest | None
    reward: RewardInfo | None
    autoencoder: AutoencoderInfo | None = None
    recipe: RecipeInfo | None = None
    proto: models_pb2.Model | None = field(default=None, repr=False, compare=False)

    @property
    def item_shape(self) -> tuple[int, ...] | None:
        """The shape of one item (``[H, D]`` for trajectories, the sample shape otherwise): a
        reward's ``input_shape``, a diffusion model's space; None when the record has neither."""
        if self.reward is not None:
            return self.reward.input_shape
        if self.manifest is not None and self.manifest.space is not None:
            return self.manifest.space.item_shape
        return None

    def trajectory_window(self) -> tuple[int, int]:
        """``(H, D)`` of a reward (or discriminator) over trajectory windows ``[H, action_dim +
        obs_dim]``, what the RL wrapper and relabelling need; InvalidInput naming ``model``
        otherwise."""
        from relreward.errors import InvalidInput  # errors imports nothing from here

        if self.reward is None:
            raise InvalidInput(f"model: {self.name!r} is a {self.kind} model; a reward or discriminator is needed")
        shape = tuple(self.item_shape or ())
        if len(shape) != 2:
            raise InvalidInput(f"model: {self.name!r} scores items of shape {list(shape)}, not trajectories "
                               "[H, action_dim + obs_dim]")
        return int(shape[0]), int(shape[1])

    @property
    def n_timesteps(self) -> int | None:
        """T, the number of diffusion steps (valid ``t``: 0 .. T-1), of any kind of model."""
        if self.reward is not None:
            return self.reward.n_timesteps
        if self.manifest is not None:
            return self.manifest.n_timesteps
        return None

    @classmethod
    def from_proto(cls, m: models_pb2.Model) -> Model:
        """The model of a ``Model`` message."""
        r = m.reward
        def recipe_of(holder: Any, name: str) -> RecipeInfo | None:
            return RecipeInfo.from_proto(getattr(holder, name)) if holder.HasField(name) else None

        reward = (RewardInfo(r.base_model, r.expert_model, r.architecture, r.window, _ints(r.input_shape),
                             r.n_timesteps, Normalizer.from_proto(r.normalizer), recipe_of(r, "base_recipe"),
                             recipe_of(r, "expert_recipe")) if m.HasField("reward") else None)
        a = m.autoencoder
        autoencoder = (AutoencoderInfo(_ints(a.image_shape), _ints(a.latent_shape), a.scaling_factor, a.shift_factor)
                       if m.HasField("autoencoder") else None)
        return cls(m.name, _enum_name(models_pb2.ModelKind, m.kind, "MODEL_KIND_"),
                   _enum_name(models_pb2.ModelFormat, m.format, "MODEL_FORMAT_"), m.parameter_count, m.sha256,
                   m.size_bytes, _time(m, "created_at"), m.description,
                   Provenance.from_proto(m.provenance) if m.HasField("provenance") else None,
                   Manifest.from_proto(m.manifest) if m.HasField("manifest") else None, reward, autoencoder,
                   recipe_of(m, "recipe"), m)


# --------------------------------------------------------------------------------------------
# Jobs


class JobState(str, enum.Enum):
    """A job's state, one type on ``get_job``, ``list_jobs`` and every event: a string enum
    that equals the CLI's spelling (``job.state == "succeeded"``)."""

    UNSPECIFIED = "unspecified"
    PENDING = "pending"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    def __str__(self) -> str:
        return self.value

    @property
    def terminal(self) -> bool:
        """SUCCEEDED, FAILED and CANCELLED: a job never leaves them."""
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)

    @classmethod
    def from_proto(cls, state: int) -> JobState:
        """The state of a wire ``JobState`` number (UNSPECIFIED for one this package does not know)."""
        return cls(_enum_name(jobs_pb2.JobState, state, "JOB_STATE_"))

    def to_proto(self) -> int:
        """The wire ``JobState`` number."""
        return jobs_pb2.JobState.Value("JOB_STATE_" + self.name)


def _spec_of(s: jobs_pb2.JobSpec) -> specs.DiffusionJob | specs.RewardJob | specs.DiscriminatorJob | None:
    """The typed spec a JobSpec message stands for (the inverse of their ``to_proto``), so
    ``client.submit_job(job.spec)`` submits the same spec again."""
    opt = None
    if s.HasField("optimization"):
        opt = specs.Optimization(**{f.name: _optional(s.optimization, f.name)
                                    for f in dataclasses.fields(specs.Optimization)})
    base = dict(output_model=s.output_model, seed=_optional(s, "seed"), optimization=opt)
    kind = s.WhichOneof("kind")
    if kind == "diffusion":
        d = s.diffusion
        p = _enum_name(models_pb2.Parametrization, d.parametrization, "PARAMETRIZATION_")
        schedule: Any = None
        if d.HasField("schedule"):
            sk = d.schedule.WhichOneof("kind")
            if sk in ("cosine", "diffuser_cosine") and getattr(d.schedule, sk).s != 0:
                schedule = {"kind": sk, "s": getattr(d.schedule, sk).s}
            elif sk == "betas":
                schedule = {"kind": sk, "betas": list(d.schedule.betas.betas)}
            else:
                schedule = sk
        arch = d.WhichOneof("architecture")
        return specs.DiffusionJob(
            dataset=d.dataset, parametrization=None if p == "unspecified" else p, schedule=schedule,
            n_timesteps=_optional(d, "n_timesteps"), horizon=_optional(d, "horizon"),
            architecture=(arch, _set_fields(getattr(d, arch))) if arch else None,
            action_weight=_optional(d, "action_weight"), clip_denoised=_optional(d, "clip_denoised"),
            normalizer_datasets=list(d.normalizer_datasets), pooled_normalizer=_optional(d, "pooled_normalizer"),
            conditional=_optional(d, "conditional"), condition_dropout=_optional(d, "condition_dropout"),
            num_classes=_optional(d, "num_classes"), **base)
    if kind == "reward":
        r = s.reward
        target = _enum_name(jobs_pb2.RewardTarget, r.target, "REWARD_TARGET_")
        point = _enum_name(jobs_pb2.EvalPoint, r.eval_point, "EVAL_POINT_")
        amortised = _set_fields(r.amortised_targets) if r.HasField("amortised_targets") else None
        return specs.RewardJob(
            base_model=r.base_model, expert_model=r.expert_model, datasets=list(r.with_dataset.datasets),
            num_chains=_optional(r.models_only, "num_chains"), architecture=_reward_architecture(r),
            target=None if target == "unspecified" else target, eval_point=None if point == "unspecified" else point,
            rho_l2=_optional(r, "rho_l2"), action_weight=_optional(r, "action_weight"),
            condition_weight=_optional(r, "condition_weight"), inpaint_condition=_optional(r, "inpaint_condition"),
            amortised_targets=amortised, base_recipe=_recipe(r, "base_recipe"),
            expert_recipe=_recipe(r, "expert_recipe"), **base)
    if kind == "discriminator":
        d = s.discriminator
        return specs.DiscriminatorJob(
            base_dataset=d.base_dataset, expert_dataset=d.expert_dataset, diffusion_model=d.diffusion_model,
            architecture=_reward_architecture(d), inpaint_condition=_optional(d, "inpaint_condition"), **base)
    return None


def _set_fields(message: Any) -> dict[str, Any]:
    """The fields of a message that are set, repeated ones as lists: the ``{...}`` a typed
    spec's ``architecture`` tuple or ``amortised_targets`` holds."""
    return {f.name: list(v) if f.is_repeated else v for f, v in message.ListFields()}


def _prompts(p: Any) -> Any:
    """A ``Prompts`` message as the client takes it: a list of labels or an embeddings array."""
    return list(p.labels) if p.labels else _tensor.decode(p.embeddings)


def _recipe(r: Any, name: str) -> specs.SamplingRecipe | None:
    """A reward job's ``base_recipe`` / ``expert_recipe`` as a :class:`relreward.SamplingRecipe`."""
    if not r.HasField(name):
        return None
    m = getattr(r, name)
    safety = None
    if m.HasField("safety"):
        s = m.safety
        safety = specs.SafetyGuidance(_prompts(s.concept), s.scale, s.warmup_steps, s.threshold, s.momentum_scale,
                                      s.momentum_beta)
    return specs.SamplingRecipe(_prompts(m.prompts), _optional(m, "guidance_scale"), safety)


def _reward_architecture(m: Any) -> tuple[str, dict[str, Any]] | None:
    if not m.HasField("architecture"):
        return None
    kind = m.architecture.WhichOneof("kind")
    return (kind, _set_fields(getattr(m.architecture, kind))) if kind else None


@dataclass(frozen=True)
class Job(_Plain):
    """A training job, as ``relreward job show ID --json`` prints it (its ``spec`` aside).

    ``state`` (a :class:`JobState`); ``step`` reached of ``total_steps``; ``loss``, the latest
    training loss (None before the first step); ``error``: why a FAILED job failed; times
    (UTC, None until they happen); ``last_seq``, the latest event's number (for
    ``watch_job(from_seq=...)``); ``spec``: the typed spec it runs
    (:class:`relreward.DiffusionJob`, :class:`relreward.RewardJob` or
    :class:`relreward.DiscriminatorJob`; ``submit_job`` takes it back). ``proto``: the
    ``Job`` message it was read from.
    """

    id: str
    state: JobState
    step: int
    total_steps: int
    loss: float | None
    error: str
    created_at: _dt.datetime | None
    started_at: _dt.datetime | None
    finished_at: _dt.datetime | None
    last_seq: int
    spec: specs.DiffusionJob | specs.RewardJob | specs.DiscriminatorJob | None
    proto: jobs_pb2.Job | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_proto(cls, j: jobs_pb2.Job) -> Job:
        """The job of a ``Job`` message, its spec as a typed spec."""
        return cls(j.id, JobState.from_proto(j.state), j.step, j.total_steps, None if math.isnan(j.loss) else j.loss,
                   j.error, _time(j, "created_at"), _time(j, "started_at"), _time(j, "finished_at"), j.last_seq,
                   _spec_of(j.spec) if j.HasField("spec") else None, j)


@dataclass(frozen=True)
class JobEvent(_Plain):
    """One recorded event of a job (``seq`` from 1, no gaps), as ``relreward job watch ID
    --json`` prints it.

    ``type`` is "state", "progress", "checkpoint" or "log". State changes set ``state`` (a
    :class:`JobState`) and ``message``; progress sets ``step``, ``total_steps``, ``loss``,
    ``grad_norm``, ``learning_rate``, ``steps_per_second``, ``eta_seconds`` (seconds) and
    ``eval_loss`` when a held-out loss was evaluated; checkpoints set ``step``; log lines set
    ``message``. ``time`` is UTC. ``proto``: the ``JobEvent`` message.
    """

    seq: int
    time: _dt.datetime | None
    type: str | None
    state: JobState | None = None
    message: str = ""
    step: int | None = None
    total_steps: int | None = None
    loss: float | None = None
    grad_norm: float | None = None
    learning_rate: float | None = None
    steps_per_second: float | None = None
    eta_seconds: float | None = None
    eval_loss: float | None = None
    proto: jobs_pb2.JobEvent | None = field(default=None, repr=False, compare=False)

    #: The fields each type sets (and ``as_dict`` writes, as the CLI does), past seq, time, type.
    _FIELDS: ClassVar[dict[str | None, tuple[str, ...]]] = {
        "state": ("state", "message"),
        "progress": ("step", "total_steps", "loss", "grad_norm", "learning_rate", "steps_per_second", "eta_seconds",
                     "eval_loss"),
        "checkpoint": ("step",),
        "log": ("message",),
        None: (),
    }

    @property
    def terminal(self) -> bool:
        """Whether this event moved the job to SUCCEEDED, FAILED or CANCELLED."""
        return self.state is not None and self.state.terminal

    def as_dict(self) -> dict[str, Any]:
        """The event as plain Python values, with the fields of its type only: one line of
        ``relreward job watch ID --json``."""
        return {name: _plain(getattr(self, name)) for name in ("seq", "time", "type", *self._FIELDS[self.type])}

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={getattr(self, n)!r}" for n in ("seq", "time", "type", *self._FIELDS[self.type]))
        return f"JobEvent({fields})"

    @classmethod
    def from_proto(cls, e: jobs_pb2.JobEvent) -> JobEvent:
        """The event of a ``JobEvent`` message, its fields per type filled in."""
        time = _time(e, "time")
        kind = e.WhichOneof("event")
        if kind == "state":
            return cls(e.seq, time, kind, state=JobState.from_proto(e.state.state), message=e.state.message, proto=e)
        if kind == "progress":
            p = e.progress
            return cls(e.seq, time, kind, step=p.step, total_steps=p.total_steps, loss=p.loss, grad_norm=p.grad_norm,
                       learning_rate=p.learning_rate, steps_per_second=p.steps_per_second, eta_seconds=p.eta_seconds,
                       eval_loss=_optional(p, "eval_loss"), proto=e)
        if kind == "checkpoint":
            return cls(e.seq, time, kind, step=e.checkpoint.step, proto=e)
        if kind == "log":
            return cls(e.seq, time, kind, message=e.log.message, proto=e)
        return cls(e.seq, time, None, proto=e)


# --------------------------------------------------------------------------------------------
# Rewards


@dataclass
class ScoreResult:
    """rho per item, float32 ``[B]``; per window ``[B, H / h]`` and per step ``[B, H]`` when asked
    for (else None). Read-only views of the response."""

    rewards: np.ndarray
    per_window: np.ndarray | None = None
    per_step: np.ndarray | None = None


@dataclass
class GradientResult:
    """grad_x rho, float32, same shape as x (times omega and the posterior variance when asked),
    in the requested gradient units; and rho per item, float32 ``[B]``. Read-only views."""

    gradient: np.ndarray
    rewards: np.ndarray

    def __iter__(self) -> Iterator[np.ndarray]:
        # ``grad, rho = client.gradient(...)`` unpacks.
        return iter((self.gradient, self.rewards))


@dataclass(frozen=True)
class Sample:
    """One sample: ``x`` in raw units and ``x_normalized``, ``[H, D]`` or the sample shape
    (float32), rho(x, 0) when a reward model was given, and for a conditional model the
    ``prompt`` it was drawn under (a label as an int, or an embedding ``[dim]``)."""

    index: int
    x: np.ndarray
    x_normalized: np.ndarray
    reward: float | None
    prompt: Any = None


@dataclass(frozen=True)
class SampleBatch:
    """All samples of a ``sample`` call stacked in index order: ``x`` and ``x_normalized``
    ``[n, H, D]`` (or ``[n, *shape]``) float32, ``rewards`` ``[n]`` float64 (None without a reward
    model), ``prompts`` each sample's condition, int64 labels ``[n]`` or embeddings ``[n, dim]``
    (None for an unconditional model)."""

    x: np.ndarray
    x_normalized: np.ndarray
    rewards: np.ndarray | None
    prompts: np.ndarray | None = None
