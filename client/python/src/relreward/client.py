"""The synchronous client: :class:`Client` and :class:`GradientStream`.

Each method is a shell around its plan in :mod:`relreward._calls` (shared with
:class:`relreward.AsyncClient`); this module performs the plans' steps with blocking grpcio
calls."""

from __future__ import annotations

import pathlib
import queue
import threading
import time
from typing import Any, Callable, Iterator, Mapping, Sequence

import grpc
import numpy as np

from relreward import _calls as calls
from relreward import _common as c
from relreward._download import DownloadedModel
from relreward.v1 import reward_pb2
from relreward.errors import RelrewardError, Unavailable, error_for, from_rpc_error
from relreward.results import (Dataset, GradientResult, Job, JobEvent, JobState, Manifest, Model, Sample,
                               SampleBatch, ScoreResult)


class Client:
    """One connection to a relreward server, with typed access to every relreward.v1 service.

    ``endpoint``: ``host:port`` or ``http://host:port`` (plaintext), ``https://host:port``
    (TLS; verified against the system's roots unless ``tls`` gives a CA); anything but a
    non-empty string raises InvalidInput naming ``endpoint``. ``token``: sent as
    ``authorization: Bearer <token>`` with every call (servers with access control). ``tls``:
    ``True`` or a :class:`relreward.TLS` (CA, client certificate for mutual TLS, server name).

    ``timeout``: seconds a call may take in all (None: no deadline): for a retried call this
    bounds every attempt and the waits between them together, so ``timeout=1.0`` against a
    server that is down fails after about 1 s; for uploads, downloads and ``sample`` it is the
    deadline of the whole stream (``watch_job`` and ``gradient_stream`` have none).
    ``retry_budget``: seconds during which a failed read is retried (default 5.0; 0: never).

    Reads and pure computations (get/list, ``score``, ``gradient``, ``health``) are retried for
    up to ``retry_budget`` seconds, and within ``timeout`` (backoff 50 ms doubling to 1 s), when
    they fail on the connection (UNAVAILABLE, or a transport failure), as the Rust client does;
    the last failure is raised once neither leaves time for another attempt. Writes (uploads,
    deletes, submit, cancel) and streams are never retried behind the caller's back.
    ``watch_job`` resumes after a dropped connection on its own. Failures raise
    :class:`relreward.RelrewardError` subclasses; arguments refused before anything is sent
    raise :class:`relreward.InvalidInput` (both an ``InvalidArgument`` and a ``ValueError``).

    Results are the package's own types (:mod:`relreward.results`: :class:`relreward.Dataset`,
    :class:`relreward.Model`, :class:`relreward.Job`, ...), never protobuf messages.

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, endpoint: str = "127.0.0.1:50051", token: str | None = None, tls: c.TLS | bool | None = None,
                 *, timeout: float | None = None, retry_budget: float = c.IDEMPOTENT_BUDGET_S) -> None:
        target, credentials, options = c.channel_args(endpoint, tls)
        self.endpoint = endpoint
        self.timeout = c.seconds("timeout", timeout)
        self.retry_budget = c.seconds("retry_budget", retry_budget, allow_none=False)
        self._metadata = c.metadata_of(token)
        self._channel = (grpc.insecure_channel(target, options=options) if credentials is None
                         else grpc.secure_channel(target, credentials, options=options))
        self._methods = calls.rpc_methods(self._channel)

    # ----------------------------------------------------------------------------------------
    # plumbing

    @property
    def channel(self) -> grpc.Channel:
        """The underlying grpcio channel (for raw stubs; calls on it carry no token)."""
        return self._channel

    def close(self) -> None:
        """Closes the channel; streams still open on it end."""
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _perform(self, step: Any, s: calls.Stepper) -> Any:
        """Performs one step of a plan (see :mod:`relreward._calls`) and returns the next."""
        try:
            kind = type(step)
            if kind is calls.Unary or kind is calls.Upload:
                reply = self._methods[step.method](step.request if kind is calls.Unary else step.messages,
                                                   metadata=self._metadata, timeout=step.timeout)
            elif step is calls.NEXT:
                reply = next(s.stream, None)
            elif kind is calls.Open:
                s.open(self._methods[step.method](step.request, metadata=self._metadata, timeout=step.timeout))
                reply = None
            elif kind is calls.Sleep:
                time.sleep(step.seconds)
                reply = None
            else:
                raise TypeError(f"a plan yielded {step!r} where no item can be emitted")
        except grpc.RpcError as e:
            return s.fail(from_rpc_error(e))
        return s.answer(reply)

    def _run(self, plan: calls.Plan) -> Any:
        """The result of a plan."""
        s = calls.Stepper(plan)
        try:
            step = s.answer(None)
            while type(step) is not calls.Done:
                step = self._perform(step, s)
            return step.value
        finally:
            s.close()

    def _iter(self, plan: calls.Plan) -> Iterator[Any]:
        """The items a plan emits; leaving the loop early ends the plan and its stream."""
        s = calls.Stepper(plan)
        try:
            step = s.answer(None)
            while type(step) is not calls.Done:
                if type(step) is calls.Emit:
                    yield step.value
                    step = s.answer(None)
                else:
                    step = self._perform(step, s)
        finally:
            s.close()

    def health(self) -> str:
        """The server's overall serving status from grpc.health.v1: "SERVING", "NOT_SERVING",
        "UNKNOWN" or "SERVICE_UNKNOWN"."""
        return self._run(calls.health(self))

    # ----------------------------------------------------------------------------------------
    # datasets

    def upload_dataset(self, name: str, data: Any, *, kind: str | None = None, key: str | None = None,
                       description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                       progress: c.Progress | bool | None = None) -> Dataset:
        """Uploads a dataset and returns it (a :class:`relreward.Dataset`) once the server
        verified and published it.

        ``data``: a D4RL-style dict of numpy arrays (``observations`` ``[N, obs_dim]``,
        ``actions`` ``[N, act_dim]``, optional ``terminals``/``timeouts``/``episode_starts``
        ``[N]``; Minari's ``terminations``/``truncations`` accepted), a numpy array ``[N, ...]``
        (a samples dataset), or a path to an ``.npz``, ``.npy`` or HDF5 file (D4RL keys or a
        Minari ``main_data.hdf5``; needs h5py) or a Minari dataset directory, told apart by the
        file's signature, not its suffix. Observations and actions of any integer or float
        dtype are sent as float32. Keys that are not part of a dataset (``rewards``,
        ``infos/...``) are left out. See :mod:`relreward.datasets` (and
        :func:`relreward.datasets.from_minari_episodes` for Minari episodes).

        Arrays are streamed in row chunks of about ``chunk_bytes`` bytes; the commit carries the
        sha256 of the payload, which the server checks before the dataset becomes visible.
        ``progress``: ``callback(sent_bytes, total_bytes)`` after each chunk, or ``True`` for a
        tqdm bar when tqdm is installed. Never retried (a write).
        """
        return self._run(calls.upload_dataset(self, name, data, kind, key, description, chunk_bytes, progress))

    def get_dataset(self, name: str) -> Dataset:
        """The dataset with its per-coordinate statistics (FULL view): a :class:`relreward.Dataset`."""
        return self._run(calls.get_dataset(self, name))

    def list_datasets(self) -> list[Dataset]:
        """Every dataset (BASIC view: no statistics), ordered by name, following pagination."""
        return self._run(calls.list_datasets(self))

    def delete_dataset(self, name: str) -> None:
        """Deletes a dataset (never retried)."""
        self._run(calls.delete_dataset(self, name))

    # ----------------------------------------------------------------------------------------
    # models

    def upload_model(self, path: str | pathlib.Path, name: str, manifest: Manifest | Mapping[str, Any] | Any,
                     *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                     progress: c.Progress | bool | None = None) -> Model:
        """Registers a diffusion model with its manifest and returns it (a
        :class:`relreward.Model`). ``manifest``: a :class:`relreward.Manifest` (e.g. another
        model's ``get_model(...).manifest``), a dict in the CLI's manifest form (see
        :func:`relreward.specs.manifest`), or a ``DiffusionManifest`` message. The file is a
        TorchScript module (``forward(x, t)``, or ``forward(x, t, cond)`` when the manifest has a
        ``conditioning``; needs a server with
        ``models.allow_torchscript_upload``), or native safetensors weights when the manifest
        names an ``architecture`` (e.g. written by ``relreward model import``; always accepted,
        loaded strictly). It is streamed in chunks with its sha256; the server validates it
        against the manifest. Needs an ``admin`` token where tokens are on. Never retried."""
        return self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress))

    def upload_reward(self, path: str | pathlib.Path, name: str, manifest: Mapping[str, Any] | Any,
                      *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                      progress: c.Progress | bool | None = None) -> Model:
        """Registers a bring-your-own reward: a TorchScript module (``torch.jit.script`` or
        ``torch.jit.trace`` output, saved) served by ``score``, ``gradient``, ``gradient_stream``,
        guided ``sample`` and OIP exactly as trained rewards are. ``manifest``: a dict (see
        :func:`relreward.specs.reward_manifest`) or a ``RewardUploadManifest`` message;
        ``signature`` "rho" calls ``forward(x, t) -> [B]``, "value_function" Diffuser's
        ``forward(x, cond: Dict[str, Tensor], t) -> [B, 1]`` with an empty ``cond``; ``x`` is
        float32 ``[B, *item_shape]`` in the diffusion models' normalized units (raw inputs are
        mapped through the manifest's normalizer), ``t`` int64 ``[B]``. The server runs it
        forward and backward once on zeros before registering it, and refuses (InvalidInput
        naming the problem, nothing stored) a module that raises, returns another shape, a
        non-float32 or non-finite value, or an output that does not depend on ``x``
        differentiably. Needs ``models.allow_torchscript_upload`` and an ``admin`` token where
        tokens are on. Never retried."""
        return self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress,
                                            reward=True))

    def upload_autoencoder(self, path: str | pathlib.Path, name: str, manifest: Mapping[str, Any] | Any,
                           *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                           progress: c.Progress | bool | None = None) -> Model:
        """Registers an autoencoder: one TorchScript module (saved ``torch.jit.script`` or
        ``torch.jit.trace_module`` output) exporting ``encode(x) -> z`` (images float32
        ``[B, *image_shape]`` to latents ``[B, *latent_shape]``) and ``decode(z) -> x``, used by
        :meth:`encode` and :meth:`decode`. ``manifest``: a dict (see
        :func:`relreward.specs.autoencoder_manifest`: ``image_shape``, ``latent_shape``,
        optional ``scaling_factor`` and ``shift_factor``, diffusers' ``vae.config`` values) or an
        ``AutoencoderUploadManifest`` message. The server runs each method once on zeros of the
        declared shapes (batch 2) before registering it, and refuses (InvalidInput naming the
        problem, nothing stored) a module without either method, one that raises, or returns
        another shape, a non-float32 or non-finite value. For a diffusers ``AutoencoderKL``,
        ``encode`` returns ``latent_dist.mean`` (not a sample: Encode is deterministic) and
        ``decode`` the ``.sample`` (docs/python.md, "Autoencoders"). Needs
        ``models.allow_torchscript_upload`` and an ``admin`` token where tokens are on. Never
        retried."""
        return self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress,
                                            autoencoder=True))

    def get_model(self, name: str) -> Model:
        """The model (a :class:`relreward.Model`): kind, format, manifest (diffusion) or reward
        info (input shape, T, normalizer); ``model.item_shape`` and ``model.n_timesteps`` say
        what ``score``/``gradient`` take, whatever its kind."""
        return self._run(calls.get_model(self, name))

    def list_models(self, kind: str | None = None) -> list[Model]:
        """Every model, or those of ``kind`` ("diffusion", "reward", "discriminator",
        "autoencoder", "recipe"), by name."""
        return self._run(calls.list_models(self, kind))

    def create_recipe(self, name: str, model: str, recipe: Any, *, description: str = "") -> Model:
        """Registers a named sampling recipe (a :class:`relreward.Model` of kind "recipe"):
        conditional diffusion ``model`` sampled as ``recipe`` (a :class:`relreward.SamplingRecipe`:
        prompt set, classifier-free guidance scale, optional safety guidance), stored as data
        with the model's sha256. The name then stands for a diffusion model: ``sample(name)``
        samples through it (sample i under its prompt i mod k; pass no prompts, guidance_scale or
        safety), and ``RewardJob(base_model=name)`` / ``expert_model=name`` runs Algorithm 2's
        chains through it (each chain draws a prompt). The model cannot be deleted while a
        recipe samples it. Refused, naming the field: a taken name (AlreadyExists), an unknown
        model (NotFound), a model that is not a conditional diffusion model
        (FailedPrecondition), a recipe that does not fit its conditioning (InvalidArgument, e.g.
        ``recipe.prompts.labels[2]``). Needs a ``train`` token where tokens are on. Never
        retried.

            client.create_recipe("digits-safe", "digits-cond",
                                 relreward.SamplingRecipe([0, 1, 2, 3], guidance_scale=3.0,
                                                          safety=relreward.SafetyGuidance.preset("strong", [3])))
        """
        return self._run(calls.create_recipe(self, name, model, recipe, description))

    def delete_model(self, name: str) -> None:
        """Deletes a model (FAILED_PRECONDITION while a job uses it or a recipe samples it;
        never retried)."""
        self._run(calls.delete_model(self, name))

    def download_model(self, name: str, out_dir: str | pathlib.Path, *, overwrite: bool = False
                       ) -> DownloadedModel:
        """Downloads model ``name`` (any kind) into ``out_dir`` (created if missing) and returns
        a :class:`relreward.DownloadedModel`: ``path`` (the model file: ``weights.safetensors``,
        native weights under PyTorch tensor names, or ``module.pt``, a TorchScript module),
        ``model`` (the record, a :class:`relreward.Model`) and ``manifest`` (the stored manifest
        as a dict: architecture and sizes, space, normalizer, n_timesteps, ...), also written as
        ``manifest.json``. An Algorithm 2 reward's ``step_norm.safetensors`` comes with it
        (``files``).

        Every file is checked against the size and sha256 the server declared before any is
        put in place; a failed download leaves no file behind. Without ``overwrite``, raises
        ``FileExistsError`` when a file of the same name is in ``out_dir``. NOT_FOUND for an
        unknown model. Not retried (a long stream; call again).

            got = client.download_model("maze-reward", "out/maze-reward")
            state = safetensors.torch.load_file(got.path)
        """
        return self._run(calls.download_model(self, name, out_dir, overwrite))

    def export_model(self, name: str, out_dir: str | pathlib.Path, *, overwrite: bool = False
                     ) -> DownloadedModel:
        """:meth:`download_model` plus the model as a TorchScript module, ``module.pt``
        (``.module``), traced by the server from the stored weights, which
        ``torch.jit.load`` runs with no relreward code:

        - a reward or discriminator: ``forward(x, t) -> rho``, ``x`` float32
          ``[B, *item_shape]`` in the dataset's **raw** units (the normalizer is inside), ``t``
          int64 ``[B]``, rho float32 ``[B]``: :meth:`score`'s values, and
          ``torch.autograd.grad`` through it gives :meth:`gradient`'s (``units="raw"``);
        - a native diffusion model: ``forward(x, t) -> eps`` (or x0, as the manifest's
          ``parametrization`` says) over **normalized** inputs, the form a TorchScript upload
          takes.

        The safetensors weights and ``manifest.json`` come as with :meth:`download_model`, for
        rebuilding the net in PyTorch. A model stored as TorchScript already raises
        FailedPrecondition (its ``module.pt`` is the export: download it).

            got = client.export_model("maze-reward", "out/maze-reward")
            rho = torch.jit.load(got.module)
            x = torch.zeros(1, *got.model.item_shape, requires_grad=True)
            grad, = torch.autograd.grad(rho(x, torch.zeros(1, dtype=torch.long)).sum(), x)
        """
        return self._run(calls.download_model(self, name, out_dir, overwrite, torchscript=True))

    # ----------------------------------------------------------------------------------------
    # jobs

    def submit_job(self, spec: Any, job_id: str | None = None) -> Job:
        """Queues a training job and returns it (a :class:`relreward.Job`). ``spec``: a
        :class:`relreward.DiffusionJob`, :class:`relreward.RewardJob`,
        :class:`relreward.DiscriminatorJob` (another job's ``job.spec`` included), a ``JobSpec``
        message, or a dict in the JobSpec's JSON form. With ``job_id``, resubmitting the same
        spec returns the existing job (a different spec under that id is AlreadyExists). Never
        retried."""
        return self._run(calls.submit_job(self, spec, job_id))

    def get_job(self, job_id: str) -> Job:
        """The job (a :class:`relreward.Job`): ``state`` (a :class:`relreward.JobState`), step /
        total_steps, latest loss, error, times, last_seq, spec."""
        return self._run(calls.get_job(self, job_id))

    def list_jobs(self, state: JobState | str | None = None) -> list[Job]:
        """Every job, or those in ``state`` ("pending", "running", "succeeded", "failed",
        "cancelled" or a :class:`relreward.JobState`), newest first."""
        return self._run(calls.list_jobs(self, state))

    def cancel_job(self, job_id: str) -> Job:
        """Stops the job at its next step and returns it (FailedPrecondition once it finished).
        Never retried."""
        return self._run(calls.cancel_job(self, job_id))

    def watch_job(self, job_id: str, from_seq: int = 0, *, reconnect_budget: float = c.WATCH_BUDGET_S
                  ) -> Iterator[JobEvent]:
        """The job's events (:class:`relreward.JobEvent`) from ``from_seq`` (0 or 1: the first),
        then live ones (progress events carry the loss as training goes) until a terminal
        state, after which the iterator ends.

        A dropped connection (server restart, network) is resumed from the last event seen
        plus one, so every event is yielded exactly once, in order; reconnects back off from
        250 ms to 5 s and give up (raising the last error) after ``reconnect_budget`` seconds
        without an event. Breaking out of the loop cancels the stream.
        """
        return self._iter(calls.watch_job(self, job_id, from_seq, reconnect_budget))

    def wait_job(self, job_id: str, on_event: Callable[[JobEvent], None] | None = None) -> Job:
        """Follows the job (:meth:`watch_job`) until it finishes and returns it (a
        :class:`relreward.Job`); ``on_event`` sees every event. Does not raise for a FAILED or
        CANCELLED job: check ``job.state``."""
        for event in self.watch_job(job_id):
            if on_event is not None:
                on_event(event)
        return self.get_job(job_id)

    # ----------------------------------------------------------------------------------------
    # rewards

    def score(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None = 0, *, units: str = "raw",
              per_window: bool = False, per_step: bool = False) -> ScoreResult:
        """rho(x, t) per item.

        ``x``: ``[B, H, D]`` trajectories (rows ``[action | observation]``) or ``[B, *shape]``
        samples, any float array-like (sent as float32; a torch tensor's values, detached,
        even one that requires grad or lives on a GPU); ``t``: diffusion step, one for all or one
        per item (``[B]``), in ``[0, T)``; ``units``: "raw" (the dataset's units) or
        "normalized". Returns float32 ``rewards`` ``[B]``, and ``per_window`` ``[B, H / h]`` /
        ``per_step`` ``[B, H]`` when asked for (windowed rewards). Retried on connection failures.
        """
        return self._run(calls.score(self, model, x, t, units, per_window, per_step))

    def gradient(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None, *, omega: float | None = None,
                 units: str = "raw", gradient_units: str | None = None,
                 scale_by_posterior_variance_of: str | None = None) -> GradientResult:
        """grad_x rho(x_t, t) and rho for a batch.

        ``x`` ``[B, H, D]`` or ``[B, *shape]`` (float32 on the wire: a C-contiguous float32
        array is copied once, into the message); ``t`` one step or ``[B]``; ``omega``: multiplies
        the gradient (unset: 1); ``units``: of ``x``; ``gradient_units``: of the gradient
        (default: the same as ``units``; "raw" goes through the normalizer's chain rule, so
        finite differences of :meth:`score` match); ``scale_by_posterior_variance_of``: a
        diffusion model whose posterior variance at t multiplies the gradient (Diffuser's
        ``scale_grad_by_std``). Returns ``GradientResult(gradient [like x], rewards [B])``,
        float32 read-only views (``grad, rho = client.gradient(...)`` unpacks). Retried on
        connection failures.
        """
        return self._run(calls.gradient(self, model, x, t, omega, units, gradient_units,
                                        scale_by_posterior_variance_of))

    def gradient_stream(self, model: str, *, omega: float | None = None, units: str = "raw",
                        gradient_units: str | None = None, scale_by_posterior_variance_of: str | None = None
                        ) -> "GradientStream":
        """Opens one ``GradientStream`` for ``model`` (a planner episode): use it as a context
        manager and call ``stream.gradient(x_t, t)`` at every denoising step, or ``submit`` several
        and collect them (pipelining). The keyword arguments are the defaults of every request
        (each call may override them); see :meth:`gradient`."""
        return GradientStream(self._methods["GradientStream"], self._metadata, model, omega, units,
                              gradient_units or units, scale_by_posterior_variance_of)

    def sample_iter(self, model: str, *, reward_model: str | None = None, omega: float = 0.0, n: int = 1,
                    seed: int | None = None, n_guide_steps: int | None = None, t_stopgrad: int | None = None,
                    scale_grad_by_std: bool = False, conditions: Mapping[int, Any] | Sequence[tuple[int, Any]] | None = None,
                    units: str = "raw", batch_size: int = 0, sampler: str = "ddpm", steps: int | None = None,
                    eta: float | None = None, timestep_spacing: str | None = None,
                    set_alpha_to_one: bool | None = None, prompts: Any = None, guidance_scale: float | None = None,
                    safety: Any = None) -> Iterator[Sample]:
        """DDPM (or DDIM) samples (:class:`relreward.Sample`) from diffusion model ``model`` as each
        finishes (any order; see ``Sample.index``), guided by ``reward_model`` with scale
        ``omega`` (0: unguided, rewards still reported); ``n`` >= 1 samples (``n=0`` raises
        InvalidInput naming ``n``: the wire reads 0 as its default, 1). ``conditions``: ``{horizon index:
        state [obs_dim]}`` inpainted after every step, in ``units``; ``n_guide_steps`` gradient
        steps per denoising step; no guidance below ``t_stopgrad``; ``seed`` makes it
        reproducible. ``sampler="ddim"`` samples with DDIM as diffusers' DDIMScheduler does
        (``steps`` of the model's T, default T; ``eta`` in [0, 1], default 0;
        ``timestep_spacing`` "leading" (default), "trailing" or "linspace"; ``set_alpha_to_one``
        default True); with DDIM, guidance shifts eps by -omega sqrt(1 - abar_t) grad rho once
        per step (Dhariwal & Nichol eq. 14), so ``n_guide_steps`` stays 1 and
        ``scale_grad_by_std`` False. A conditional model (its manifest's conditioning) takes
        ``prompts``: one class label (an int) or embedding for every sample, or one per sample
        (a sequence of ``n``); ``guidance_scale`` s forms pred(null) + s (pred(c) - pred(null))
        (classifier-free guidance; default 1: the conditional model alone); ``safety`` (a
        :class:`relreward.SafetyGuidance`) adds Safe Latent Diffusion's guidance away from a
        concept. ``model`` may name a recipe (:meth:`create_recipe`), which brings its prompts
        and guidance (sample i under prompt i mod k). Each sample's ``prompt`` says its
        condition. Not retried."""
        return self._iter(calls.sample_iter(self, model, reward_model, omega, n, seed, n_guide_steps, t_stopgrad,
                                            scale_grad_by_std, conditions, units, batch_size,
                                            c.ddim_options(sampler, steps, eta, timestep_spacing, set_alpha_to_one),
                                            prompts, guidance_scale, safety))

    def sample(self, model: str, **kwargs: Any) -> SampleBatch:
        """All samples of :meth:`sample_iter` stacked in index order: ``x`` and
        ``x_normalized`` ``[n, H, D]`` float32, ``rewards`` ``[n]`` (None without a reward model),
        ``prompts`` ``[n]`` labels or ``[n, dim]`` embeddings (None for unconditional models)."""
        return c.stack_samples(list(self.sample_iter(model, **kwargs)))

    # ----------------------------------------------------------------------------------------
    # latents

    def encode(self, model: str, images: Any, *, max_batch_bytes: int = calls.LATENT_BATCH_BYTES) -> np.ndarray:
        """Images ``[B, *image_shape]`` (any float array, sent as float32) to latents ``[B,
        *latent_shape]`` float32 through autoencoder ``model``: ``(encode(images) -
        shift_factor) * scaling_factor``, the scaled latents a latent diffusion model works on.
        The model's record is read first; the images are checked against its shape (InvalidInput
        naming ``images``) and sent in batches whose request and answer each stay under
        ``max_batch_bytes``. Retried on connection failures."""
        return self._run(calls.convert(self, "Encode", model, images, max_batch_bytes))

    def decode(self, model: str, latents: Any, *, max_batch_bytes: int = calls.LATENT_BATCH_BYTES) -> np.ndarray:
        """Latents ``[B, *latent_shape]`` (scaled, as :meth:`encode` answers them and a latent
        diffusion model samples them) to images ``[B, *image_shape]`` float32 through
        autoencoder ``model``: ``decode(latents / scaling_factor + shift_factor)``. Batched and
        checked as :meth:`encode`."""
        return self._run(calls.convert(self, "Decode", model, latents, max_batch_bytes))


_END = object()


class PendingGradient:
    """A request sent on a :class:`GradientStream`; :meth:`result` waits for its answer."""

    __slots__ = ("_stream", "request_id")

    def __init__(self, stream: "GradientStream", request_id: int) -> None:
        self._stream = stream
        self.request_id = request_id

    def result(self) -> GradientResult:
        """The answer (``GradientResult``), or the request's own error raised as a
        RelrewardError (the stream goes on)."""
        return self._stream._result(self.request_id)


class GradientStream:
    """One open ``GradientStream`` call: requests go out in order, answers are matched by
    ``request_id`` (they may come back in any order).

    ``gradient(x_t, t)`` sends one request and waits for its answer; ``submit`` sends without
    waiting (several in flight: pipelining) and returns a :class:`PendingGradient`. A failed
    request raises its own error from ``result()`` and the stream continues; a failure of the
    whole call (server gone, malformed frame) raises from every pending and later call. Thread
    safe. Close it (or leave the ``with`` block) to end the request side.
    """

    def __init__(self, method: Any, metadata: Any, model: str, omega: float | None, units: str,
                 gradient_units: str, scale_by_posterior_variance_of: str | None) -> None:
        self.model = model
        self._defaults = (omega, units, gradient_units, scale_by_posterior_variance_of)
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._responses = method(iter(self._requests.get, _END), metadata=metadata)
        self._done: dict[int, reward_pb2.GradientResponse] = {}
        self._next_id = 0
        self._lock = threading.Lock()
        self._failed: RelrewardError | None = None
        self._closed = False

    def __enter__(self) -> "GradientStream":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def failed(self) -> RelrewardError | None:
        """The failure of the whole call, once it failed (every later request raises it), else
        None: a request refused on its own leaves the stream usable."""
        return self._failed

    def submit(self, x: Any, t: int | Sequence[int] | np.ndarray | None, *, model: str | None = None,
               omega: float | None = None, units: str | None = None, gradient_units: str | None = None,
               scale_by_posterior_variance_of: str | None = None) -> PendingGradient:
        """Sends grad_x rho(x, t) for ``x`` ``[B, H, D]`` at step(s) ``t`` without waiting; the
        keyword arguments override the stream's defaults for this request."""
        if self._failed is not None:
            raise self._failed
        if self._closed:
            raise ValueError("the gradient stream is closed")
        d_omega, d_units, d_gunits, d_scale = self._defaults
        with self._lock:
            self._next_id += 1
            rid = self._next_id
        req = c.gradient_request(model or self.model, x, t, d_omega if omega is None else omega, units or d_units,
                                 gradient_units or d_gunits, scale_by_posterior_variance_of or d_scale, rid)
        self._requests.put(req)
        return PendingGradient(self, rid)

    def gradient(self, x: Any, t: int | Sequence[int] | np.ndarray | None, **kwargs: Any) -> GradientResult:
        """Sends one request and returns its ``GradientResult(gradient, rewards)`` (float32
        read-only views; ``gradient`` shaped like ``x``, ``rewards`` ``[B]``)."""
        return self.submit(x, t, **kwargs).result()

    def _result(self, rid: int) -> GradientResult:
        with self._lock:
            while rid not in self._done:
                if self._failed is not None:
                    raise self._failed
                try:
                    r = next(self._responses)
                except StopIteration:
                    self._failed = Unavailable("the gradient stream ended before answering every request")
                    raise self._failed from None
                except grpc.RpcError as e:
                    self._failed = from_rpc_error(e)
                    raise self._failed from None
                self._done[r.request_id] = r
            r = self._done.pop(rid)
        if r.HasField("error"):
            raise error_for(r.error.code, r.error.message)
        return c.gradient_result(r)

    def close(self) -> None:
        """Ends the request side; answers still owed are dropped and the call ends."""
        if not self._closed:
            self._closed = True
            self._requests.put(_END)
            self._responses.cancel()
