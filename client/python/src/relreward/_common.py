"""What the sync and asyncio clients share below the plans of :mod:`relreward._calls`:
connection settings, the retry clock, argument checks, request builders and the upload
streams' messages."""

from __future__ import annotations

import hashlib
import pathlib
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import grpc
import numpy as np

from relreward import _tensor
from relreward.specs import prompts_message
from relreward.v1 import autoencoder_pb2, datasets_pb2, models_pb2, reward_pb2, tensor_pb2
from relreward.datasets import UploadSource, row_chunks
from relreward.errors import InvalidInput
from relreward.results import GradientResult, Sample, SampleBatch, ScoreResult

#: Largest message either way (tensors in requests and responses can be large), as the Rust client.
MAX_MESSAGE_BYTES = 64 << 20
#: Default payload bytes per upload chunk, as the Rust client.
DEFAULT_CHUNK_BYTES = 1 << 20

# Retry policy of idempotent calls (the Rust client's IDEMPOTENT_RETRY): 50 ms doubling to 1 s,
# within 5 s. And of WatchJob reconnects (its RetryPolicy default): 250 ms doubling to 5 s,
# within 60 s without an event.
IDEMPOTENT_INITIAL_S, IDEMPOTENT_MAX_S, IDEMPOTENT_BUDGET_S = 0.05, 1.0, 5.0
WATCH_INITIAL_S, WATCH_MAX_S, WATCH_BUDGET_S = 0.25, 5.0, 60.0

_UNITS: dict[str, reward_pb2.Units] = {"raw": reward_pb2.UNITS_RAW, "normalized": reward_pb2.UNITS_NORMALIZED}


def backoff_delay(attempt: int, initial: float, maximum: float, left: float) -> float | None:
    """Delay before retry number ``attempt`` (from 0), or None once ``left`` (seconds of the
    budget) is spent; the last delay is cut so as not to overrun the budget."""
    if left <= 0:
        return None
    return min(initial * (2 ** min(attempt, 20)), maximum, left)


def seconds(name: str, v: float | None, *, allow_none: bool = True) -> float | None:
    """A client setting in seconds: None (when allowed) or a finite number >= 0."""
    if v is None and allow_none:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 <= float(v) < float("inf")):
        raise ValueError(f"{name}: {v!r}; expected a finite number of seconds >= 0"
                         + (" or None" if allow_none else ""))
    return float(v)


class Attempts:
    """The clock of one retried call (``relreward._calls.read``): ``timeout``
    bounds the whole call, retries and their backoff included (each attempt gets what is left of
    it as its deadline), and retries stop once ``budget`` seconds have passed since the first
    attempt, whichever comes first."""

    __slots__ = ("_started", "_timeout", "_budget", "_attempt")

    def __init__(self, timeout: float | None, budget: float) -> None:
        self._started = time.monotonic()
        self._timeout = timeout
        self._budget = budget
        self._attempt = 0

    def deadline(self) -> float | None:
        """Seconds the next attempt may take (None: no deadline)."""
        if self._timeout is None:
            return None
        return max(self._timeout - (time.monotonic() - self._started), 0.0)

    def delay(self) -> float | None:
        """Seconds to back off before the next attempt, or None when there is no time for one
        (the budget is spent, or the wait would reach the timeout)."""
        elapsed = time.monotonic() - self._started
        d = backoff_delay(self._attempt, IDEMPOTENT_INITIAL_S, IDEMPOTENT_MAX_S, self._budget - elapsed)
        if d is None or (self._timeout is not None and elapsed + d >= self._timeout):
            return None
        self._attempt += 1
        return d


@dataclass(frozen=True)
class TLS:
    """TLS settings (PEM bytes or paths to PEM files).

    ``ca_cert``: the CA the server's certificate must chain to (None: the system's roots);
    ``client_cert`` and ``client_key``: for servers that require mutual TLS; ``server_name``:
    the name to check the certificate against when it is not the endpoint's host.
    """

    ca_cert: bytes | str | pathlib.Path | None = None
    client_cert: bytes | str | pathlib.Path | None = None
    client_key: bytes | str | pathlib.Path | None = None
    server_name: str | None = None

    @staticmethod
    def _read(v: bytes | str | pathlib.Path | None) -> bytes | None:
        if v is None or isinstance(v, bytes):
            return v
        return pathlib.Path(v).read_bytes()

    def credentials(self) -> grpc.ChannelCredentials:
        """grpcio channel credentials from these settings (reads the PEM files now)."""
        if (self.client_cert is None) != (self.client_key is None):
            raise ValueError("client_cert and client_key go together")
        return grpc.ssl_channel_credentials(root_certificates=self._read(self.ca_cert),
                                            private_key=self._read(self.client_key),
                                            certificate_chain=self._read(self.client_cert))


def channel_args(endpoint: str, tls: TLS | bool | None) -> tuple[str, grpc.ChannelCredentials | None, list]:
    """(target, credentials or None for plaintext, channel options) for an endpoint such as
    ``127.0.0.1:50051``, ``http://host:port`` or ``https://host:port``; InvalidInput naming
    ``endpoint`` for anything but a non-empty string (``Client(None)``)."""
    if not isinstance(endpoint, str) or not endpoint.strip():
        raise InvalidInput(f"endpoint: {endpoint!r}"
                           + ("" if isinstance(endpoint, str) else f" is {type(endpoint).__name__}, not a string")
                           + "; expected host:port, http://host:port or https://host:port")
    https = endpoint.startswith("https://")
    target = endpoint.split("://", 1)[1] if "://" in endpoint else endpoint
    target = target.rstrip("/")
    options: list = [("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
                     ("grpc.max_send_message_length", MAX_MESSAGE_BYTES)]
    if endpoint.startswith("http://") and tls:
        raise ValueError(f"TLS settings were given but {endpoint} is not https://; use an https:// endpoint")
    if not https and not tls:
        return target, None, options
    settings = tls if isinstance(tls, TLS) else TLS()
    if settings.server_name:
        options.append(("grpc.ssl_target_name_override", settings.server_name))
    return target, settings.credentials(), options


def metadata_of(token: str | None) -> tuple[tuple[str, str], ...] | None:
    """The per-call metadata: ``authorization: Bearer <token>`` when a token is given."""
    if token is None:
        return None
    token = token.strip()
    if not token.isascii() or not token.isprintable():
        raise ValueError("token: not printable ASCII; copy it again")
    return (("authorization", f"Bearer {token}"),)


def health_status(raw: bytes) -> str:
    """The status of a grpc.health.v1 HealthCheckResponse's bytes (field 1, a varint enum; the
    package carries no health stubs, and an empty message means 0, UNKNOWN)."""
    status = raw[1] if len(raw) >= 2 and raw[0] == 0x08 else 0
    return {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}.get(status, "UNKNOWN")


def units(u: str, name: str = "units") -> reward_pb2.Units:
    """The wire's Units for ``u``, or InvalidInput naming ``name`` (``units`` or
    ``gradient_units``): the names are exact, so ``"Raw"`` is refused, not guessed."""
    if isinstance(u, str) and u in _UNITS:
        return _UNITS[u]
    raise InvalidInput(f"{name}: {u!r}; expected 'raw' or 'normalized'")


_U32, U64 = (1 << 32) - 1, (1 << 64) - 1


def text(name: str, v: Any) -> str:
    """``v`` for a string field, or InvalidInput naming ``name``: protobuf's own refusal ("bad
    argument type for built-in operation") names neither the field nor the type."""
    if isinstance(v, str):
        return v
    raise InvalidInput(f"{name}: {v!r} is {type(v).__name__}, not a string")


def unsigned(name: str, v: Any, limit: int = _U32) -> int:
    """``v`` as an int for an unsigned wire field (uint32 unless ``limit`` says uint64), or
    InvalidInput naming ``name``: protobuf's own refusal ("Value out of range: -1") names no
    field, and ``int()`` would silently truncate 2.5 to 2."""
    if isinstance(v, (bool, np.bool_)):
        raise InvalidInput(f"{name}: {v!r} is a bool; expected a non-negative integer")
    if isinstance(v, (int, np.integer)):
        i = int(v)
    elif isinstance(v, (float, np.floating)) and float(v).is_integer():
        i = int(v)
    else:
        raise InvalidInput(f"{name}: {v!r} is not an integer; expected an integer in [0, {limit}]")
    if i < 0:
        raise InvalidInput(f"{name}: {i} is negative; expected an integer in [0, {limit}]")
    if i > limit:
        raise InvalidInput(f"{name}: {i} is past {limit}, the largest value the field holds")
    return i


def times(t: int | Sequence[int] | np.ndarray | None, name: str = "t") -> list[int]:
    """The wire's ``t``: [] (0 for all) for None, [t] (broadcast) for one int, else one per item.
    Steps that are negative, fractional or past uint32 raise InvalidInput naming ``t`` (and the
    item), as the server would name a step past the model's T."""
    if t is None:
        return []
    if isinstance(t, (int, np.integer)) and not isinstance(t, (bool, np.bool_)):
        return [unsigned(name, t)]
    a = np.asarray(t)
    if a.ndim == 0:
        return [unsigned(name, a.item())]
    a = a.reshape(-1)
    if a.dtype.kind in "iu" and a.size:
        # One vectorised bounds check (a planner's [B] steps); the loop only names the culprit.
        if int(a.min()) >= 0 and int(a.max()) <= _U32:
            return a.tolist()
    elif a.dtype.kind not in "iuf" and a.size:
        raise InvalidInput(f"{name}: {a.dtype} steps; expected integers in [0, {_U32}]")
    return [unsigned(f"{name}[{k}]", v) for k, v in enumerate(a.tolist())]


# --------------------------------------------------------------------------------------------
# Requests


def score_request(model: str, x: Any, t: Any, input_units: str, per_window: bool,
                  per_step: bool) -> reward_pb2.ScoreRequest:
    return reward_pb2.ScoreRequest(model=text("model", model), x=_tensor.encode(x), t=times(t), input_units=units(input_units),
                                   per_window=per_window, per_step=per_step)


def score_result(r: reward_pb2.ScoreResponse) -> ScoreResult:
    return ScoreResult(_tensor.decode(r.rewards), _tensor.decode(r.per_window) if r.HasField("per_window") else None,
                       _tensor.decode(r.per_step) if r.HasField("per_step") else None)


_GradientRequest = reward_pb2.GradientRequest


def gradient_request(model: str, x: Any, t: Any, omega: float | None, input_units: str, gradient_units: str,
                     scale_by_posterior_variance_of: str | None, request_id: int = 0) -> reward_pb2.GradientRequest:
    # The hot path of a planner: keyword arguments only where set (each costs a field write).
    req = _GradientRequest(request_id=request_id, model=model if type(model) is str else text("model", model),
                           x=_tensor.encode(x),
                           t=[t] if type(t) is int and 0 <= t <= _U32 else times(t),
                           input_units=units(input_units), gradient_units=units(gradient_units, "gradient_units"))
    if scale_by_posterior_variance_of:
        req.scale_by_posterior_variance_of = text("scale_by_posterior_variance_of", scale_by_posterior_variance_of)
    if omega is not None:
        req.omega = omega
    return req


def gradient_result(r: reward_pb2.GradientResponse) -> GradientResult:
    return GradientResult(_tensor.decode(r.gradient), _tensor.decode(r.rewards))


def sample_request(model: str, reward_model: str | None, omega: float, n: int, seed: int | None,
                   n_guide_steps: int | None, t_stopgrad: int | None, scale_grad_by_std: bool,
                   conditions: Any, input_units: str, batch_size: int, prompts: Any = None,
                   guidance_scale: float | None = None, safety: Any = None) -> reward_pb2.SampleRequest:
    count = unsigned("n", n)
    if count < 1:  # proto3 sends 0 as "unset", which the server reads as its default, 1
        raise InvalidInput(f"n: {count} is below 1; expected a positive number of samples")
    req = reward_pb2.SampleRequest(model=text("model", model), reward_model=text("reward_model", reward_model or ""),
                                   omega=omega, n=count, scale_grad_by_std=scale_grad_by_std,
                                   input_units=units(input_units), batch_size=unsigned("batch_size", batch_size))
    for name, v, limit in (("seed", seed, U64), ("n_guide_steps", n_guide_steps, _U32),
                           ("t_stopgrad", t_stopgrad, _U32)):
        if v is not None:
            setattr(req, name, unsigned(name, v, limit))
    items = conditions.items() if hasattr(conditions, "items") else (conditions or ())
    for index, state in items:
        req.conditions.add(index=unsigned(f"conditions index {index!r}", index), state=_tensor.encode(state))
    if prompts is not None:
        req.prompts.CopyFrom(prompts_message("prompts", prompts))
    if guidance_scale is not None:
        req.guidance_scale = float(guidance_scale)
    if safety is not None:
        req.safety.CopyFrom(safety.to_proto() if hasattr(safety, "to_proto") else safety)
    return req


_SPACINGS = {None: reward_pb2.TIMESTEP_SPACING_UNSPECIFIED, "leading": reward_pb2.TIMESTEP_SPACING_LEADING,
             "trailing": reward_pb2.TIMESTEP_SPACING_TRAILING, "linspace": reward_pb2.TIMESTEP_SPACING_LINSPACE}


def ddim_options(sampler: str, steps: int | None, eta: float | None, timestep_spacing: str | None,
                 set_alpha_to_one: bool | None) -> reward_pb2.Ddim | None:
    """SampleRequest.ddim for ``sampler="ddim"``, None for "ddpm"; DDIM's options without it are
    refused (they would be ignored), as are samplers and spacings the server does not offer."""
    if sampler not in ("ddpm", "ddim"):
        raise InvalidInput(f"sampler {sampler!r}: expected 'ddpm' or 'ddim'")
    if sampler == "ddpm":
        given = [k for k, v in (("steps", steps), ("eta", eta), ("timestep_spacing", timestep_spacing),
                                ("set_alpha_to_one", set_alpha_to_one)) if v is not None]
        if given:
            raise InvalidInput(f"{given[0]}: only applies to sampler='ddim'")
        return None
    if timestep_spacing not in _SPACINGS:
        raise InvalidInput(f"timestep_spacing {timestep_spacing!r}: expected 'leading', 'trailing' or 'linspace'")
    d = reward_pb2.Ddim(n_steps=unsigned("steps", steps or 0), eta=float(eta or 0.0),
                        timestep_spacing=_SPACINGS[timestep_spacing])
    if set_alpha_to_one is not None:
        d.set_alpha_to_one = bool(set_alpha_to_one)
    return d


def sample_of(r: reward_pb2.SampleResponse) -> Sample:
    prompt: Any = None
    if r.HasField("prompt"):
        p = r.prompt
        prompt = _tensor.decode(p.embeddings) if p.HasField("embeddings") else (int(p.labels[0]) if p.labels else None)
    return Sample(r.index, _tensor.decode(r.x), _tensor.decode(r.x_normalized),
                  r.reward if r.HasField("reward") else None, prompt)


def stack_samples(samples: list[Sample]) -> SampleBatch:
    samples = sorted(samples, key=lambda s: s.index)
    rewards = None
    if samples and all(s.reward is not None for s in samples):
        rewards = np.array([s.reward for s in samples], dtype=np.float64)
    prompts = None
    if samples and all(s.prompt is not None for s in samples):
        prompts = np.stack([np.asarray(s.prompt) for s in samples])
    return SampleBatch(np.stack([s.x for s in samples]) if samples else np.zeros((0,), np.float32),
                       np.stack([s.x_normalized for s in samples]) if samples else np.zeros((0,), np.float32),
                       rewards, prompts)


class UploadFailure:
    """Holds an exception raised while producing an upload's messages (reading the input): the
    stream then ends without a commit, and the caller reports this rather than the server's
    complaint about the missing commit."""

    def __init__(self) -> None:
        self.error: BaseException | None = None


Progress = Callable[[int, int], None]


_warned_no_tqdm = False


def _warn_no_tqdm() -> None:
    """Says once per process that ``progress=True`` shows nothing here (it used to be silent)."""
    global _warned_no_tqdm
    if not _warned_no_tqdm:
        _warned_no_tqdm = True
        # stacklevel 7 names the caller of upload_*: past this function, progress_callback, the
        # plan, Stepper.answer, the client's _run and its method (the same depth sync and async).
        warnings.warn("progress=True shows a tqdm bar, but tqdm is not installed: no progress is shown "
                      "(pip install 'relreward[progress]', or pass a callback(sent_bytes, total_bytes))",
                      RuntimeWarning, stacklevel=7)


def progress_callback(progress: Progress | bool | None, total: int, desc: str) -> tuple[Progress | None, Any]:
    """(callback(sent_bytes, total_bytes), object to close): ``True`` shows a tqdm bar when tqdm
    is installed (otherwise nothing, with a RuntimeWarning the first time); a callable is called
    after each chunk."""
    if progress is True:
        try:
            from tqdm.auto import tqdm
        except ImportError:
            _warn_no_tqdm()
            return None, None
        bar = tqdm(total=total, unit="B", unit_scale=True, desc=desc)

        def update(sent: int, _total: int) -> None:
            bar.update(sent - bar.n)

        return update, bar
    if callable(progress):
        return progress, None
    return None, None


def dataset_messages(name: str, source: UploadSource, description: str, chunk_bytes: int,
                     progress: Progress | None, failure: UploadFailure) -> Iterator[datasets_pb2.UploadDatasetRequest]:
    """Header, every array in row chunks of about ``chunk_bytes``, then the commit with the sha256
    of the concatenated raw little-endian bytes of every array in header order (what the server
    verifies; independent of the chunking)."""
    total = source.total_bytes()
    try:
        yield datasets_pb2.UploadDatasetRequest(header=datasets_pb2.UploadHeader(
            name=name, kind=source.kind, arrays=source.specs(), description=description))
        digest = hashlib.sha256()
        sent = 0
        for array_name, array in source.arrays:
            for chunk in row_chunks(array, max(1, chunk_bytes)):
                data = chunk.tobytes()
                digest.update(data)
                yield datasets_pb2.UploadDatasetRequest(chunk=datasets_pb2.DatasetChunk(
                    array=array_name, data=tensor_pb2.Tensor(shape=chunk.shape, dtype=_tensor.wire_dtype(chunk.dtype),
                                                             data=data)))
                sent += len(data)
                if progress is not None:
                    progress(sent, total)
        yield datasets_pb2.UploadDatasetRequest(commit=datasets_pb2.UploadCommit(sha256=digest.hexdigest()))
    except Exception as e:  # reading the input failed: end without a commit
        failure.error = e


def upload_header(name: str, manifest: models_pb2.DiffusionManifest | models_pb2.RewardUploadManifest
                  | autoencoder_pb2.AutoencoderUploadManifest, description: str) -> models_pb2.UploadModelHeader:
    """The upload's header; one rule gives its format: native safetensors weights when a
    diffusion manifest names an architecture, a TorchScript module otherwise (a reward's
    manifest goes in ``reward``, an autoencoder's in ``autoencoder``: both are always
    TorchScript)."""
    if isinstance(manifest, models_pb2.RewardUploadManifest):
        return models_pb2.UploadModelHeader(name=name, reward=manifest, description=description,
                                            format=models_pb2.MODEL_FORMAT_TORCHSCRIPT)
    if isinstance(manifest, autoencoder_pb2.AutoencoderUploadManifest):
        return models_pb2.UploadModelHeader(name=name, autoencoder=manifest, description=description,
                                            format=models_pb2.MODEL_FORMAT_TORCHSCRIPT)
    fmt = models_pb2.MODEL_FORMAT_NATIVE if manifest.WhichOneof("architecture") else models_pb2.MODEL_FORMAT_TORCHSCRIPT
    return models_pb2.UploadModelHeader(name=name, manifest=manifest, description=description, format=fmt)


def model_messages(path: pathlib.Path, header: models_pb2.UploadModelHeader, chunk_bytes: int,
                   progress: Progress | None, failure: UploadFailure) -> Iterator[models_pb2.UploadModelRequest]:
    """Header, the file's bytes in chunks, then the commit with the file's sha256."""
    try:
        total = path.stat().st_size
        yield models_pb2.UploadModelRequest(header=header)
        digest = hashlib.sha256()
        sent = 0
        with open(path, "rb") as f:
            while chunk := f.read(max(1, chunk_bytes)):
                digest.update(chunk)
                yield models_pb2.UploadModelRequest(chunk=chunk)
                sent += len(chunk)
                if progress is not None:
                    progress(sent, total)
        yield models_pb2.UploadModelRequest(commit=datasets_pb2.UploadCommit(sha256=digest.hexdigest()))
    except Exception as e:
        failure.error = e
