"""Experiment tracking: a training job's events written as TensorBoard event files, and
optionally to a Weights & Biases run in offline mode.

    from relreward.tracking import follow
    with relreward.Client("127.0.0.1:50051") as client:
        follow(client, job.id, "runs")            # then: tensorboard --logdir runs

or from a shell: ``python -m relreward.tracking JOB_ID --logdir runs [--wandb-project NAME]``.

Module map:

- :class:`Writer`: what a tracker implements: ``start(job, resumed)``, ``write(event, step)``,
  ``close()``.
- :class:`TensorBoardWriter`: tensorboardX's ``SummaryWriter``: progress events as scalars
  (``train/loss``, ``train/eval_loss``, ``train/grad_norm``, ``train/learning_rate``,
  ``train/steps_per_second``) at the event's training step and time; state changes, log lines
  and checkpoints as text (``job/state``, ``job/log``, ``job/checkpoint``); the job's kind and
  spec as text (``job/spec``) once, at step 0.
- :class:`WandbWriter`: ``wandb.init(mode="offline")``, the job's spec as the run's config,
  the same scalars through ``run.log(..., step=step)``, the job's state in the run's summary.
- :func:`log_events`: any iterable of :class:`relreward.JobEvent` into writers.
- :func:`follow` / :func:`follow_async`: watch a job (sync or asyncio client) to its end into
  a logdir, resumable: ``<logdir>/relreward-<job>.seq`` holds the last event number written,
  and a re-run starts after it.

Where things go under the logdir: ``<job>/`` holds the job's TensorBoard event files (so
``tensorboard --logdir DIR`` shows each followed job as a run named by its id),
``relreward-<job>.seq`` the follower's position, and ``wandb/`` the W&B offline runs (upload
them with ``wandb sync DIR/wandb/offline-run-*``).

**Restarts.** The position is recorded *before* an event is handed to the writers: a follower
killed at any point never writes an event twice when run again, at the cost of losing, on a
hard kill (SIGKILL, power loss), the events still in the writers' buffers (TensorBoard's are
flushed every ``flush_secs``, 2 s here). An exception or Ctrl-C closes the writers, which writes
out everything handed to them. A job whose events were all written (terminal, its last event
recorded) returns at once, opening no writer, so nothing new appears in the logdir. A server
restart mid-job replays the steps after the job's last checkpoint as new events: TensorBoard
shows the replayed points in place of the first ones (it drops points whose step went
backwards), W&B keeps the first ones (it ignores a step below one it has).

tensorboardX (``pip install relreward[tensorboard]``) and wandb (``pip install
relreward[wandb]``) are optional: neither is imported until its writer is made.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
from typing import TYPE_CHECKING, Any, Callable, Iterable, Protocol

from relreward import specs
from relreward.errors import InvalidInput, RelrewardError
from relreward.results import Job, JobEvent, JobState

if TYPE_CHECKING:
    from relreward.aio import AsyncClient
    from relreward.client import Client

#: Where the scalars of a progress event go, by JobEvent field.
SCALARS = {"loss": "train/loss", "eval_loss": "train/eval_loss", "grad_norm": "train/grad_norm",
           "learning_rate": "train/learning_rate", "steps_per_second": "train/steps_per_second"}

_KINDS = {specs.DiffusionJob: "diffusion", specs.RewardJob: "reward", specs.DiscriminatorJob: "discriminator"}


class Writer(Protocol):
    """A tracker :func:`log_events` and :func:`follow` write to."""

    def start(self, job: Job, resumed: bool) -> None:
        """Called once per :func:`follow`, before any event; ``resumed``: the logdir already
        holds this job's earlier events (so the spec was written before)."""

    def write(self, event: JobEvent, step: int) -> None:
        """One event, at training step ``step`` (the event's own for progress and checkpoint
        events, else the last step written before it)."""

    def close(self) -> None:
        """Writes out whatever is buffered; no call follows."""


def kind_of(job: Job) -> str | None:
    """"diffusion", "reward" or "discriminator": what the job trains (None without a spec)."""
    return _KINDS.get(type(job.spec))


def spec_dict(job: Job) -> dict[str, Any]:
    """The job's kind and typed spec as plain values (``job.as_dict()``'s spec), without the
    fields left unset (None: the server's defaults, whose values the spec does not hold)."""
    def set_only(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: set_only(x) for k, x in v.items() if x is not None}
        return [set_only(x) for x in v] if isinstance(v, list) else v

    spec = job.as_dict().get("spec") or {}
    return {"job_id": job.id, "kind": kind_of(job), **set_only(spec)}


def _scalars(event: JobEvent) -> dict[str, float]:
    return {tag: float(getattr(event, name)) for name, tag in SCALARS.items() if getattr(event, name) is not None}


def _state_text(event: JobEvent) -> str:
    return f"{event.state}: {event.message}" if event.message else str(event.state)


class TensorBoardWriter:
    """TensorBoard event files in ``logdir`` through tensorboardX's ``SummaryWriter`` (a new
    file per writer, as TensorBoard expects of a restarted run). Walltimes are the events'
    server times, so a resumed or replayed job's points keep their real times.

    ``filename_suffix`` ends the event file's name, ``events.out.tfevents.<unix seconds>.<host>``:
    tensorboardX truncates a file of the same name, so two writers started in one second need
    different suffixes, and TensorBoard reads a run's files in name order."""

    def __init__(self, logdir: str | os.PathLike, *, flush_secs: int = 2, filename_suffix: str = "") -> None:
        try:
            from tensorboardX import SummaryWriter
        except ImportError as e:
            raise ImportError("relreward.tracking.TensorBoardWriter needs tensorboardX: "
                              "pip install relreward[tensorboard]") from e
        self.logdir = pathlib.Path(logdir)
        # flush_secs: how long a hard-killed follower's points may sit unwritten (module docs).
        self._tb = SummaryWriter(logdir=str(self.logdir), flush_secs=flush_secs, filename_suffix=filename_suffix)

    def start(self, job: Job, resumed: bool) -> None:
        if resumed:
            return
        # Markdown: an indented block keeps the JSON's layout in TensorBoard's text dashboard.
        body = json.dumps(spec_dict(job), indent=2, sort_keys=True)
        text = f"**{kind_of(job)}** job `{job.id}`\n\n" + "\n".join("    " + line for line in body.splitlines())
        self._tb.add_text("job/spec", text, 0, walltime=_walltime(job.created_at))

    def write(self, event: JobEvent, step: int) -> None:
        walltime = _walltime(event.time)
        if event.type == "progress":
            for tag, value in _scalars(event).items():
                self._tb.add_scalar(tag, value, step, walltime=walltime)
        elif event.type == "state":
            self._tb.add_text("job/state", _state_text(event), step, walltime=walltime)
        elif event.type == "log":
            self._tb.add_text("job/log", event.message, step, walltime=walltime)
        elif event.type == "checkpoint":
            self._tb.add_text("job/checkpoint", f"checkpoint at step {step}", step, walltime=walltime)

    def close(self) -> None:
        self._tb.close()


class WandbWriter:
    """A W&B run in offline mode under ``dir`` (``<dir>/wandb/offline-run-*``), one per job: its
    id and name are the job's id and its config the job's spec (:func:`spec_dict`), so
    ``wandb sync`` uploads every follower's part of a job into one run. Scalars are logged at
    the events' training steps (stamped with the time they are logged: ``run.log`` takes no
    time, unlike TensorBoard's writer, which gets the events' own); the job's state goes to the run's summary (``job/state``,
    ``job/message``), and a job that failed or was cancelled finishes the run with exit code 1.

    ``close()`` finishes the run; W&B's service process writes the rest of the run's file
    after that, and it is complete when the service lets go of it: at this process's exit, or
    once ``wandb.teardown()`` (which finishes every run of the process) returns."""

    def __init__(self, project: str, dir: str | os.PathLike) -> None:
        try:
            import wandb
        except ImportError as e:
            raise ImportError("relreward.tracking.WandbWriter needs wandb: pip install relreward[wandb]") from e
        self._wandb = wandb
        self.project = project
        self.dir = pathlib.Path(dir)
        self._run: Any = None
        self._exit_code = 0

    def start(self, job: Job, resumed: bool) -> None:
        # resume="allow" with the job's id: a resumed follower continues the same run on sync.
        # reinit="create_new": a run the caller has open stays theirs (by default init would
        # return it, and the job's metrics would land in it). console="off": the follower's own
        # output is not the job's log.
        self._run = self._wandb.init(
            mode="offline", dir=str(self.dir), project=self.project, name=job.id, id=job.id, resume="allow",
            reinit="create_new", config=spec_dict(job), settings=self._wandb.Settings(console="off", silent=True))

    def write(self, event: JobEvent, step: int) -> None:
        if event.type == "progress":
            self._run.log(_scalars(event), step=step)
        elif event.type == "state":
            self._run.summary["job/state"] = str(event.state)
            self._run.summary["job/message"] = event.message
            if event.state in (JobState.FAILED, JobState.CANCELLED):
                self._exit_code = 1

    def close(self) -> None:
        if self._run is not None:
            self._run.finish(exit_code=self._exit_code)
            self._run = None


def _walltime(t: Any) -> float | None:
    return t.timestamp() if t is not None else None


def _step_of(event: JobEvent, last: int) -> int:
    """The training step an event is written at: progress and checkpoint events carry theirs;
    state changes and log lines happen at the last step seen (TensorBoard needs one)."""
    return event.step if event.type in ("progress", "checkpoint") and event.step is not None else last


def log_events(events: Iterable[JobEvent], writers: Iterable[Writer], *, step: int = 0,
               before_write: Callable[[JobEvent, int], None] | None = None) -> int:
    """Writes each event to every writer, in order, and returns the step of the last one.

    ``step``: the step to write state changes and log lines at until a progress event comes
    (a resumed follower passes the step it had reached). ``before_write(event, step)`` runs
    before the writers see the event (:func:`follow` records its position there)."""
    writers = list(writers)
    for event in events:
        step = _step_of(event, step)
        if before_write is not None:
            before_write(event, step)
        for w in writers:
            w.write(event, step)
    return step


# --------------------------------------------------------------------------------------------
# Following a job into a logdir


@dataclasses.dataclass(frozen=True)
class _Position:
    """The last event written of a job (seq 0: none yet, only the spec) and its step."""

    seq: int
    step: int


class _Log:
    """A job's logdir: its position file and the writers for it."""

    def __init__(self, logdir: str | os.PathLike, job_id: str, wandb_project: str | None) -> None:
        self.logdir = pathlib.Path(logdir)
        self.job_id = job_id
        self.wandb_project = wandb_project
        self.path = self.logdir / f"relreward-{job_id}.seq"

    def read(self) -> _Position | None:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        try:
            d = json.loads(text)
            if d["job"] != self.job_id:
                raise ValueError(f"it is job {d['job']!r}'s")
            return _Position(int(d["seq"]), int(d["step"]))
        except (ValueError, KeyError, TypeError) as e:
            raise InvalidInput(f"logdir: {self.path} is not a relreward position file of job {self.job_id!r} ({e}); "
                               "remove it to write the job from its start") from None

    def save(self, seq: int, step: int) -> None:
        # Written beside and renamed over: a kill mid-write leaves the old position, never half a file.
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps({"job": self.job_id, "seq": seq, "step": step}) + "\n")
        os.replace(tmp, self.path)

    def check(self, job: Job, at: _Position | None) -> bool:
        """Whether anything is left to write: not when the job finished and its last event was
        written. A position past the job's last event is another job's of that id (a server
        with other data): refused, rather than skipping that job's first events."""
        if at is None:
            return True
        if at.seq > job.last_seq:
            raise InvalidInput(f"logdir: {self.path} records {at.seq} events written, but job {job.id!r} has "
                               f"{job.last_seq}: it was written from another server's job of that id; "
                               "use another logdir")
        return not (job.state.terminal and at.seq >= job.last_seq)

    def open(self, job: Job, at: _Position | None) -> tuple[list[Writer], _Position]:
        """The writers, started, and the position to go on from."""
        # W&B's writer first: it only imports wandb, so a missing wandb is reported before the
        # TensorBoard writer creates its event file.
        wandb = [WandbWriter(self.wandb_project, self.logdir)] if self.wandb_project is not None else []
        self.logdir.mkdir(parents=True, exist_ok=True)
        # The first seq it will hold names the file: a follower resumed in the second its
        # predecessor started gets a file of its own, which sorts after the predecessor's.
        first = at.seq + 1 if at is not None else 0
        tb = TensorBoardWriter(self.logdir / self.job_id, filename_suffix=f".relreward-from-{first:09d}")
        writers: list[Writer] = [tb, *wandb]
        try:
            resumed = at is not None
            if at is None:
                # Recorded before the spec is written, as every event is (module docs).
                at = _Position(0, 0)
                self.save(at.seq, at.step)
            for w in writers:
                w.start(job, resumed)
        except BaseException:
            _close(writers)
            raise
        return writers, at


def _close(writers: list[Writer]) -> None:
    errors = []
    for w in writers:
        try:
            w.close()
        except Exception as e:  # close the others first
            errors.append(e)
    if errors:
        raise errors[0]


def follow(client: Client, job_id: str, logdir: str | os.PathLike, *, wandb_project: str | None = None) -> Job:
    """Watches job ``job_id`` until it finishes, writing every event to TensorBoard under
    ``<logdir>/<job_id>/`` (and to a W&B offline run under ``<logdir>/wandb/`` with
    ``wandb_project``), and returns the job (a :class:`relreward.Job`) as it ended.

    ``client``: a :class:`relreward.Client`. Resumable: a follower stopped at any point and run
    again writes the events after the last one it wrote, never one twice; for a job whose events
    were all written it returns at once, writing nothing. An unknown job raises
    :class:`relreward.NotFound` before anything is created. Does not raise for a FAILED or
    CANCELLED job: check ``job.state``."""
    job = client.get_job(job_id)
    log = _Log(logdir, job_id, wandb_project)
    at = log.read()
    if not log.check(job, at):
        return job
    writers, at = log.open(job, at)
    try:
        log_events(client.watch_job(job_id, from_seq=at.seq + 1), writers, step=at.step,
                   before_write=lambda e, step: log.save(e.seq, step))
    finally:
        _close(writers)
    return client.get_job(job_id)


async def follow_async(client: AsyncClient, job_id: str, logdir: str | os.PathLike, *,
                       wandb_project: str | None = None) -> Job:
    """:func:`follow` for a :class:`relreward.AsyncClient`. The writers' calls are quick local
    writes made on the event loop (W&B's ``init`` takes about a second, once)."""
    job = await client.get_job(job_id)
    log = _Log(logdir, job_id, wandb_project)
    at = log.read()
    if not log.check(job, at):
        return job
    writers, at = log.open(job, at)
    try:
        step = at.step
        async for event in client.watch_job(job_id, from_seq=at.seq + 1):
            step = _step_of(event, step)
            log.save(event.seq, step)
            for w in writers:
                w.write(event, step)
    finally:
        _close(writers)
    return await client.get_job(job_id)


# --------------------------------------------------------------------------------------------
# Command line


def main(argv: list[str] | None = None) -> int:
    """``python -m relreward.tracking JOB_ID --logdir DIR``: exit status 0 when the job
    succeeded, 1 when it failed or was cancelled or on an error (printed as ``error: ...``, as
    the relreward CLI prints them), 130 on Ctrl-C (run it again to resume)."""
    import relreward

    p = argparse.ArgumentParser(prog="python -m relreward.tracking",
                                description="Write a relreward training job's events as TensorBoard event files "
                                            "(and a W&B offline run); resumable.")
    p.add_argument("job_id", metavar="JOB_ID")
    p.add_argument("--logdir", required=True, metavar="DIR",
                   help="TensorBoard logdir: the job's events go to DIR/JOB_ID, its W&B run to DIR/wandb")
    p.add_argument("--endpoint", default=os.environ.get("RELREWARD_ENDPOINT", "127.0.0.1:50051"), metavar="HOST:PORT",
                   help="server address, HOST:PORT or http(s)://HOST:PORT "
                        "(default: $RELREWARD_ENDPOINT or 127.0.0.1:50051)")
    p.add_argument("--token", default=os.environ.get("RELREWARD_TOKEN"), metavar="TOKEN",
                   help="bearer token for a server with access control (default: $RELREWARD_TOKEN)")
    p.add_argument("--wandb-project", metavar="NAME", help="also write a W&B offline run in this project")
    args = p.parse_args(argv)
    try:
        with relreward.Client(args.endpoint, token=args.token) as client:
            job = follow(client, args.job_id, args.logdir, wandb_project=args.wandb_project)
    except KeyboardInterrupt:
        print("interrupted: run the same command again to go on", file=sys.stderr)
        return 130
    except (RelrewardError, ImportError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    where = pathlib.Path(args.logdir) / job.id
    print(f"job {job.id} {job.state}: events in {where} (tensorboard --logdir {args.logdir})")
    if job.state is not JobState.SUCCEEDED:
        print(f"error: job {job.id} {job.state}" + (f": {job.error}" if job.error else ""), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
