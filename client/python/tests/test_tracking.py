"""relreward.tracking against the real server: a tiny reward job (base and expert from the
`tiny` fixture, 12 steps, progress every 2, held-out loss every 4) followed into a logdir, its
TensorBoard event files read back with TensorBoard's own reader and compared with the job's
events; a follower cut mid-stream and run again writes every point exactly once; a job already
written writes nothing; the W&B offline run's history holds the losses."""

from __future__ import annotations

import json
import pathlib
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

import relreward
from relreward import tracking

pytest.importorskip("tensorboardX")
event_accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")

STEPS = 12


@pytest.fixture(scope="module")
def job(client, tiny):
    """The tiny reward job, submitted and not waited for: the first follower sees it live."""
    return client.submit_job(relreward.RewardJob(
        output_model="py-track-rw", base_model=tiny.base, expert_model=tiny.expert, datasets=[tiny.dataset], seed=5,
        architecture=("windowed_mlp", {"window": 4, "hidden": [8]}),
        optimization=relreward.Optimization(steps=STEPS, batch_size=8, log_every=2, eval_every=4)),
        job_id="py-track-job")


def read_run(run_dir: pathlib.Path) -> event_accumulator.EventAccumulator:
    ea = event_accumulator.EventAccumulator(str(run_dir), size_guidance={"scalars": 0, "tensors": 0})
    ea.Reload()
    return ea


def scalars(ea, tag: str) -> list[tuple[int, float, float]]:
    return [(s.step, s.value, s.wall_time) for s in ea.Scalars(tag)]


def texts(ea, tag: str) -> list[tuple[int, str]]:
    return [(t.step, t.tensor_proto.string_val[0].decode()) for t in ea.Tensors(f"{tag}/text_summary")]


def expected(events, field: str) -> list[tuple[int, float, float]]:
    """(step, value as float32, time) of every progress event that has ``field``."""
    return [(e.step, float(np.float32(getattr(e, field))), e.time.timestamp())
            for e in events if e.type == "progress" and getattr(e, field) is not None]


def files(d: pathlib.Path) -> dict[str, int]:
    return {str(p.relative_to(d)): p.stat().st_size for p in sorted(d.rglob("*")) if p.is_file()}


def check_run(ea, events) -> None:
    """The run holds each progress event's scalars once, at its step and time, and each state
    change once, in order."""
    for field, tag in tracking.SCALARS.items():
        got = scalars(ea, tag)
        want = expected(events, field)
        assert [(s, v) for s, v, _ in got] == [(s, v) for s, v, _ in want], tag
        np.testing.assert_allclose([w for *_, w in got], [w for *_, w in want], rtol=0, atol=1e-3)
    states = [str(e.state) + (f": {e.message}" if e.message else "") for e in events if e.type == "state"]
    assert [t for _, t in texts(ea, "job/state")] == states


def test_follow_writes_the_jobs_events_once_and_a_second_follow_writes_nothing(client, job, tmp_path):
    done = tracking.follow(client, job.id, tmp_path)
    assert done.state is relreward.JobState.SUCCEEDED
    events = list(client.watch_job(job.id))
    progress = [e for e in events if e.type == "progress"]
    assert [e.step for e in progress] == [1, *range(2, STEPS + 1, 2)]  # step 1, then every log_every

    ea = read_run(tmp_path / job.id)
    check_run(ea, events)
    # held-out loss where the job evaluated one (every 4 steps and the last), and only there
    assert [s for s, *_ in scalars(ea, "train/eval_loss")] == [4, 8, 12]
    final_step, final = texts(ea, "job/state")[-1]
    assert final_step == STEPS and final.startswith("succeeded: registered model 'py-track-rw'")
    (spec_step, spec), = texts(ea, "job/spec")
    assert spec_step == 0 and "**reward** job `py-track-job`" in spec and '"base_model": "base"' in spec
    position = json.loads((tmp_path / f"relreward-{job.id}.seq").read_text())
    assert position == {"job": job.id, "seq": events[-1].seq, "step": STEPS}

    before = files(tmp_path)
    started = time.monotonic()
    assert tracking.follow(client, job.id, tmp_path).state is relreward.JobState.SUCCEEDED
    assert time.monotonic() - started < 1.0  # returns at once: no watch, no writer opened
    assert files(tmp_path) == before


class CutAfter:
    """A client whose event stream breaks after ``n`` events, as a dying follower's would."""

    def __init__(self, client, n: int) -> None:
        self.client, self.n = client, n

    def get_job(self, job_id):
        return self.client.get_job(job_id)

    def watch_job(self, job_id, from_seq=0):
        for i, event in enumerate(self.client.watch_job(job_id, from_seq)):
            if i == self.n:
                raise ConnectionError("cut")
            yield event


def test_a_follower_cut_mid_stream_resumes_where_it_stopped(client, job, tmp_path):
    client.wait_job(job.id)
    events = list(client.watch_job(job.id))
    with pytest.raises(ConnectionError):
        tracking.follow(CutAfter(client, 5), job.id, tmp_path)
    assert json.loads((tmp_path / f"relreward-{job.id}.seq").read_text())["seq"] == 5
    with pytest.raises(ConnectionError):
        tracking.follow(CutAfter(client, 3), job.id, tmp_path)  # at once again: a file of its own
    assert tracking.follow(client, job.id, tmp_path).state is relreward.JobState.SUCCEEDED
    assert len(list((tmp_path / job.id).glob("events.out.tfevents.*"))) == 3
    ea = read_run(tmp_path / job.id)
    check_run(ea, events)
    assert len(texts(ea, "job/spec")) == 1


def test_follow_async(server, client, job, tmp_path):
    import asyncio

    client.wait_job(job.id)

    async def main():
        async with relreward.AsyncClient(server.addr) as ac:
            first = await tracking.follow_async(ac, job.id, tmp_path)
            before = files(tmp_path)
            again = await tracking.follow_async(ac, job.id, tmp_path)
            return first, again, before

    first, again, before = asyncio.run(main())
    assert first.state == again.state == "succeeded" and files(tmp_path) == before
    check_run(read_run(tmp_path / job.id), list(client.watch_job(job.id)))


def test_unknown_job_is_not_found_and_creates_nothing(client, server, tmp_path, capsys):
    logdir = tmp_path / "runs"
    with pytest.raises(relreward.NotFound):
        tracking.follow(client, "no-such-job", logdir)
    assert not logdir.exists()
    assert tracking.main(["no-such-job", "--logdir", str(logdir), "--endpoint", server.addr]) == 1
    assert capsys.readouterr().err.startswith("error: NOT_FOUND: ")
    assert not logdir.exists()


def test_a_position_past_the_jobs_events_is_refused(client, job, tmp_path):
    client.wait_job(job.id)
    (tmp_path / f"relreward-{job.id}.seq").write_text(json.dumps({"job": job.id, "seq": 10_000, "step": 0}))
    with pytest.raises(relreward.InvalidInput, match="another server's job of that id"):
        tracking.follow(client, job.id, tmp_path)
    (tmp_path / f"relreward-{job.id}.seq").write_text("garbage")
    with pytest.raises(relreward.InvalidInput, match=r"logdir: .* is not a relreward position file"):
        tracking.follow(client, job.id, tmp_path)


def test_command_line(server, client, job, tmp_path):
    client.wait_job(job.id)
    p = subprocess.run([sys.executable, "-m", "relreward.tracking", job.id, "--logdir", str(tmp_path),
                        "--endpoint", server.addr], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stderr == "" and p.stdout.startswith(f"job {job.id} succeeded: events in ")
    assert scalars(read_run(tmp_path / job.id), "train/loss")


def test_missing_writers_name_the_extra(monkeypatch, client, job, tmp_path):
    monkeypatch.setitem(sys.modules, "wandb", None)  # import wandb fails, as when not installed
    with pytest.raises(ImportError, match=r"pip install relreward\[wandb\]"):
        tracking.follow(client, job.id, tmp_path, wandb_project="p")
    assert files(tmp_path) == {}  # refused before the TensorBoard writer made a file
    monkeypatch.setitem(sys.modules, "tensorboardX", None)
    with pytest.raises(ImportError, match=r"pip install relreward\[tensorboard\]"):
        tracking.TensorBoardWriter(tmp_path)


# --------------------------------------------------------------------------------------------
# W&B offline


def wandb_records(path: pathlib.Path):
    """The records of a W&B run file (``run-<id>.wandb``): LevelDB's log format (32 KiB blocks
    of chunks, each a 7-byte header: CRC32C, length, type 1 full / 2 first / 3 middle / 4 last)
    after W&B's 7-byte file header (":W&B", magic, version), each record a ``Record`` message.
    wandb 0.31 ships no reader of its own; this one is for the test only."""
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    assert data[:4] == b":W&B"
    pos, pending = 7, b""
    while pos + 7 <= len(data):
        room = 32768 - pos % 32768
        if room < 7:  # a block's tail too short for a header is padding
            pos += room
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0:  # zero fill up to the block's end
            pos += room
            continue
        pending += data[pos + 7:pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            yield record
            pending = b""


def history_rows(path: pathlib.Path) -> list[dict]:
    """The rows ``run.log`` wrote (with W&B's own ``_step``, ``_runtime``, ``_timestamp``)."""
    return [{item.nested_key[0] if item.nested_key else item.key: json.loads(item.value_json)
             for item in r.history.item}
            for r in wandb_records(path) if r.WhichOneof("record_type") == "history"]


def test_wandb_offline_run_holds_the_losses(client, job, tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    # W&B's settings, cache and artifacts stay in the test's directory.
    for var in ("WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR", "WANDB_ARTIFACT_DIR"):
        monkeypatch.setenv(var, str(tmp_path / "wandb-home"))
    import wandb

    client.wait_job(job.id)
    events = list(client.watch_job(job.id))
    mine = wandb.init(mode="offline", dir=str(tmp_path / "mine"), project="mine", reinit="create_new")
    tracking.follow(client, job.id, tmp_path / "runs", wandb_project="relreward-test")
    mine.log({"mine": 1.0})  # the caller's own run is left open (a finished run refuses log)
    mine.finish()
    wandb.teardown()  # W&B's service writes the rest of the run file after finish(): wait for it
    mine_file, = (tmp_path / "mine" / "wandb").glob("offline-run-*/*.wandb")
    mine_keys = {key for row in history_rows(mine_file) for key in row}
    assert "mine" in mine_keys and "train/loss" not in mine_keys  # and holds none of the job's
    run_file, = (tmp_path / "runs" / "wandb").glob(f"offline-run-*-{job.id}/run-{job.id}.wandb")
    history = {row["_step"]: row for row in history_rows(run_file)}
    kinds = [r.WhichOneof("record_type") for r in wandb_records(run_file)]
    run, = (r.run for r in wandb_records(run_file) if r.WhichOneof("record_type") == "run")
    assert run.run_id == job.id and run.project == "relreward-test"
    config = {u.key: json.loads(u.value_json) for u in run.config.update}
    progress = [e for e in events if e.type == "progress"]
    assert sorted(history) == [e.step for e in progress], (kinds, run_file.stat().st_size)
    for e in progress:
        assert history[e.step]["train/loss"] == pytest.approx(e.loss, rel=1e-12)
        assert history[e.step].get("train/eval_loss") == (None if e.eval_loss is None else pytest.approx(e.eval_loss))
    assert config["kind"] == "reward" and config["base_model"] == "base" and config["job_id"] == job.id
