"""The asyncio client: :class:`AsyncClient`, with the methods of :class:`relreward.Client` as
coroutines (``watch_job`` and ``sample_iter`` as async iterators, ``gradient_stream`` as an
async context manager). Same retry policy: reads and pure computations retried on
connection failures for up to 5 s, writes never."""

from __future__ import annotations

import asyncio
import pathlib
import time
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


class AsyncClient:
    """asyncio twin of :class:`relreward.Client` (same arguments; see its docstrings for units
    and shapes). Create it inside a running event loop; ``async with`` closes it."""

    def __init__(self, endpoint: str = "127.0.0.1:50051", token: str | None = None, tls: c.TLS | bool | None = None,
                 *, timeout: float | None = None) -> None:
        target, credentials, options = c.channel_args(endpoint, tls)
        self.endpoint = endpoint
        self.timeout = timeout
        self._metadata = c.metadata_of(token)
        self._channel = (grpc.aio.insecure_channel(target, options=options) if credentials is None
                         else grpc.aio.secure_channel(target, credentials, options=options))
        self._datasets = datasets_pb2_grpc.DatasetServiceStub(self._channel)
        self._models = models_pb2_grpc.ModelServiceStub(self._channel)
        self._jobs = jobs_pb2_grpc.JobServiceStub(self._channel)
        self._rewards = reward_pb2_grpc.RewardServiceStub(self._channel)

    async def close(self) -> None:
        await self._channel.close()

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
        started = time.monotonic()
        attempt = 0
        while True:
            try:
                return await method(request, metadata=self._metadata, timeout=self.timeout)
            except grpc.RpcError as e:
                if not is_retryable(e):
                    raise from_rpc_error(e) from None
                delay = c.backoff_delay(attempt, c.IDEMPOTENT_INITIAL_S, c.IDEMPOTENT_MAX_S,
                                        c.IDEMPOTENT_BUDGET_S - (time.monotonic() - started))
                if delay is None:
                    raise from_rpc_error(e) from None
                attempt += 1
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
        return await self._idempotent(self._datasets.GetDataset,
                                      datasets_pb2.GetDatasetRequest(name=name, view=datasets_pb2.DATASET_VIEW_FULL))

    async def list_datasets(self) -> list[datasets_pb2.Dataset]:
        return await self._all_pages(lambda page: self._idempotent(
            self._datasets.ListDatasets, datasets_pb2.ListDatasetsRequest(page=page, view=datasets_pb2.DATASET_VIEW_BASIC)),
            "datasets")

    async def delete_dataset(self, name: str) -> None:
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
        return await self._idempotent(self._models.GetModel, models_pb2.GetModelRequest(name=name))

    async def list_models(self, kind: str | None = None) -> list[models_pb2.Model]:
        k = _KINDS[kind]
        return await self._all_pages(lambda page: self._idempotent(
            self._models.ListModels, models_pb2.ListModelsRequest(page=page, kind=k)), "models")

    async def delete_model(self, name: str) -> None:
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
        return await self._once(self._jobs.SubmitJob,
                                jobs_pb2.SubmitJobRequest(spec=job_spec(spec), job_id=job_id or ""))

    async def get_job(self, job_id: str) -> jobs_pb2.Job:
        return await self._idempotent(self._jobs.GetJob, jobs_pb2.GetJobRequest(id=job_id))

    async def list_jobs(self, state: str | None = None) -> list[jobs_pb2.Job]:
        s = _STATES[state.lower() if state else None]
        return await self._all_pages(lambda page: self._idempotent(
            self._jobs.ListJobs, jobs_pb2.ListJobsRequest(page=page, state=s)), "jobs")

    async def cancel_job(self, job_id: str) -> jobs_pb2.Job:
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

    async def wait_job(self, job_id: str) -> jobs_pb2.Job:
        async for _ in self.watch_job(job_id):
            pass
        return await self.get_job(job_id)

    # rewards
    async def score(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None = 0, *, units: str = "raw",
                    per_window: bool = False, per_step: bool = False) -> c.ScoreResult:
        return c.score_result(await self._idempotent(self._rewards.Score,
                                                     c.score_request(model, x, t, units, per_window, per_step)))

    async def gradient(self, model: str, x: Any, t: int | Sequence[int] | np.ndarray | None, *,
                       omega: float | None = None, units: str = "raw", gradient_units: str | None = None,
                       scale_by_posterior_variance_of: str | None = None) -> c.GradientResult:
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
        return await (await self.submit(x, t, **kwargs))

    async def close(self) -> None:
        if self._call is not None:
            self._call.cancel()
        if self._reader is not None:
            try:
                await self._reader
            except BaseException:
                pass
