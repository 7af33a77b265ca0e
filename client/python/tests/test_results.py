"""The package's own results (issue 34, items 12 and 13): no public method of Client or
AsyncClient returns a protobuf message, every returned type can be imported from the module it
names, a job's state is one type everywhere, the results carry the CLI's names and values,
a job's spec comes back as the typed spec it stands for, and the sync and asyncio clients,
which run the same plans, return equal results for the same calls."""

from __future__ import annotations

import asyncio
import dataclasses
import datetime as dt
import enum
import importlib
import inspect
import json
import math
import pathlib
import sys
import warnings

import numpy as np
import pytest
import torch
from google.protobuf.message import Message

import relreward
from relreward.v1 import jobs_pb2

from conftest import tiny_trajectories


def _protobuf_inside(value, path="result", seen=None):
    """Paths under ``value`` that hold a protobuf message, or an object whose class cannot be
    imported from the module it names (what protobuf's classes report: ``relreward.v1``).
    ``.proto`` attributes are the documented way to the raw message and are skipped."""
    seen = set() if seen is None else seen
    if id(value) in seen or value is None or isinstance(value, (str, bytes, int, float, bool, pathlib.Path,
                                                                  dt.datetime, np.ndarray, np.generic)):
        return []
    seen.add(id(value))
    if isinstance(value, Message):
        return [f"{path}: a {type(value).__module__}.{type(value).__qualname__} message"]
    out = []
    cls = type(value)
    try:
        resolved = importlib.import_module(cls.__module__)
        for part in cls.__qualname__.split("."):
            resolved = getattr(resolved, part)
        if resolved is not cls:
            out.append(f"{path}: {cls.__module__}.{cls.__qualname__} is another class")
    except (ImportError, AttributeError):
        out.append(f"{path}: its class {cls.__module__}.{cls.__qualname__} cannot be imported")
    if dataclasses.is_dataclass(value):
        for f in dataclasses.fields(value):
            if f.name != "proto":
                out += _protobuf_inside(getattr(value, f.name), f"{path}.{f.name}", seen)
    elif isinstance(value, dict):
        for k, v in value.items():
            out += _protobuf_inside(v, f"{path}[{k!r}]", seen)
    elif isinstance(value, (list, tuple)):
        for k, v in enumerate(value):
            out += _protobuf_inside(v, f"{path}[{k}]", seen)
    return out


class _HalvingAutoencoder(torch.nn.Module):
    """[1, 4] items <-> [1, 2] latents (pairs averaged, then repeated back)."""

    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool1d(x, 2)

    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return z.repeat_interleave(2, dim=2)


class _ConditionalDenoiser(torch.nn.Module):
    """forward(x, t, cond): a conditional eps model small enough for the walk's recipe."""

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return 0.5 * x + cond.to(x.dtype).view(-1, 1, 1)


def _public_methods(cls) -> set[str]:
    return {n for n, m in inspect.getmembers(cls) if not n.startswith("_") and inspect.isfunction(m)}


@pytest.fixture(scope="module")
def finished(client, tiny):
    """A diffusion job that ran to the end (the tiny fixture's jobs ran through the CLI)."""
    job = client.submit_job(relreward.DiffusionJob(
        output_model="py-results-m", dataset=tiny.dataset, horizon=8, n_timesteps=10, seed=3,
        architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
        optimization=relreward.Optimization(steps=4, batch_size=8, log_every=2)), job_id="py-results-job")
    done = client.wait_job(job.id)
    assert done.state is relreward.JobState.SUCCEEDED, done
    return done


def test_no_public_method_returns_a_protobuf_message(client, server, tiny, finished, tmp_path):
    """Every public method of both clients, called against the real server: what it returns
    (iterators drained, streams asked) holds the package's types only."""
    x = np.zeros((2, tiny.horizon, tiny.transition_dim), np.float32)
    long_job = relreward.DiffusionJob(output_model="py-results-long", dataset=tiny.dataset, horizon=8, n_timesteps=10,
                                      architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
                                      optimization=relreward.Optimization(steps=100000, batch_size=8))

    def calls(tag: str):
        """(method name, thunk) for every public method; a thunk returns an awaitable or a
        value, and iterators are drained below."""
        base = client.get_model(tiny.base)
        weights = client.download_model(tiny.base, tmp_path / f"base-{tag}").path
        # A bring-your-own reward: the tiny reward's export (raw units, so the identity normalizer).
        module = client.export_model(tiny.reward, tmp_path / f"byo-{tag}").module
        byo = {"signature": "rho", "n_timesteps": tiny.n_timesteps, "normalizer": {"kind": "identity"},
               "space": {"kind": "trajectory", "horizon": tiny.horizon, "action_dim": 2,
                         "obs_dim": tiny.transition_dim - 2}}
        autoencoder = tmp_path / f"ae-{tag}.pt"
        torch.jit.script(_HalvingAutoencoder()).save(str(autoencoder))
        conditional = tmp_path / f"cond-{tag}.pt"
        torch.jit.script(_ConditionalDenoiser()).save(str(conditional))
        client.upload_model(conditional, f"py-walk-cond-{tag}", {
            "parametrization": "epsilon", "n_timesteps": 4, "clip_denoised": False, "schedule": {"kind": "cosine"},
            "space": {"kind": "sample", "shape": [1, 4]}, "normalizer": {"kind": "identity"},
            "conditioning": {"kind": "labels", "num_classes": 3, "null_class": 2}})
        return {
            "health": lambda c: c.health(),
            "upload_dataset": lambda c: c.upload_dataset(f"py-walk-{tag}", np.zeros((4, 3), np.float32)),
            "get_dataset": lambda c: c.get_dataset(tiny.dataset),
            "list_datasets": lambda c: c.list_datasets(),
            "delete_dataset": lambda c: c.delete_dataset(f"py-walk-{tag}"),
            "upload_model": lambda c: c.upload_model(weights, f"py-walk-{tag}", base.manifest),
            "upload_reward": lambda c: c.upload_reward(module, f"py-walk-byo-{tag}", byo),
            "upload_autoencoder": lambda c: c.upload_autoencoder(autoencoder, f"py-walk-ae-{tag}",
                                                                 {"image_shape": [1, 4], "latent_shape": [1, 2]}),
            "get_model": lambda c: c.get_model(tiny.reward),
            "list_models": lambda c: c.list_models(),
            "delete_model": lambda c: c.delete_model(f"py-walk-{tag}"),
            "create_recipe": lambda c: c.create_recipe(f"py-walk-recipe-{tag}", f"py-walk-cond-{tag}",
                                                       relreward.SamplingRecipe([0, 1], guidance_scale=2.0)),
            "download_model": lambda c: c.download_model(tiny.reward, tmp_path / f"rw-{tag}"),
            "export_model": lambda c: c.export_model(tiny.reward, tmp_path / f"rw-export-{tag}"),
            "submit_job": lambda c: c.submit_job(long_job, job_id=f"py-walk-{tag}"),
            "cancel_job": lambda c: c.cancel_job(f"py-walk-{tag}"),
            "get_job": lambda c: c.get_job(finished.id),
            "list_jobs": lambda c: c.list_jobs(),
            "watch_job": lambda c: c.watch_job(finished.id),
            "wait_job": lambda c: c.wait_job(finished.id),
            "score": lambda c: c.score(tiny.reward, x, 1, per_step=True),
            "gradient": lambda c: c.gradient(tiny.reward, x, 1),
            "sample_iter": lambda c: c.sample_iter(tiny.base, n=2, seed=1, reward_model=tiny.reward),
            "sample": lambda c: c.sample(tiny.base, n=2, seed=1),
            "encode": lambda c: c.encode(f"py-walk-ae-{tag}", np.ones((2, 1, 4), np.float32)),
            "decode": lambda c: c.decode(f"py-walk-ae-{tag}", np.ones((2, 1, 2), np.float32)),
            "gradient_stream": lambda c: c.gradient_stream(tiny.reward),
            "close": lambda c: c.close(),
        }

    sync_calls, async_calls = calls("sync"), calls("async")
    for cls in (relreward.Client, relreward.AsyncClient):
        assert _public_methods(cls) == set(sync_calls), f"{cls.__name__}: a method this test does not call"

    got = {}
    with relreward.Client(server.addr) as c:
        for name, call in sync_calls.items():
            value = call(c)
            if name == "gradient_stream":
                with value as stream:
                    value = [stream.gradient(x, 1), stream.submit(x, 2).result()]
            elif inspect.isgenerator(value):
                value = list(value)
            got[f"Client.{name}"] = value

    async def run_async():
        c = relreward.AsyncClient(server.addr)
        for name, call in async_calls.items():
            value = call(c)
            if name == "gradient_stream":
                async with value as stream:
                    value = [await stream.gradient(x, 1), await (await stream.submit(x, 2))]
            elif inspect.isasyncgen(value):
                value = [v async for v in value]
            elif inspect.isawaitable(value):
                value = await value
            got[f"AsyncClient.{name}"] = value

    asyncio.run(run_async())
    problems = [p for name, value in got.items() for p in _protobuf_inside(value, name)]
    assert not problems, problems
    # Not vacuous: the calls answered with the package's types.
    assert isinstance(got["Client.get_model"], relreward.Model)
    assert isinstance(got["AsyncClient.get_job"], relreward.Job)
    assert isinstance(got["Client.download_model"].model, relreward.Model)
    assert all(isinstance(e, relreward.JobEvent) for e in got["AsyncClient.watch_job"])
    assert got["Client.cancel_job"].id == "py-walk-sync" and got["AsyncClient.upload_model"].format == "native"


def test_sync_and_async_return_equal_results(client, server, tiny, finished):
    x = np.random.default_rng(0).standard_normal((3, tiny.horizon, tiny.transition_dim)).astype(np.float32)

    def reads(c):
        return [c.health(), c.get_dataset(tiny.dataset), c.list_datasets(), c.get_model(tiny.base),
                c.get_model(tiny.reward), c.list_models(), c.list_models("reward"), c.get_job(finished.id),
                c.list_jobs("succeeded"), c.watch_job(finished.id), c.watch_job(finished.id, from_seq=3),
                c.wait_job(finished.id), c.score(tiny.reward, x, [0, 1, 2]), c.gradient(tiny.reward, x, 2),
                c.sample(tiny.base, n=2, seed=4)]

    sync = [list(v) if inspect.isgenerator(v) else v for v in reads(client)]

    async def run_async():
        async with relreward.AsyncClient(server.addr) as ac:
            out = []
            for v in reads(ac):
                out.append([e async for e in v] if inspect.isasyncgen(v) else await v)
            return out

    for s, a in zip(sync, asyncio.run(run_async()), strict=True):
        if isinstance(s, (relreward.ScoreResult, relreward.GradientResult, relreward.SampleBatch)):
            assert type(s) is type(a)
            for f in dataclasses.fields(s):
                np.testing.assert_array_equal(getattr(s, f.name), getattr(a, f.name))
        else:
            assert s == a
    assert sync[1].arrays[0].stats is not None and sync[7].spec.output_model == "py-results-m"


def test_a_job_state_is_one_type_everywhere(client, tiny, finished):
    job = client.get_job(finished.id)
    listed = next(j for j in client.list_jobs() if j.id == finished.id)
    events = list(client.watch_job(finished.id))
    states = [e.state for e in events if e.type == "state"]
    assert job.state is listed.state is client.wait_job(finished.id).state is states[-1] is relreward.JobState.SUCCEEDED
    assert all(isinstance(s, relreward.JobState) for s in states) and states[0] in ("pending", "running")
    assert job.state == "succeeded" and str(job.state) == "succeeded" and f"{job.state}" == "succeeded"
    assert events[-1].terminal and job.state.terminal and not relreward.JobState.RUNNING.terminal
    # Every wire state has its member, and back.
    for number in jobs_pb2.JobState.values():
        assert relreward.JobState.from_proto(number).to_proto() == number
    # The filter takes the enum or its name in any case, and names a state it does not know.
    by_enum = [j.id for j in client.list_jobs(relreward.JobState.SUCCEEDED)]
    assert by_enum == [j.id for j in client.list_jobs("SUCCEEDED")] == [j.id for j in client.list_jobs("succeeded")]
    assert finished.id in by_enum
    # A cancelled job: cancel_job's answer, its last event and get_job all say so with the one type.
    job = client.submit_job(relreward.DiffusionJob(
        output_model="py-results-cancel", dataset=tiny.dataset, horizon=8, n_timesteps=10,
        architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
        optimization=relreward.Optimization(steps=100000, batch_size=8, log_every=1)))
    assert isinstance(client.cancel_job(job.id).state, relreward.JobState)
    last = list(client.watch_job(job.id))[-1]
    assert last.state is client.get_job(job.id).state is relreward.JobState.CANCELLED


def test_bad_filters_and_names_are_refused_naming_the_argument():
    with relreward.Client("127.0.0.1:1") as client:  # nothing is sent
        with pytest.raises(relreward.InvalidInput, match="state: 'done'"):
            client.list_jobs("done")
        with pytest.raises(relreward.InvalidInput, match="kind: 'rewards'"):
            client.list_models("rewards")
        for call, says in ((lambda: client.get_model(3), "name: 3 is int, not a string"),
                           (lambda: client.get_job(None), "job_id: None is NoneType"),
                           (lambda: client.score(7, np.zeros((1, 2)), 0), "model: 7 is int"),
                           (lambda: client.gradient(b"m", np.zeros((1, 2)), 0), "model: b'm' is bytes")):
            with pytest.raises(relreward.InvalidInput, match=says):
                call()


def _same_values(py, cli, path="") -> list[str]:
    """Where the package's ``as_dict()`` and the CLI's ``--json`` differ: the same keys and
    values, times as instants the CLI truncated, a non-finite number equal to the CLI's null."""
    if isinstance(cli, dict) and isinstance(py, dict):
        if set(py) != set(cli):
            return [f"{path}: keys {sorted(set(py) ^ set(cli))} differ"]
        return [d for k in cli for d in _same_values(py[k], cli[k], f"{path}.{k}")]
    if isinstance(cli, list) and isinstance(py, list):
        if len(py) != len(cli):
            return [f"{path}: {len(py)} items, the CLI's {len(cli)}"]
        return [d for i, (p, q) in enumerate(zip(py, cli)) for d in _same_values(p, q, f"{path}[{i}]")]
    if isinstance(cli, str) and isinstance(py, str) and cli.endswith("Z") and py.endswith("Z") and "T" in cli:
        # The CLI truncates times (to seconds, to milliseconds for events).
        late = dt.datetime.fromisoformat(py[:-1] + "+00:00") - dt.datetime.fromisoformat(cli[:-1] + "+00:00")
        return [] if dt.timedelta(0) <= late < dt.timedelta(seconds=1) else [f"{path}: {py} != {cli}"]
    if cli is None and isinstance(py, float) and not math.isfinite(py):
        return []
    if isinstance(cli, float) and isinstance(py, float):
        return [] if cli == py or math.isclose(cli, py, rel_tol=1e-12) else [f"{path}: {py!r} != {cli!r}"]
    return [] if py == cli and type(py) is type(cli) or (py == cli and {type(py), type(cli)} <= {int, float}) \
        else [f"{path}: {py!r} != {cli!r}"]


def test_results_carry_the_clis_names_and_values(client, server, tiny, finished):
    for name in (tiny.base, tiny.reward):
        diff = _same_values(client.get_model(name).as_dict(), server.cli_json("model", "show", name))
        assert not diff, (name, diff)
    diff = _same_values(client.get_dataset(tiny.dataset).as_dict(), server.cli_json("dataset", "show", tiny.dataset))
    assert not diff, diff
    job, cli_job = client.get_job(finished.id).as_dict(), server.cli_json("job", "show", finished.id)
    job.pop("spec")
    cli_job.pop("spec")  # the CLI prints its config file's form; the package gives the typed spec
    assert not _same_values(job, cli_job), _same_values(job, cli_job)
    lines = server.cli("--json", "job", "watch", finished.id).stdout.splitlines()
    cli_events = [json.loads(line) for line in lines if line.startswith("{") and '"seq"' in line]
    events = [e.as_dict() for e in client.watch_job(finished.id)]
    assert cli_events and not _same_values(events, cli_events), _same_values(events, cli_events)
    # as_dict() is plain JSON.
    json.dumps([client.get_model(tiny.base).as_dict(), client.get_dataset(tiny.dataset).as_dict()])


def test_item_shape_and_t_of_every_kind(client, tiny):
    for name in (tiny.base, tiny.expert, tiny.reward):
        m = client.get_model(name)
        assert m.item_shape == (tiny.horizon, tiny.transition_dim) and m.n_timesteps == tiny.n_timesteps, m
    base = client.get_model(tiny.base)
    assert base.manifest.space.kind == "trajectory" and base.manifest.space.item_shape == base.item_shape
    assert client.get_model(tiny.reward).reward.normalizer.kind in ("limits", "gaussian", "identity")


def test_a_jobs_spec_is_the_typed_spec_and_submits_the_same_job(client, tiny, finished):
    """job.spec rebuilds the JobSpec exactly: resubmitted under the job's own id, the server
    finds it the same spec (a different one would be AlreadyExists) and returns that job."""
    spec = finished.spec
    # What was given comes back; the server filled in its defaults for the rest.
    assert isinstance(spec, relreward.DiffusionJob)
    assert (spec.output_model, spec.dataset, spec.horizon, spec.n_timesteps, spec.seed, spec.architecture) == (
        "py-results-m", tiny.dataset, 8, 10, 3, ("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}))
    assert (spec.optimization.steps, spec.optimization.batch_size, spec.optimization.log_every) == (4, 8, 2)
    assert spec.parametrization in ("x0", "epsilon") and spec.schedule is not None
    assert client.submit_job(spec, job_id=finished.id).id == finished.id
    # The tiny fixture's jobs came from the CLI's own config and flags: each spec kind.
    jobs = {j.spec.output_model: j for j in client.list_jobs() if j.spec is not None}
    for name, kind in ((tiny.base, relreward.DiffusionJob), (tiny.reward, relreward.RewardJob)):
        job = jobs[name]
        assert isinstance(job.spec, kind), job.spec
        assert client.submit_job(job.spec, job_id=job.id).id == job.id
    client.upload_dataset("py-results-expert", tiny_trajectories(seed=12))
    disc = client.submit_job(relreward.DiscriminatorJob(
        output_model="py-results-disc", base_dataset=tiny.dataset, expert_dataset="py-results-expert",
        diffusion_model=tiny.base, architecture=("windowed_mlp", {"window": 4, "hidden": [8]}), seed=1,
        inpaint_condition=True, optimization=relreward.Optimization(steps=2, batch_size=8)))
    assert isinstance(disc.spec, relreward.DiscriminatorJob) and disc.spec.inpaint_condition is True
    assert client.submit_job(disc.spec, job_id=disc.id).id == disc.id
    client.wait_job(disc.id)


def test_reprs_are_short_and_name_the_record(client, tiny, finished):
    model = client.get_model(tiny.reward)
    text = repr(model)
    assert text.startswith(f"Model(name='{tiny.reward}', kind='reward'") and "proto" not in text
    stats = relreward.ArrayStats(*[tuple(float(i) for i in range(40))] * 4)
    assert "[40 values]" in repr(stats) and len(repr(stats)) < 400
    assert model == dataclasses.replace(model, proto=None)  # the raw message is not part of ==
    space = client.get_model(tiny.base).manifest.space
    assert repr(space) == f"Space(kind='trajectory', horizon={tiny.horizon}, action_dim={space.action_dim}, " \
                          f"obs_dim={space.obs_dim})"
    state = next(e for e in client.watch_job(finished.id) if e.type == "state")
    assert repr(state).startswith("JobEvent(seq=1, time=") and "message=" in repr(state) and "loss=" not in repr(state)
    assert model.proto.name == tiny.reward


def test_progress_warning_names_the_callers_line(server, monkeypatch):
    """Without tqdm, ``progress=True`` warns at the caller's upload line, from either client
    (the plans run a few frames below the public method)."""
    from relreward import _common

    monkeypatch.setitem(sys.modules, "tqdm", None)
    monkeypatch.setitem(sys.modules, "tqdm.auto", None)
    data = np.zeros((4, 2), np.float32)
    for run in ("sync", "async"):
        monkeypatch.setattr(_common, "_warned_no_tqdm", False)
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            if run == "sync":
                with relreward.Client(server.addr) as c:
                    c.upload_dataset("py-results-warn-sync", data, progress=True)
            else:
                async def main():
                    async with relreward.AsyncClient(server.addr) as ac:
                        await ac.upload_dataset("py-results-warn-async", data, progress=True)

                asyncio.run(main())
        tqdm_warnings = [w for w in seen if "tqdm is not installed" in str(w.message)]
        assert tqdm_warnings and tqdm_warnings[0].filename == __file__, (run, [(w.filename, w.lineno) for w in seen])


def test_job_state_is_a_string_enum():
    assert issubclass(relreward.JobState, str) and issubclass(relreward.JobState, enum.Enum)
    assert [s.value for s in relreward.JobState] == ["unspecified", "pending", "running", "succeeded", "failed",
                                                      "cancelled"]


def test_a_failure_is_raised_alone(client, server):
    """A call's RelrewardError does not carry grpcio's exception as its context or cause (the
    clients used to say ``raise ... from None``; the plans raise what the driver throws into
    them), from either client."""
    with pytest.raises(relreward.NotFound) as sync:
        client.get_model("py-results-nope")

    async def main():
        async with relreward.AsyncClient(server.addr) as ac:
            await ac.get_model("py-results-nope")

    with pytest.raises(relreward.NotFound) as aio:
        asyncio.run(main())
    for e in (sync.value, aio.value):
        assert e.__context__ is None and e.__cause__ is None, repr(e.__context__)
