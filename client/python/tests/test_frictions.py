"""Frictions a newcomer hit with the package (issue 34, items 14-16): arguments refused at the
package's door with the argument named, a retry budget that is a setting and a timeout that
bounds the whole call, writable arrays from the guide, a word when progress=True cannot show
anything, and builds that write nothing into the checkout.

None of these tests needs a server except where a fixture says so (a port nothing listens on
stands for a dead server)."""

from __future__ import annotations

import asyncio
import os
import re
import socket
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

import relreward
from relreward import _common
from relreward.guide import RewardGuide

from conftest import REPO


def dead_endpoint() -> str:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{s.getsockname()[1]}"


# ------------------------------------------------------------------------------------------
# Item 15: negative and fractional steps and counts are refused naming the argument.


BAD_T = [(-1, "t: -1 is negative"), ([3, -2], "t[1]: -2 is negative"), (np.array([0, -5]), "t[1]: -5 is negative"),
         (2.5, "t: 2.5 is not an integer"), (1 << 40, "t: 1099511627776 is past")]


@pytest.mark.parametrize("t, says", BAD_T)
def test_bad_t_is_refused_naming_t_in_every_call(t, says):
    x = np.zeros((2, 8, 4), np.float32)
    # Nothing listens: the refusal must come before any connection is tried.
    with relreward.Client(dead_endpoint()) as client:
        calls = [lambda: client.score("m", x, t=t), lambda: client.gradient("m", x, t=t)]
        with client.gradient_stream("m") as stream:
            calls.append(lambda: stream.submit(x, t))
            for call in calls:
                with pytest.raises(relreward.InvalidArgument, match=re.escape(says)) as e:
                    call()
                assert isinstance(e.value, ValueError) and isinstance(e.value, relreward.InvalidInput)
                assert "Value out of range" not in str(e.value)


def test_bad_integer_fields_of_sample_watch_and_specs_are_named():
    with relreward.Client(dead_endpoint()) as client:
        for kwargs, says in (({"n": -1}, "n: -1 is negative"), ({"t_stopgrad": -1}, "t_stopgrad: -1"),
                             ({"n_guide_steps": 1.5}, "n_guide_steps: 1.5 is not an integer"),
                             ({"seed": -7}, "seed: -7 is negative"), ({"batch_size": -2}, "batch_size: -2"),
                             ({"conditions": {-1: [0.0, 0.0]}}, "conditions index -1")):
            with pytest.raises(relreward.InvalidInput, match=says):
                client.sample("m", **kwargs)
        with pytest.raises(relreward.InvalidInput, match="from_seq: 2.5"):
            next(iter(client.watch_job("j", from_seq=2.5)))
        with pytest.raises(relreward.InvalidInput, match=r"DiffusionJob.horizon: -1 is negative"):
            client.submit_job(relreward.DiffusionJob("m", "d", horizon=-1))
        with pytest.raises(relreward.InvalidInput, match=r"RewardJob.optimization.steps: -3 is negative"):
            client.submit_job(relreward.RewardJob("m", "b", "e", optimization=relreward.Optimization(steps=-3)))


def test_async_client_refuses_bad_t_the_same_way():
    async def main():
        async with relreward.AsyncClient(dead_endpoint()) as client:
            x = np.zeros((1, 8, 4), np.float32)
            for call in (client.score("m", x, t=-1), client.gradient("m", x, t=-1)):
                with pytest.raises(relreward.InvalidInput, match="t: -1 is negative"):
                    await call
            with pytest.raises(relreward.InvalidInput, match="n: -1 is negative"):
                await client.sample("m", n=-1)
            async with client.gradient_stream("m") as stream:
                with pytest.raises(relreward.InvalidInput, match=r"t\[0\]: -3 is negative"):
                    await stream.submit(x, [-3])

    asyncio.run(main())


def test_valid_steps_still_go_through_unchanged():
    assert _common.times(None) == [] and _common.times(3) == [3] and _common.times(np.int64(4)) == [4]
    assert _common.times(np.array([0, 9], np.int32)) == [0, 9] and _common.times([1.0, 2]) == [1, 2]
    req = _common.gradient_request("m", np.zeros((1, 2, 2), np.float32), 7, None, "raw", "raw", None)
    assert list(req.t) == [7]


# ------------------------------------------------------------------------------------------
# Item 14: the retry budget is a setting; timeout bounds the whole call, retries included.


def test_timeout_bounds_the_whole_retried_call():
    with relreward.Client(dead_endpoint(), timeout=1.0) as client:
        started = time.monotonic()
        with pytest.raises(relreward.Unavailable):
            client.list_datasets()  # a read: retried, but only within the timeout
        assert time.monotonic() - started < 1.5
        assert client.retry_budget == 5.0  # the default, as the Rust client's


def test_retry_budget_is_a_setting():
    with relreward.Client(dead_endpoint(), retry_budget=0.3) as client:
        started = time.monotonic()
        with pytest.raises(relreward.Unavailable):
            client.get_model("m")
        assert time.monotonic() - started < 1.0
    with relreward.Client(dead_endpoint(), retry_budget=0) as client:
        started = time.monotonic()
        with pytest.raises(relreward.Unavailable):
            client.health()  # one attempt
        assert time.monotonic() - started < 0.5
    for bad in (-1, float("nan"), "5"):
        with pytest.raises(ValueError, match="retry_budget"):
            relreward.Client(dead_endpoint(), retry_budget=bad)
    with pytest.raises(ValueError, match="timeout"):
        relreward.Client(dead_endpoint(), timeout=-1)


def test_async_timeout_and_retry_budget():
    async def main():
        async with relreward.AsyncClient(dead_endpoint(), timeout=1.0) as client:
            started = time.monotonic()
            with pytest.raises(relreward.Unavailable):
                await client.list_models()
            assert time.monotonic() - started < 1.5
        async with relreward.AsyncClient(dead_endpoint(), retry_budget=0.3) as client:
            started = time.monotonic()
            with pytest.raises(relreward.Unavailable):
                await client.get_job("j")
            assert time.monotonic() - started < 1.0

    asyncio.run(main())


# ------------------------------------------------------------------------------------------
# Item 16: the guide's arrays are writable; progress=True without tqdm says so; builds leave
# the checkout as it was.


class _ReadOnlyStream:
    """Answers as the client does: read-only views of the response bytes."""

    def gradient(self, x, t):
        x = np.asarray(x, np.float32)
        grad = np.frombuffer(np.ones_like(x).tobytes(), np.float32).reshape(x.shape)
        rho = np.frombuffer(np.arange(x.shape[0], dtype=np.float32).tobytes(), np.float32)
        assert not grad.flags.writeable
        return relreward.GradientResult(grad, rho)


def test_guide_gradients_are_writable_for_diffusers_in_place_edit():
    guide = RewardGuide(None, "m")  # type: ignore[arg-type]
    guide._stream = _ReadOnlyStream()  # type: ignore[assignment]
    x = np.zeros((3, 8, 4), np.float32)
    t = np.array([0, 5, 9])
    y, grad = guide.gradients(x, None, t)
    t_stopgrad = 2
    grad[t < t_stopgrad] = 0  # Diffuser's n_step_guided_p_sample does this
    y[0] = 1.0
    assert grad[0].sum() == 0 and grad[1:].min() == 1 and y.tolist() == [1.0, 1.0, 2.0]


def test_progress_true_without_tqdm_warns_once(monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)  # import tqdm.auto now raises ImportError
    monkeypatch.setitem(sys.modules, "tqdm.auto", None)
    monkeypatch.setattr(_common, "_warned_no_tqdm", False, raising=False)
    with pytest.warns(RuntimeWarning, match="tqdm is not installed"):
        assert _common.progress_callback(True, 10, "d") == (None, None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _common.progress_callback(True, 10, "d") == (None, None)  # once per process


def _tree(root):
    """Every file under ``root`` (ignored ones included) with its size and mtime, less bytecode
    caches (pytest writes those while this runs)."""
    out = {}
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if d not in ("__pycache__", ".pytest_cache")]
        for name in files:
            st = os.stat(os.path.join(folder, name))
            out[os.path.relpath(os.path.join(folder, name), root)] = (st.st_size, st.st_mtime_ns)
    return out


def test_building_from_the_checkout_writes_nothing_into_it(tmp_path):
    pkg = REPO / "client" / "python"
    before = _tree(pkg)
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                        "--wheel-dir", str(tmp_path), str(pkg)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    assert list(tmp_path.glob("relreward-*.whl"))
    after = _tree(pkg)
    added = sorted(set(after) - set(before))
    changed = sorted(k for k in set(after) & set(before) if after[k] != before[k])
    assert not added and not changed, f"the build wrote into {pkg}: new {added[:10]}, rewritten {changed[:10]}"


# ------------------------------------------------------------------------------------------
# Item 13: AsyncClient has what Client has, may be made outside a loop, and every public
# method says what it does.


def test_async_client_made_outside_a_loop_works_in_asyncio_run(server):
    client = relreward.AsyncClient(server.addr)  # no loop runs here

    async def main():
        async with client:
            models = await client.list_models()  # used to fail: "attached to a different loop"
            assert await client.health() == "SERVING"
            assert client.channel is client.channel  # one channel, made on the first call
            return models

    assert isinstance(asyncio.run(main()), list)
    # Closed by `async with`; a new loop gets a new channel.
    assert asyncio.run(client.health()) == "SERVING"


def test_async_client_says_when_it_is_used_from_another_loop_or_none():
    client = relreward.AsyncClient(dead_endpoint())
    with pytest.raises(RuntimeError, match="no running event loop"):
        client.channel  # noqa: B018 (the property makes the channel)

    async def first():
        client.channel  # noqa: B018

    asyncio.run(first())

    async def second():
        with pytest.raises(RuntimeError, match="one AsyncClient per event loop"):
            await client.get_model("m")

    asyncio.run(second())


def test_async_wait_job_calls_on_event(server, tiny):
    async def main():
        async with relreward.AsyncClient(server.addr) as client:
            job = await client.submit_job(relreward.DiffusionJob(
                output_model="py-friction-wait", dataset=tiny.dataset, horizon=8, n_timesteps=10, seed=4,
                architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
                optimization=relreward.Optimization(steps=4, batch_size=8, log_every=2)))
            plain, awaited = [], []

            async def record(e):
                awaited.append(e.seq)

            done = await client.wait_job(job.id, on_event=plain.append)
            await client.wait_job(job.id, on_event=record)  # a finished job replays its events
            return done, plain, awaited

    done, plain, awaited = asyncio.run(main())
    assert done.state is relreward.JobState.SUCCEEDED
    assert [e.seq for e in plain] == list(range(1, len(plain) + 1)) and plain[-1].terminal
    assert awaited == [e.seq for e in plain]


def test_every_public_method_has_a_docstring():
    import inspect

    missing = []
    for name in relreward.__all__:
        cls = getattr(relreward, name)
        if not inspect.isclass(cls) or issubclass(cls, BaseException):
            continue
        for attr, member in inspect.getmembers(cls):
            if attr.startswith("_"):
                continue
            if inspect.isfunction(member) or inspect.ismethod(member) or isinstance(member, property):
                if not (member.__doc__ or "").strip():
                    missing.append(f"{name}.{attr}")
    assert not missing, missing
