"""The asyncio client: :class:`AsyncClient`, with the methods of :class:`relreward.Client` as
coroutines (``watch_job`` and ``sample_iter`` as async iterators, ``gradient_stream`` as an
async context manager). Each method runs the same plan of :mod:`relreward._calls` as its sync
twin (same requests, retry policy, results); this module performs the plans' steps with
grpc.aio and ``asyncio.sleep``."""

from __future__ import annotations

import asyncio
import pathlib
from typing import Any, AsyncIterator, Callable, Mapping, Sequence

import grpc
import grpc.aio
import numpy as np

from relreward import _calls as calls
from relreward import _common as c
from relreward._download import DownloadedModel
from relreward.client import Client
from relreward.errors import RelrewardError, Unavailable, error_for, from_rpc_error
from relreward.results import (Dataset, GradientResult, Job, JobEvent, JobState, Manifest, Model, Sample,
                               SampleBatch, ScoreResult)


class _Connection:
    """A grpc.aio channel and its methods. A grpc.aio channel belongs to the event loop it was
    made in (used from another, every call fails with asyncio's "attached to a different
    loop"), so it is made on first use, inside the loop that uses it, and remembers that loop."""

    def __init__(self, target: str, credentials: grpc.ChannelCredentials | None, options: list) -> None:
        self.loop = asyncio.get_running_loop()
        self.channel = (grpc.aio.insecure_channel(target, options=options) if credentials is None
                        else grpc.aio.secure_channel(target, credentials, options=options))
        self.methods = calls.rpc_methods(self.channel)


def _doc(sync: Callable[..., Any], note: str = "") -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Gives an AsyncClient method the docstring of its :class:`relreward.Client` twin (one
    text for both: they run the same plan), with ``note`` on what differs under asyncio."""

    def give(method: Callable[..., Any]) -> Callable[..., Any]:
        method.__doc__ = f"{(sync.__doc__ or '').rstrip()}\n\n        asyncio: {note}" if note else sync.__doc__
        return method

    return give


class AsyncClient:
    """asyncio twin of :class:`relreward.Client`: the same arguments (``timeout`` and
    ``retry_budget`` included), the same methods as coroutines (``watch_job`` and
    ``sample_iter`` as async iterators, ``gradient_stream`` as an async context manager), the
    same results; each method's docstring is its sync twin's.

    It may be created anywhere, inside or outside a running loop (``client =
    AsyncClient(...)`` at module level, then ``asyncio.run(main())``): the grpc.aio channel is
    made on the first call, in the loop that runs it. That loop then owns it; using the client
    from another loop raises a RuntimeError saying so (create one client per loop).
    ``async with`` (or ``await client.close()``) closes it.
    """

    def __init__(self, endpoint: str = "127.0.0.1:50051", token: str | None = None, tls: c.TLS | bool | None = None,
                 *, timeout: float | None = None, retry_budget: float = c.IDEMPOTENT_BUDGET_S) -> None:
        # Settings are checked here, where the caller wrote them, not at the first call.
        self._args = c.channel_args(endpoint, tls)
        self.endpoint = endpoint
        self.timeout = c.seconds("timeout", timeout)
        self.retry_budget = c.seconds("retry_budget", retry_budget, allow_none=False)
        self._metadata = c.metadata_of(token)
        self._connection: _Connection | None = None

    def _conn(self) -> _Connection:
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            raise RuntimeError("relreward.AsyncClient: no running event loop; call its methods from a coroutine "
                               "(asyncio.run(main())), or use relreward.Client outside asyncio") from None
        if self._connection is None:
            self._connection = _Connection(*self._args)
        elif self._connection.loop is not loop:
            raise RuntimeError("relreward.AsyncClient: this client's channel belongs to the event loop it was first "
                               "used in, not the one running now; create one AsyncClient per event loop")
        return self._connection

    @property
    def channel(self) -> grpc.aio.Channel:
        """The underlying grpc.aio channel (for raw stubs; calls on it carry no token). Made
        now if no call made it yet, so read it inside the loop that will use it."""
        return self._conn().channel

    async def close(self) -> None:
        """Closes the channel (if a call made one); streams still open on it end. A later call
        makes a new one."""
        if self._connection is not None:
            connection, self._connection = self._connection, None
            await connection.channel.close()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _perform(self, step: Any, s: calls.Stepper) -> Any:
        """Performs one step of a plan (see :mod:`relreward._calls`) and returns the next."""
        try:
            kind = type(step)
            if kind is calls.Unary or kind is calls.Upload:
                reply = await self._conn().methods[step.method](step.request if kind is calls.Unary else step.messages,
                                                                metadata=self._metadata, timeout=step.timeout)
            elif step is calls.NEXT:
                message = await s.stream.read()
                reply = None if message is grpc.aio.EOF else message
            elif kind is calls.Open:
                s.open(self._conn().methods[step.method](step.request, metadata=self._metadata, timeout=step.timeout))
                reply = None
            elif kind is calls.Sleep:
                await asyncio.sleep(step.seconds)
                reply = None
            else:
                raise TypeError(f"a plan yielded {step!r} where no item can be emitted")
        except grpc.RpcError as e:
            return s.fail(from_rpc_error(e))
        return s.answer(reply)

    async def _run(self, plan: calls.Plan) -> Any:
        """The result of a plan."""
        s = calls.Stepper(plan)
        try:
            step = s.answer(None)
            while type(step) is not calls.Done:
                step = await self._perform(step, s)
            return step.value
        finally:
            s.close()

    async def _iter(self, plan: calls.Plan) -> AsyncIterator[Any]:
        """The items a plan emits; leaving the loop early ends the plan and its stream."""
        s = calls.Stepper(plan)
        try:
            step = s.answer(None)
            while type(step) is not calls.Done:
                if type(step) is calls.Emit:
                    yield step.value
                    step = s.answer(None)
                else:
                    step = await self._perform(step, s)
        finally:
            s.close()

    @_doc(Client.health)
    async def health(self) -> str:
        return await self._run(calls.health(self))

    # datasets
    @_doc(Client.upload_dataset, "the input is read on the event loop's thread between chunks.")
    async def upload_dataset(self, name: str, data: Any, *, kind: str | None = None, key: str | None = None,
                             description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                             progress: c.Progress | bool | None = None) -> Dataset:
        return await self._run(calls.upload_dataset(self, name, data, kind, key, description, chunk_bytes, progress))

    @_doc(Client.get_dataset)
    async def get_dataset(self, name: str) -> Dataset:
        return await self._run(calls.get_dataset(self, name))

    @_doc(Client.list_datasets)
    async def list_datasets(self) -> list[Dataset]:
        return await self._run(calls.list_datasets(self))

    @_doc(Client.delete_dataset)
    async def delete_dataset(self, name: str) -> None:
        await self._run(calls.delete_dataset(self, name))

    # models
    @_doc(Client.upload_model, "the file is read on the event loop's thread between chunks.")
    async def upload_model(self, path: str | pathlib.Path, name: str, manifest: Manifest | Mapping[str, Any] | Any,
                           *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                           progress: c.Progress | bool | None = None) -> Model:
        return await self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress))

    @_doc(Client.upload_reward, "the file is read on the event loop's thread between chunks.")
    async def upload_reward(self, path: str | pathlib.Path, name: str, manifest: Mapping[str, Any] | Any,
                            *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                            progress: c.Progress | bool | None = None) -> Model:
        return await self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress,
                                                  reward=True))

    @_doc(Client.upload_autoencoder, "the file is read on the event loop's thread between chunks.")
    async def upload_autoencoder(self, path: str | pathlib.Path, name: str, manifest: Mapping[str, Any] | Any,
                                 *, description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                                 progress: c.Progress | bool | None = None) -> Model:
        return await self._run(calls.upload_model(self, path, name, manifest, description, chunk_bytes, progress,
                                                  autoencoder=True))

    @_doc(Client.get_model)
    async def get_model(self, name: str) -> Model:
        return await self._run(calls.get_model(self, name))

    @_doc(Client.list_models)
    async def list_models(self, kind: str | None = None) -> list[Model]:
        return await self._run(calls.list_models(self, kind))

    @_doc(Client.create_recipe)
    async def create_recipe(self, name: str, model: str, recipe: Any, *, description: str = "") -> Model:
        return await self._run(calls.create_recipe(self, name, model, recipe, description))

    @_doc(Client.delete_model)
    async def delete_model(self, name: str) -> None:
        await self._run(calls.delete_model(self, name))

    @_doc(Client.download_model, "files are written on the event loop's thread as chunks arrive.")
    async def download_model(self, name: str, out_dir: str | pathlib.Path, *, overwrite: bool = False
                             ) -> DownloadedModel:
        return await self._run(calls.download_model(self, name, out_dir, overwrite))

    @_doc(Client.export_model, "files are written on the event loop's thread as chunks arrive.")
    async def export_model(self, name: str, out_dir: str | pathlib.Path, *, overwrite: bool = False
                           ) -> DownloadedModel:
        return await self._run(calls.download_model(self, name, out_dir, overwrite, torchscript=True))

    # jobs
    @_doc(Client.submit_job)
    async def submit_job(self, spec: Any, job_id: str | None = None) -> Job:
        return await self._run(calls.submit_job(self, spec, job_id))

    @_doc(Client.get_job)
    async def get_job(self, job_id: str) -> Job:
        return await self._run(calls.get_job(self, job_id))

    @_doc(Client.list_jobs)
    async def list_jobs(self, state: JobState | str | None = None) -> list[Job]:
        return await self._run(calls.list_jobs(self, state))

    @_doc(Client.cancel_job)
    async def cancel_job(self, job_id: str) -> Job:
        return await self._run(calls.cancel_job(self, job_id))

    @_doc(Client.watch_job, "an async iterator: ``async for event in client.watch_job(job_id)``.")
    def watch_job(self, job_id: str, from_seq: int = 0, *, reconnect_budget: float = c.WATCH_BUDGET_S
                  ) -> AsyncIterator[JobEvent]:
        return self._iter(calls.watch_job(self, job_id, from_seq, reconnect_budget))

    @_doc(Client.wait_job, "``on_event`` may also be a coroutine function, which is awaited.")
    async def wait_job(self, job_id: str, on_event: Callable[[JobEvent], Any] | None = None) -> Job:
        async for event in self.watch_job(job_id):
            if on_event is not None:
                result = on_event(event)
                if asyncio.iscoroutine(result):
                    await result
        return await self.get_job(job_id)

    # rewards
    @_doc(Client.score)
    async def score(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None = 0, *, units: str = "raw",
                    per_window: bool = False, per_step: bool = False) -> ScoreResult:
        return await self._run(calls.score(self, model, x, t, units, per_window, per_step))

    @_doc(Client.gradient)
    async def gradient(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None, *,
                       omega: float | None = None, units: str = "raw", gradient_units: str | None = None,
                       scale_by_posterior_variance_of: str | None = None) -> GradientResult:
        return await self._run(calls.gradient(self, model, x, t, omega, units, gradient_units,
                                              scale_by_posterior_variance_of))

    @_doc(Client.gradient_stream, "an :class:`AsyncGradientStream`: ``async with client.gradient_stream(model) as "
                                  "s: grad, rho = await s.gradient(x, t)``.")
    def gradient_stream(self, model: str, *, omega: float | None = None, units: str = "raw",
                        gradient_units: str | None = None, scale_by_posterior_variance_of: str | None = None
                        ) -> "AsyncGradientStream":
        return AsyncGradientStream(self._conn().methods["GradientStream"], self._metadata, model, omega, units,
                                   gradient_units or units, scale_by_posterior_variance_of)

    @_doc(Client.sample_iter, "an async iterator: ``async for s in client.sample_iter(model)``.")
    def sample_iter(self, model: str, *, reward_model: str | None = None, omega: float = 0.0, n: int = 1,
                    seed: int | None = None, n_guide_steps: int | None = None, t_stopgrad: int | None = None,
                    scale_grad_by_std: bool = False, conditions: Mapping[int, Any] | Sequence[tuple[int, Any]] | None = None,
                    units: str = "raw", batch_size: int = 0, sampler: str = "ddpm", steps: int | None = None,
                    eta: float | None = None, timestep_spacing: str | None = None,
                    set_alpha_to_one: bool | None = None, prompts: Any = None, guidance_scale: float | None = None,
                    safety: Any = None) -> AsyncIterator[Sample]:
        return self._iter(calls.sample_iter(self, model, reward_model, omega, n, seed, n_guide_steps, t_stopgrad,
                                            scale_grad_by_std, conditions, units, batch_size,
                                            c.ddim_options(sampler, steps, eta, timestep_spacing, set_alpha_to_one),
                                            prompts, guidance_scale, safety))

    @_doc(Client.sample)
    async def sample(self, model: str, **kwargs: Any) -> SampleBatch:
        return c.stack_samples([s async for s in self.sample_iter(model, **kwargs)])

    # latents
    @_doc(Client.encode)
    async def encode(self, model: str, images: Any, *, max_batch_bytes: int = calls.LATENT_BATCH_BYTES) -> np.ndarray:
        return await self._run(calls.convert(self, "Encode", model, images, max_batch_bytes))

    @_doc(Client.decode)
    async def decode(self, model: str, latents: Any, *, max_batch_bytes: int = calls.LATENT_BATCH_BYTES
                     ) -> np.ndarray:
        return await self._run(calls.convert(self, "Decode", model, latents, max_batch_bytes))


class AsyncGradientStream:
    """asyncio twin of :class:`relreward.GradientStream`: ``await s.gradient(x, t)``, or
    ``fut = s.submit(x, t)`` for several in flight and ``await fut``. A reader task matches
    answers to requests by ``request_id``."""

    def __init__(self, method: Any, metadata: Any, model: str, omega: float | None, units: str, gradient_units: str,
                 scale_by_posterior_variance_of: str | None) -> None:
        self.model = model
        self._defaults = (omega, units, gradient_units, scale_by_posterior_variance_of)
        self._method, self._metadata = method, metadata
        self._call: Any = None
        self._reader: asyncio.Task | None = None
        self._pending: dict[int, asyncio.Future] = {}
        self._next_id = 0
        self._failed: RelrewardError | None = None

    async def __aenter__(self) -> "AsyncGradientStream":
        self._call = self._method(metadata=self._metadata)
        self._reader = asyncio.ensure_future(self._read())
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _read(self) -> None:
        try:
            async for r in self._call:
                fut = self._pending.pop(r.request_id, None)
                if fut is None or fut.done():
                    continue
                if r.HasField("error"):
                    fut.set_exception(error_for(r.error.code, r.error.message))
                else:
                    fut.set_result(c.gradient_result(r))
            self._failed = Unavailable("the gradient stream ended before answering every request")
        except grpc.RpcError as e:
            self._failed = from_rpc_error(e)
        except asyncio.CancelledError:
            self._failed = Unavailable("the gradient stream is closed")
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(self._failed)
        self._pending.clear()

    async def submit(self, x: Any, t: Any, *, model: str | None = None, omega: float | None = None,
                     units: str | None = None, gradient_units: str | None = None,
                     scale_by_posterior_variance_of: str | None = None) -> "asyncio.Future[GradientResult]":
        """Sends a request; returns a future of its ``GradientResult``. An argument refused
        before sending raises InvalidInput here, and leaves no future behind."""
        if self._call is None:
            raise ValueError("use the stream as `async with client.gradient_stream(model) as s`")
        if self._failed is not None:
            raise self._failed
        d_omega, d_units, d_gunits, d_scale = self._defaults
        rid = self._next_id + 1
        # The request first: a refusal (a bad t, units) must come before a future is registered,
        # or the reader would later fail that orphan and asyncio log its unretrieved exception.
        request = c.gradient_request(model or self.model, x, t, d_omega if omega is None else omega,
                                     units or d_units, gradient_units or d_gunits,
                                     scale_by_posterior_variance_of or d_scale, rid)
        self._next_id = rid
        fut: asyncio.Future = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        try:
            await self._call.write(request)
        except BaseException as e:
            # Not sent: this future is nobody's (the reader may already have failed it).
            self._pending.pop(rid, None)
            if fut.done():
                if not fut.cancelled():
                    fut.exception()  # retrieved: the error is raised below instead
            else:
                fut.cancel()
            if isinstance(e, grpc.RpcError):
                raise from_rpc_error(e) from None
            raise
        return fut

    async def gradient(self, x: Any, t: Any, **kwargs: Any) -> GradientResult:
        """Sends one request and awaits its ``GradientResult(gradient, rewards)``."""
        return await (await self.submit(x, t, **kwargs))

    async def close(self) -> None:
        """Ends the call; requests still waiting fail with Unavailable."""
        if self._call is not None:
            self._call.cancel()
        if self._reader is not None:
            try:
                await self._reader
            except BaseException:
                pass
