"""Every public method of :class:`relreward.Client` and :class:`relreward.AsyncClient`, once.

The two clients differ only in how they wait (a blocking grpcio call and ``time.sleep``, or
``await``), so what a method does lives here, written once, as a *plan*: a generator that
yields the steps it needs performed (:class:`Unary`, :class:`Upload`, :class:`Open` and
:data:`NEXT` for a server stream, :class:`Sleep`), receives each step's answer back, and
returns the method's result; a plan behind an iterator (``watch_job``, ``sample_iter``) also
yields :class:`Emit` for each item. A failed step is raised inside the plan as a
:class:`relreward.RelrewardError` at the ``yield``, so retries, reconnects, paging, the
upload's own failures and the conversion into :mod:`relreward.results` are decided here. Each
client has one small driver (``_run``, ``_iter``, ``_perform``) that performs the steps in its
own way, and every public method is a one-line shell around a plan. (The "sans-I/O" pattern of
h11 and hyper-h2.)

``cfg`` is the client itself: plans read its ``timeout`` and ``retry_budget`` when they run.
"""

from __future__ import annotations

import dataclasses
import pathlib
import time
from dataclasses import dataclass
from typing import Any, Callable, Generator, Mapping, TypeVar

import numpy as np

from relreward import _common as c
from relreward import _tensor
from relreward._download import DownloadedModel, ModelDownload
from relreward.v1 import (autoencoder_pb2, datasets_pb2, datasets_pb2_grpc, jobs_pb2, jobs_pb2_grpc, models_pb2,
                          models_pb2_grpc, reward_pb2, reward_pb2_grpc, tensor_pb2)
from relreward.datasets import source_of
from relreward.errors import InvalidInput, RelrewardError, Unavailable, Unimplemented, error_for, is_retryable
from relreward.results import Dataset, GradientResult, Job, JobEvent, JobState, Manifest, Model, ScoreResult
from relreward.specs import SamplingRecipe, autoencoder_manifest, job_spec, manifest as manifest_of, reward_manifest

R = TypeVar("R")
Plan = Generator[Any, Any, R]


# --------------------------------------------------------------------------------------------
# Steps


@dataclass(frozen=True, slots=True)
class Unary:
    """Call unary RPC ``method`` with ``request`` and this deadline; answered with the reply."""

    method: str
    request: Any
    timeout: float | None


@dataclass(frozen=True, slots=True)
class Upload:
    """Call client-streaming RPC ``method`` with the request iterator ``messages``; answered
    with the reply."""

    method: str
    messages: Any
    timeout: float | None


@dataclass(frozen=True, slots=True)
class Open:
    """Open server-streaming RPC ``method`` (the driver cancels one it opened before, and the
    open one when the plan ends); answered with None. Each :data:`NEXT` then reads from it."""

    method: str
    request: Any
    timeout: float | None


class _Next:
    """The open stream's next message; answered with it, or None once the stream ended."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "NEXT"


NEXT = _Next()


@dataclass(frozen=True, slots=True)
class Sleep:
    """Wait ``seconds`` (a backoff); answered with None."""

    seconds: float


@dataclass(frozen=True, slots=True)
class Emit:
    """Hand ``value`` to the caller of an iterator method; answered with None when it asks
    for the next one."""

    value: Any


@dataclass(frozen=True, slots=True)
class Done:
    """Not a step: what :meth:`Stepper.answer` returns once the plan returned ``value``."""

    value: Any


class Stepper:
    """A driver's handle on one running plan, and on the server stream it opened.

    ``answer(reply)`` sends the last step's answer (None to start) and ``fail(error)`` raises
    the step's failure inside the plan; both return the plan's next step, or :class:`Done`.
    ``close()`` ends the plan (its ``finally`` blocks run) and cancels the open stream.
    """

    __slots__ = ("_plan", "stream")

    def __init__(self, plan: Plan) -> None:
        self._plan = plan
        self.stream: Any = None

    def answer(self, reply: Any) -> Any:
        try:
            return self._plan.send(reply)
        except StopIteration as done:
            return Done(done.value)

    def fail(self, error: RelrewardError) -> Any:
        try:
            return self._plan.throw(error)
        except StopIteration as done:
            return Done(done.value)

    def open(self, stream: Any) -> None:
        self.cancel_stream()
        self.stream = stream

    def cancel_stream(self) -> None:
        if self.stream is not None:
            self.stream.cancel()
            self.stream = None

    def close(self) -> None:
        self._plan.close()
        self.cancel_stream()


def rpc_methods(channel: Any) -> dict[str, Callable[..., Any]]:
    """Every RPC a plan names, by method name, as callables on ``channel`` (a grpcio or a
    grpc.aio channel: their stubs are made alike). "Check" is grpc.health.v1's: the package
    carries no health stubs, so its request is empty bytes and its reply raw bytes."""
    methods: dict[str, Callable[..., Any]] = {}
    for stub in (datasets_pb2_grpc.DatasetServiceStub, models_pb2_grpc.ModelServiceStub,
                 jobs_pb2_grpc.JobServiceStub, reward_pb2_grpc.RewardServiceStub):
        methods.update(vars(stub(channel)))
    methods["Check"] = channel.unary_unary("/grpc.health.v1.Health/Check", request_serializer=lambda _: b"",
                                           response_deserializer=lambda b: b)
    return methods


# --------------------------------------------------------------------------------------------
# Calls: reads are retried, writes are not, lists follow every page


def read(method: str, request: Any, cfg: Any) -> Plan[Any]:
    """A read or pure computation: retried on connection failures (backoff 50 ms doubling to
    1 s) while ``cfg.retry_budget`` seconds have not passed, all within ``cfg.timeout``, as
    the Rust client's IDEMPOTENT_RETRY; the last failure is raised otherwise."""
    clock = c.Attempts(cfg.timeout, cfg.retry_budget)
    while True:
        try:
            return (yield Unary(method, request, clock.deadline()))
        except RelrewardError as failure:
            if not is_retryable(failure):
                raise
            delay = clock.delay()
            if delay is None:
                raise
            yield Sleep(delay)


def write(method: str, request: Any, cfg: Any) -> Plan[Any]:
    """A write: one attempt (a retry could apply it twice)."""
    return (yield Unary(method, request, cfg.timeout))


def pages(method: str, request_of: Callable[[tensor_pb2.PageRequest], Any], field: str,
          convert: Callable[[Any], R], cfg: Any) -> Plan[list[R]]:
    """Every item of a paginated list: each page a read, until no next page token."""
    out: list[R] = []
    token = ""
    while True:
        page = yield from read(method, request_of(tensor_pb2.PageRequest(page_token=token)), cfg)
        out.extend(convert(item) for item in getattr(page, field))
        token = page.next_page_token
        if not token:
            return out


def health(cfg: Any) -> Plan[str]:
    return c.health_status((yield from read("Check", None, cfg)))


# --------------------------------------------------------------------------------------------
# Datasets


def upload(method: str, messages: Any, failure: c.UploadFailure, cfg: Any) -> Plan[Any]:
    """A client-streaming upload (never retried). When reading the input failed, the stream
    ended without its commit: that failure is raised, not the server's complaint about the
    missing commit."""
    try:
        return (yield Upload(method, messages, cfg.timeout))
    except RelrewardError:
        if failure.error is not None:
            raise failure.error from None
        raise


def upload_dataset(cfg: Any, name: str, data: Any, kind: str | None, key: str | None, description: str,
                   chunk_bytes: int, progress: c.Progress | bool | None) -> Plan[Dataset]:
    name, description = c.text("name", name), c.text("description", description)
    source, closer = source_of(data, kind, key)
    try:
        callback, bar = c.progress_callback(progress, source.total_bytes(), name)
        failure = c.UploadFailure()
        try:
            reply = yield from upload("UploadDataset", c.dataset_messages(name, source, description, chunk_bytes,
                                                                          callback, failure), failure, cfg)
        finally:
            if bar is not None:
                bar.close()
    finally:
        if closer is not None:
            closer.close()
    return Dataset.from_proto(reply)


def get_dataset(cfg: Any, name: str) -> Plan[Dataset]:
    request = datasets_pb2.GetDatasetRequest(name=c.text("name", name), view=datasets_pb2.DATASET_VIEW_FULL)
    return Dataset.from_proto((yield from read("GetDataset", request, cfg)))


def list_datasets(cfg: Any) -> Plan[list[Dataset]]:
    return (yield from pages("ListDatasets", lambda page: datasets_pb2.ListDatasetsRequest(
        page=page, view=datasets_pb2.DATASET_VIEW_BASIC), "datasets", Dataset.from_proto, cfg))


def delete_dataset(cfg: Any, name: str) -> Plan[None]:
    yield from write("DeleteDataset", datasets_pb2.DeleteDatasetRequest(name=c.text("name", name)), cfg)


# --------------------------------------------------------------------------------------------
# Models

_KINDS = {"diffusion": models_pb2.MODEL_KIND_DIFFUSION, "reward": models_pb2.MODEL_KIND_REWARD,
          "discriminator": models_pb2.MODEL_KIND_DISCRIMINATOR, "autoencoder": models_pb2.MODEL_KIND_AUTOENCODER,
          "recipe": models_pb2.MODEL_KIND_RECIPE}


def model_kind(kind: str | None) -> int:
    if kind is None:
        return models_pb2.MODEL_KIND_UNSPECIFIED
    try:
        return _KINDS[kind]
    except (KeyError, TypeError):
        raise InvalidInput(f"kind: {kind!r}; expected 'diffusion', 'reward', 'discriminator', 'autoencoder', "
                           "'recipe' or None (every kind)") from None


def manifest_message(manifest: Manifest | Mapping[str, Any] | models_pb2.DiffusionManifest
                     ) -> models_pb2.DiffusionManifest:
    """A :class:`relreward.Manifest` (``get_model(...).manifest``, or a changed copy), a dict in
    the CLI's manifest form, or the message itself."""
    if isinstance(manifest, Manifest):
        return manifest.to_proto()
    return manifest_of(manifest)


def upload_model(cfg: Any, path: str | pathlib.Path, name: str, manifest: Any, description: str, chunk_bytes: int,
                 progress: c.Progress | bool | None, reward: bool = False, autoencoder: bool = False) -> Plan[Model]:
    """``reward``: ``manifest`` is a bring-your-own reward's (:func:`relreward.specs.reward_manifest`);
    ``autoencoder``: an autoencoder's (:func:`relreward.specs.autoencoder_manifest`)."""
    path = pathlib.Path(path)
    name = c.text("name", name)
    if autoencoder:
        message: Any = autoencoder_manifest(manifest)
    else:
        message = reward_manifest(manifest) if reward else manifest_message(manifest)
    header = c.upload_header(name, message, c.text("description", description))
    callback, bar = c.progress_callback(progress, path.stat().st_size, name)
    failure = c.UploadFailure()
    try:
        reply = yield from upload("UploadModel", c.model_messages(path, header, chunk_bytes, callback, failure),
                                  failure, cfg)
    finally:
        if bar is not None:
            bar.close()
    return Model.from_proto(reply)


def get_model(cfg: Any, name: str) -> Plan[Model]:
    return Model.from_proto((yield from read("GetModel", models_pb2.GetModelRequest(name=c.text("name", name)), cfg)))


def list_models(cfg: Any, kind: str | None) -> Plan[list[Model]]:
    k = model_kind(kind)
    return (yield from pages("ListModels", lambda page: models_pb2.ListModelsRequest(page=page, kind=k), "models",
                             Model.from_proto, cfg))


def create_recipe(cfg: Any, name: str, model: str, recipe: Any, description: str) -> Plan[Model]:
    """Never retried (a second attempt after a lost answer would meet ALREADY_EXISTS)."""
    if isinstance(recipe, SamplingRecipe):
        recipe = recipe.to_proto()
    elif not isinstance(recipe, reward_pb2.SamplingRecipe):
        raise InvalidInput(f"recipe: expected a relreward.SamplingRecipe, got {type(recipe).__name__}")
    req = models_pb2.CreateRecipeRequest(name=c.text("name", name), model=c.text("model", model), recipe=recipe,
                                         description=c.text("description", description))
    return Model.from_proto((yield from write("CreateRecipe", req, cfg)))


def delete_model(cfg: Any, name: str) -> Plan[None]:
    yield from write("DeleteModel", models_pb2.DeleteModelRequest(name=c.text("name", name)), cfg)


def download_model(cfg: Any, name: str, out_dir: str | pathlib.Path, overwrite: bool,
                   torchscript: bool = False) -> Plan[DownloadedModel]:
    """Not retried (a long stream); the files go in place only once every one arrived whole
    (:class:`relreward._download.ModelDownload`). ``torchscript``: the export (the server
    traces the model and sends ``module.pt`` last)."""
    download = ModelDownload(c.text("name", name), out_dir, overwrite)
    try:
        yield Open("DownloadModel", models_pb2.DownloadModelRequest(name=name, torchscript=torchscript), cfg.timeout)
        while (message := (yield NEXT)) is not None:
            download.feed(message)
        got = download.finish()
    finally:
        download.close()
    if torchscript and got.module is None:
        # A server from before the export ignores the request's `torchscript`.
        raise Unimplemented(f"export_model: the server sent no module.pt (it predates model export); the plain "
                            f"download is in {out_dir}")
    return dataclasses.replace(got, model=Model.from_proto(got.model))


# --------------------------------------------------------------------------------------------
# Jobs


def job_state(state: JobState | str | None) -> int:
    """``list_jobs``'s filter: a :class:`relreward.JobState` or its name in any case."""
    if state is None:
        return jobs_pb2.JOB_STATE_UNSPECIFIED
    try:
        parsed = JobState(state.lower()) if isinstance(state, str) else JobState(state)
    except ValueError:
        parsed = None
    if parsed is None or parsed is JobState.UNSPECIFIED:
        raise InvalidInput(f"state: {state!r}; expected 'pending', 'running', 'succeeded', 'failed', 'cancelled' "
                           "or None (every state)")
    return parsed.to_proto()


def submit_job(cfg: Any, spec: Any, job_id: str | None) -> Plan[Job]:
    request = jobs_pb2.SubmitJobRequest(spec=job_spec(spec), job_id="" if job_id is None else c.text("job_id", job_id))
    return Job.from_proto((yield from write("SubmitJob", request, cfg)))


def get_job(cfg: Any, job_id: str) -> Plan[Job]:
    return Job.from_proto((yield from read("GetJob", jobs_pb2.GetJobRequest(id=c.text("job_id", job_id)), cfg)))


def list_jobs(cfg: Any, state: JobState | str | None) -> Plan[list[Job]]:
    s = job_state(state)
    return (yield from pages("ListJobs", lambda page: jobs_pb2.ListJobsRequest(page=page, state=s), "jobs",
                             Job.from_proto, cfg))


def cancel_job(cfg: Any, job_id: str) -> Plan[Job]:
    return Job.from_proto((yield from write("CancelJob", jobs_pb2.CancelJobRequest(id=c.text("job_id", job_id)), cfg)))


def watch_job(cfg: Any, job_id: str, from_seq: int, reconnect_budget: float) -> Plan[None]:
    """Emits each event once, in order, until a terminal state. A stream that fails on the
    connection, or ends while the job still runs, is reopened from the last event seen plus
    one (events before that are replays and skipped), backing off from 250 ms to 5 s, until
    ``reconnect_budget`` seconds pass without an event (the Rust client's RetryPolicy)."""
    job_id = c.text("job_id", job_id)
    cursor = max(c.unsigned("from_seq", from_seq, c.U64), 1)
    budget = c.seconds("reconnect_budget", reconnect_budget, allow_none=False)
    attempt, down_since = 0, None
    while True:
        failure: RelrewardError | None = None
        try:
            yield Open("WatchJob", jobs_pb2.WatchJobRequest(id=job_id, from_seq=cursor), None)
            while (raw := (yield NEXT)) is not None:
                attempt, down_since = 0, None
                if raw.seq < cursor:
                    continue
                cursor = raw.seq + 1
                event = JobEvent.from_proto(raw)
                yield Emit(event)
                if event.terminal:
                    return
        except RelrewardError as e:
            failure = e
        if failure is None:
            if (yield from get_job(cfg, job_id)).state.terminal:
                return
            failure = Unavailable("the event stream ended before the job finished")
        if not is_retryable(failure):
            raise failure
        now = time.monotonic()
        down_since = now if down_since is None else down_since
        delay = c.backoff_delay(attempt, c.WATCH_INITIAL_S, c.WATCH_MAX_S, budget - (now - down_since))
        if delay is None:
            raise error_for(failure.code, f"{failure.message} (gave up reconnecting after {now - down_since:.0f} s; "
                                          f"events from {cursor} on were not seen)")
        attempt += 1
        yield Sleep(delay)


# --------------------------------------------------------------------------------------------
# Rewards


def score(cfg: Any, model: str, x: Any, t: Any, units: str, per_window: bool, per_step: bool) -> Plan[ScoreResult]:
    return c.score_result((yield from read("Score", c.score_request(model, x, t, units, per_window, per_step), cfg)))


def gradient(cfg: Any, model: str, x: Any, t: Any, omega: float | None, units: str, gradient_units: str | None,
             scale_by_posterior_variance_of: str | None) -> Plan[GradientResult]:
    request = c.gradient_request(model, x, t, omega, units, gradient_units or units, scale_by_posterior_variance_of)
    return c.gradient_result((yield from read("Gradient", request, cfg)))


def sample_iter(cfg: Any, model: str, reward_model: str | None, omega: float, n: int, seed: int | None,
                n_guide_steps: int | None, t_stopgrad: int | None, scale_grad_by_std: bool, conditions: Any,
                units: str, batch_size: int, ddim: Any = None, prompts: Any = None,
                guidance_scale: float | None = None, safety: Any = None) -> Plan[None]:
    """Emits each sample as it finishes (not retried)."""
    request = c.sample_request(model, reward_model, omega, n, seed, n_guide_steps, t_stopgrad, scale_grad_by_std,
                               conditions, units, batch_size, prompts, guidance_scale, safety)
    if ddim is not None:
        request.ddim.CopyFrom(ddim)
    yield Open("Sample", request, cfg.timeout)
    while (r := (yield NEXT)) is not None:
        yield Emit(c.sample_of(r))


# --------------------------------------------------------------------------------------------
# Latents

#: Bytes of one Encode/Decode request, and of its answer, at most: half the server's default
#: request limit (16 MiB), as the CLI's batches.
LATENT_BATCH_BYTES = 8 << 20


def convert(cfg: Any, method: str, model: str, items: Any, max_batch_bytes: int) -> Plan[np.ndarray]:
    """``method`` "Encode" (images to latents) or "Decode" (latents to images) through
    autoencoder ``model``: its record read first (its shapes), ``items`` checked against them,
    then sent in batches whose request and answer each carry at most ``max_batch_bytes`` of
    values, each a read (retried); the answers joined into one writable float32 array. A model
    of another kind is asked as it is, so that the server's FAILED_PRECONDITION says why."""
    name = c.text("model", model)
    field = "images" if method == "Encode" else "latents"
    make = ((lambda x: autoencoder_pb2.EncodeRequest(model=name, images=x)) if method == "Encode"
            else (lambda x: autoencoder_pb2.DecodeRequest(model=name, latents=x)))
    answer = (lambda r: r.latents) if method == "Encode" else (lambda r: r.images)
    try:
        x = _tensor.as_f32(items)
    except (TypeError, ValueError) as e:
        raise InvalidInput(f"{field}: not an array of numbers ({e})") from None
    record = yield from get_model(cfg, name)
    info = record.autoencoder
    if info is None:
        return np.array(_tensor.decode(answer((yield from read(method, make(_tensor.encode(x)), cfg)))))
    item, out = (info.image_shape, info.latent_shape) if method == "Encode" else (info.latent_shape, info.image_shape)
    if x.ndim != len(item) + 1 or tuple(x.shape[1:]) != tuple(item):
        raise InvalidInput(f"{field}: shape {list(x.shape)} but autoencoder {name!r} takes {field} of shape "
                           f"[B, {', '.join(str(d) for d in item)}]")
    bad = np.flatnonzero(~np.isfinite(x.reshape(-1)))
    if bad.size:
        raise InvalidInput(f"{field}: value at flat index {int(bad[0])} is not a finite float32")
    per_item = 4 * max(int(np.prod(item)), int(np.prod(out)))
    batch = max(1, int(max_batch_bytes) // per_item)
    parts = []
    for start in range(0, x.shape[0], batch):
        reply = yield from read(method, make(_tensor.encode(x[start:start + batch])), cfg)
        parts.append(_tensor.decode(answer(reply)))
    if not parts:
        return np.zeros((0, *out), np.float32)
    return np.concatenate(parts, axis=0)
