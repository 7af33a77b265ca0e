"""The asyncio client: :class:`AsyncClient`, with the methods of :class:`relreward.Client` as
coroutines (``watch_job`` and ``sample_iter`` as async iterators, ``gradient_stream`` as an
async context manager). Same retry policy: reads and pure computations retried on
connection failures for up to ``retry_budget`` seconds (5 by default) within ``timeout``,
writes never."""

from __future__ import annotations

import asyncio
import pathlib
from typing import Any, AsyncIterator, Awaitable, Callable, Mapping, Sequence, TypeVar

import grpc
import grpc.aio
import numpy as np

from relreward import _common as c
from relreward._proto import (datasets_pb2, datasets_pb2_grpc, jobs_pb2, jobs_pb2_grpc, models_pb2,
                              models_pb2_grpc, reward_pb2, reward_pb2_grpc, tensor_pb2)
from relreward._download import DownloadedModel, ModelDownload
from relreward.client import _KINDS, _STATES
from relreward.datasets import source_of
from relreward.errors import RelrewardError, Unavailable, error_for, from_rpc_error, is_retryable
from relreward.specs import job_spec, manifest as manifest_of

T = TypeVar("T")


class _Connection:
    """A grpc.aio channel and its stubs. A grpc.aio channel belongs to the event loop it was
    made in (used from another, every call fails with asyncio's "attached to a different
    loop"), so it is made on first use, inside the loop that uses it, and remembers that loop."""

    def __init__(self, target: str, credentials: grpc.ChannelCredentials | None, options: list) -> None:
        self.loop = asyncio.get_running_loop()
        self.channel = (grpc.aio.insecure_channel(target, options=options) if credentials is None
                        else grpc.aio.secure_channel(target, credentials, options=options))
        self.datasets = datasets_pb2_grpc.DatasetServiceStub(self.channel)
        self.models = models_pb2_grpc.ModelServiceStub(self.channel)
        self.jobs = jobs_pb2_grpc.JobServiceStub(self.channel)
        self.rewards = reward_pb2_grpc.RewardServiceStub(self.channel)
        self.health = self.channel.unary_unary("/grpc.health.v1.Health/Check", request_serializer=lambda _: b"",
                                               response_deserializer=lambda b: b)


class AsyncClient:
    """asyncio twin of :class:`relreward.Client`: the same arguments (``timeout`` and
    ``retry_budget`` included), the same methods as coroutines (``watch_job`` and
    ``sample_iter`` as async iterators, ``gradient_stream`` as an async context manager); see
    :class:`relreward.Client`'s docstrings for units and shapes.

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

    @property
    def _datasets(self) -> datasets_pb2_grpc.DatasetServiceStub:
        return self._conn().datasets

    @property
    def _models(self) -> models_pb2_grpc.ModelServiceStub:
        return self._conn().models

    @property
    def _jobs(self) -> jobs_pb2_grpc.JobServiceStub:
        return self._conn().jobs

    @property
    def _rewards(self) -> reward_pb2_grpc.RewardServiceStub:
        return self._conn().rewards

    async def close(self) -> None:
        """Closes the channel (if a call made one); streams still open on it end. A later call
        makes a new one."""
        if self._connection is not None:
            connection, self._connection = self._connection, None
            await connection.channel.close()

    async def health(self) -> str:
        """See :meth:`relreward.Client.health`: "SERVING", "NOT_SERVING", "UNKNOWN" or
        "SERVICE_UNKNOWN" from grpc.health.v1 (retried as a read)."""
        return c.health_status(await self._idempotent(self._conn().health, None))

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _once(self, method: Callable[..., Awaitable[T]], request: Any) -> T:
        try:
            return await method(request, metadata=self._metadata, timeout=self.timeout)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None

    async def _idempotent(self, method: Callable[..., Awaitable[T]], request: Any) -> T:
        clock = c.Attempts(self.timeout, self.retry_budget)
        while True:
            try:
                return await method(request, metadata=self._metadata, timeout=clock.deadline())
            except grpc.RpcError as e:
                if not is_retryable(e):
                    raise from_rpc_error(e) from None
                delay = clock.delay()
                if delay is None:
                    raise from_rpc_error(e) from None
                await asyncio.sleep(delay)

    async def _all_pages(self, call: Callable[[tensor_pb2.PageRequest], Awaitable[Any]], field: str) -> list:
        out: list = []
        token = ""
        while True:
            resp = await call(tensor_pb2.PageRequest(page_token=token))
            out.extend(getattr(resp, field))
            token = resp.next_page_token
            if not token:
                return out

    # datasets
    async def upload_dataset(self, name: str, data: Any, *, kind: str | None = None, key: str | None = None,
                             description: str = "", chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                             progress: c.Progress | bool | None = None) -> datasets_pb2.Dataset:
        """See :meth:`relreward.Client.upload_dataset` (the input is read on the event loop's
        thread between chunks)."""
        source, closer = source_of(data, kind, key)
        try:
            callback, bar = c.progress_callback(progress, source.total_bytes(), name)
            failure = c.UploadFailure()
            try:
                return await self._datasets.UploadDataset(
                    c.dataset_messages(name, source, description, chunk_bytes, callback, failure),
                    metadata=self._metadata, timeout=self.timeout)
            except grpc.RpcError as e:
                if failure.error is not None:
                    raise failure.error from None
                raise from_rpc_error(e) from None
            finally:
                if bar is not None:
                    bar.close()
        finally:
            if closer is not None:
                closer.close()

    async def get_dataset(self, name: str) -> datasets_pb2.Dataset:
        """See :meth:`relreward.Client.get_dataset`: the dataset with its statistics."""
        return await self._idempotent(self._datasets.GetDataset,
                                      datasets_pb2.GetDatasetRequest(name=name, view=datasets_pb2.DATASET_VIEW_FULL))

    async def list_datasets(self) -> list[datasets_pb2.Dataset]:
        """See :meth:`relreward.Client.list_datasets`: every dataset, by name."""
        return await self._all_pages(lambda page: self._idempotent(
            self._datasets.ListDatasets, datasets_pb2.ListDatasetsRequest(page=page, view=datasets_pb2.DATASET_VIEW_BASIC)),
            "datasets")

    async def delete_dataset(self, name: str) -> None:
        """See :meth:`relreward.Client.delete_dataset` (never retried)."""
        await self._once(self._datasets.DeleteDataset, datasets_pb2.DeleteDatasetRequest(name=name))

    # models
    async def upload_model(self, path: str | pathlib.Path, name: str,
                           manifest: Mapping[str, Any] | models_pb2.DiffusionManifest, *, description: str = "",
                           chunk_bytes: int = c.DEFAULT_CHUNK_BYTES,
                           progress: c.Progress | bool | None = None) -> models_pb2.Model:
        """See :meth:`relreward.Client.upload_model`."""
        path = pathlib.Path(path)
        header = c.upload_header(name, manifest_of(manifest), description)
        callback, bar = c.progress_callback(progress, path.stat().st_size, name)
        failure = c.UploadFailure()
        try:
            return await self._models.UploadModel(c.model_messages(path, header, chunk_bytes, callback, failure),
                                                  metadata=self._metadata, timeout=self.timeout)
        except grpc.RpcError as e:
            if failure.error is not None:
                raise failure.error from None
            raise from_rpc_error(e) from None
        finally:
            if bar is not None:
                bar.close()

    async def get_model(self, name: str) -> models_pb2.Model:
        """See :meth:`relreward.Client.get_model`: kind, manifest or reward info."""
        return await self._idempotent(self._models.GetModel, models_pb2.GetModelRequest(name=name))

    async def list_models(self, kind: str | None = None) -> list[models_pb2.Model]:
        """See :meth:`relreward.Client.list_models`: every model, or those of ``kind``."""
        k = _KINDS[kind]
        return await self._all_pages(lambda page: self._idempotent(
            self._models.ListModels, models_pb2.ListModelsRequest(page=page, kind=k)), "models")

    async def delete_model(self, name: str) -> None:
        """See :meth:`relreward.Client.delete_model` (never retried)."""
        await self._once(self._models.DeleteModel, models_pb2.DeleteModelRequest(name=name))

    async def download_model(self, name: str, out_dir: str | pathlib.Path, *, overwrite: bool = False
                             ) -> DownloadedModel:
        """See :meth:`relreward.Client.download_model` (files are written on the event loop's
        thread as chunks arrive)."""
        download = ModelDownload(name, out_dir, overwrite)
        call = self._models.DownloadModel(models_pb2.DownloadModelRequest(name=name), metadata=self._metadata,
                                          timeout=self.timeout)
        try:
            async for message in call:
                download.feed(message)
            return download.finish()
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None
        finally:
            download.close()
            call.cancel()

    # jobs
    async def submit_job(self, spec: Any, job_id: str | None = None) -> jobs_pb2.Job:
        """See :meth:`relreward.Client.submit_job`: queues a training job (never retried)."""
        return await self._once(self._jobs.SubmitJob,
                                jobs_pb2.SubmitJobRequest(spec=job_spec(spec), job_id=job_id or ""))

    async def get_job(self, job_id: str) -> jobs_pb2.Job:
        """See :meth:`relreward.Client.get_job`: state, step / total_steps, loss, error."""
        return await self._idempotent(self._jobs.GetJob, jobs_pb2.GetJobRequest(id=job_id))

    async def list_jobs(self, state: str | None = None) -> list[jobs_pb2.Job]:
        """See :meth:`relreward.Client.list_jobs`: every job, or those in ``state``, newest first."""
        s = _STATES[state.lower() if state else None]
        return await self._all_pages(lambda page: self._idempotent(
            self._jobs.ListJobs, jobs_pb2.ListJobsRequest(page=page, state=s)), "jobs")

    async def cancel_job(self, job_id: str) -> jobs_pb2.Job:
        """See :meth:`relreward.Client.cancel_job` (never retried)."""
        return await self._once(self._jobs.CancelJob, jobs_pb2.CancelJobRequest(id=job_id))

    async def watch_job(self, job_id: str, from_seq: int = 0, *, reconnect_budget: float = c.WATCH_BUDGET_S
                        ) -> AsyncIterator[c.JobEvent]:
        """See :meth:`relreward.Client.watch_job`: every event once, resuming after a drop."""
        watch = c.WatchCursor(job_id, from_seq, reconnect_budget)
        while True:
            call = None
            try:
                call = self._jobs.WatchJob(watch.request(), metadata=self._metadata)
                async for raw in call:
                    event = watch.accept(raw)
                    if event is not None:
                        yield event
                        if event.terminal:
                            return
                if c.is_terminal((await self.get_job(job_id)).state):
                    return
                failure = watch.ended()
            except grpc.RpcError as e:
                failure = from_rpc_error(e)
            finally:
                if call is not None:
                    call.cancel()
            await asyncio.sleep(watch.retry_delay(failure))

    async def wait_job(self, job_id: str, on_event: Callable[[c.JobEvent], Any] | None = None) -> jobs_pb2.Job:
        """See :meth:`relreward.Client.wait_job`: follows the job until it finishes and returns
        it; ``on_event`` sees every event (a plain function, or a coroutine function, which is
        awaited). Does not raise for a FAILED or CANCELLED job: check ``job.state``."""
        async for event in self.watch_job(job_id):
            if on_event is not None:
                result = on_event(event)
                if asyncio.iscoroutine(result):
                    await result
        return await self.get_job(job_id)

    # rewards
    async def score(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None = 0, *, units: str = "raw",
                    per_window: bool = False, per_step: bool = False) -> c.ScoreResult:
        """See :meth:`relreward.Client.score`: rho(x, t) per item (retried as a read)."""
        return c.score_result(await self._idempotent(self._rewards.Score,
                                                     c.score_request(model, x, t, units, per_window, per_step)))

    async def gradient(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None, *,
                       omega: float | None = None, units: str = "raw", gradient_units: str | None = None,
                       scale_by_posterior_variance_of: str | None = None) -> c.GradientResult:
        """See :meth:`relreward.Client.gradient`: grad_x rho(x_t, t) and rho (retried as a read)."""
        req = c.gradient_request(model, x, t, omega, units, gradient_units or units, scale_by_posterior_variance_of)
        return c.gradient_result(await self._idempotent(self._rewards.Gradient, req))

    def gradient_stream(self, model: str, *, omega: float | None = None, units: str = "raw",
                        gradient_units: str | None = None, scale_by_posterior_variance_of: str | None = None
                        ) -> "AsyncGradientStream":
        """``async with client.gradient_stream(model) as s: grad, rho = await s.gradient(x, t)``."""
        return AsyncGradientStream(self._rewards.GradientStream, self._metadata, model, omega, units,
                                   gradient_units or units, scale_by_posterior_variance_of)

    async def sample_iter(self, model: str, *, reward_model: str | None = None, omega: float = 0.0, n: int = 1,
                          seed: int | None = None, n_guide_steps: int | None = None, t_stopgrad: int | None = None,
                          scale_grad_by_std: bool = False, conditions: Any = None, units: str = "raw",
                          batch_size: int = 0) -> AsyncIterator[c.Sample]:
        """See :meth:`relreward.Client.sample_iter`: each sample as it finishes (not retried)."""
        req = c.sample_request(model, reward_model, omega, n, seed, n_guide_steps, t_stopgrad, scale_grad_by_std,
                               conditions, units, batch_size)
        call = self._rewards.Sample(req, metadata=self._metadata, timeout=self.timeout)
        try:
            async for r in call:
                yield c.sample_of(r)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None
        finally:
            call.cancel()

    async def sample(self, model: str, **kwargs: Any) -> c.SampleBatch:
        """See :meth:`relreward.Client.sample`: every sample stacked in index order."""
        return c.stack_samples([s async for s in self.sample_iter(model, **kwargs)])


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
                     scale_by_posterior_variance_of: str | None = None) -> "asyncio.Future[c.GradientResult]":
        """Sends a request; returns a future of its ``GradientResult``."""
        if self._call is None:
            raise ValueError("use the stream as `async with client.gradient_stream(model) as s`")
        if self._failed is not None:
            raise self._failed
        d_omega, d_units, d_gunits, d_scale = self._defaults
        self._next_id += 1
        rid = self._next_id
        fut: asyncio.Future = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        await self._call.write(c.gradient_request(model or self.model, x, t, d_omega if omega is None else omega,
                                                  units or d_units, gradient_units or d_gunits,
                                                  scale_by_posterior_variance_of or d_scale, rid))
        return fut

    async def gradient(self, x: Any, t: Any, **kwargs: Any) -> c.GradientResult:
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
