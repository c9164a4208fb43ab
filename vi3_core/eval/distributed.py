"""Evaluation on a Ray cluster (``vi3 eval INPUT... --ray [ADDRESS]``): the clips of independent evaluations, and
whole sequences of chained ones (a sequence's online state is sequential), as tasks of a pool of Ray actors.

Each actor (``EvalWorker``) builds the backbone once and opens the inputs itself, from a path that every node sees
(a shared file system), keeping the last sequence it opened; what travels is a task's frame indices and options
one way and its ``ClipEval`` records (numpy data, no tensors) the other. A task calls the serial evaluation's own
functions (``runner.evaluate_frames`` per clip, ``runner.evaluate_online`` per chained sequence), so every clip gets
the numbers the serial run gives it.

Faults: a task whose worker process dies (killed, out of memory, its node lost) is run again on a fresh worker, at
most ``retries`` times; a task that still fails, or that fails in the evaluation itself (a clip that cannot be
read), is reported in its job's ``errors`` and the others go on. Ctrl-C (KeyboardInterrupt) kills the workers and
returns what had finished, ``interrupted`` set.

Ray is optional: it is imported when a run starts (``import_ray``).
"""

from __future__ import annotations

import os
import socket
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vi3_core.backbones.base import Backbone
from vi3_core.dataset.sequence import Sequence
from vi3_core.errors import ClusterUnavailable, DataError, Vi3Error
from vi3_core.eval import runner
from vi3_core.eval.clip_eval import ClipEval

INSTALL_HINT = "pip install ray (in a clone of this repository: pip install '.[ray]')"
POLL_S = 0.5  # how often the progress of running chained sequences is asked for


def import_ray() -> Any:
    """The ``ray`` module, or ClusterUnavailable saying how to install it."""
    try:
        import ray
    except ImportError as err:
        raise ClusterUnavailable(f"evaluating on Ray needs Ray, which this Python cannot import ({err}); install "
                                 f"it with {INSTALL_HINT}") from None
    return ray


def connect(address: str | None) -> bool:
    """Connect this process to the Ray cluster at ``address`` ("auto": the cluster this machine belongs to,
    "HOST:PORT" of its head node, "ray://HOST:PORT" through Ray Client), or start a local instance on this machine's
    cores (None, or "local"; None connects to RAY_ADDRESS when that is set). A process already connected stays as it
    is. Returns whether this call connected (the caller then disconnects: ``ray.shutdown()``)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    try:
        ray.init(address=address or None)
    except (ConnectionError, RuntimeError, ValueError) as err:
        raise ClusterUnavailable(f"cannot connect to the Ray cluster at {address or 'RAY_ADDRESS'}: {err}") from None
    return True


@dataclass(frozen=True)
class Job:
    """One evaluation of one input: ``source`` the path the workers open (absolute: every node must see it),
    ``name`` the sequence's name in the report, ``options`` (``progress`` is ignored: the caller's bar counts
    clips), ``clips`` the frame indices [n] of its clips (``runner.check_sequence``), ``chained``: one task for the
    whole sequence (``runner.evaluate_online``) instead of one per clip (``runner.evaluate_frames``)."""

    source: str
    name: str
    options: runner.EvalOptions
    clips: tuple[np.ndarray, ...]
    chained: bool = False


@dataclass
class JobResult:
    """What a job (or one of its tasks) produced: ``evals`` in clip order (the clips that were evaluated),
    ``online`` (chained jobs) and ``errors``, each naming the clip or sequence that failed and why."""

    evals: list[ClipEval] = field(default_factory=list)
    online: runner.OnlineRun | None = None
    errors: list[str] = field(default_factory=list)


@dataclass
class RunReport:
    """A distributed run: ``results`` one per job, in the jobs' order; ``workers`` where each worker ran (host and
    pid, replacements included); ``retried``: a line per task run again after its worker died; ``interrupted``:
    Ctrl-C stopped the run (the unfinished jobs say so in their errors)."""

    results: list[JobResult]
    workers: list[str]
    retried: list[str]
    interrupted: bool = False


class EvalWorker:
    """The body of an evaluation actor: ``backbone()`` built once, the last opened sequence kept. ``error`` says why
    the backbone could not be built ("" when it was): the driver asks (``ready``) before giving it work."""

    def __init__(self, backbone: Callable[[], Backbone], open_sequence: Callable[[str], Sequence]) -> None:
        os.dup2(2, 1)  # what a backbone prints goes to the driver's stderr: its stdout may carry a JSON report
        self.where = f"{socket.gethostname()} pid {os.getpid()}"
        self.error = ""
        self._open, self._seq = open_sequence, None
        self._done = 0
        try:
            self.backbone = backbone()
        except (Vi3Error, ImportError, ValueError, OSError, RuntimeError) as err:
            self.backbone, self.error = None, f"{type(err).__name__}: {err}"

    def ready(self) -> tuple[str, str]:
        """(where this worker runs, why its backbone could not be built or "")."""
        return self.where, self.error

    def progress(self) -> int:
        """Clips that the running chained task has evaluated (asked while it runs: ``concurrency_group``)."""
        return self._done

    def _sequence(self, source: str, name: str) -> Sequence:
        if self._seq is None or self._seq[0] != (source, name):
            self._seq = None  # let the previous one go first: bags are read whole
            try:
                seq = self._open(source)
            except (Vi3Error, ValueError, OSError) as err:
                raise DataError(f"cannot open {source} on {self.where}: {err}") from err
            seq.name = name
            self._seq = ((source, name), seq)
        return self._seq[1]

    def clip(self, source: str, name: str, options: runner.EvalOptions, idx: np.ndarray) -> JobResult:
        """The clip of frames ``idx`` of the input at ``source``."""
        try:
            return JobResult([runner.evaluate_frames(self._sequence(source, name), idx, self.backbone,
                                                     options=options)])
        except (Vi3Error, ValueError, OSError) as err:
            return JobResult(errors=[f"{runner.clip_label(name, idx)}: {err}"])

    def sequence(self, source: str, name: str, options: runner.EvalOptions) -> JobResult:
        """The chained evaluation of the input at ``source``; what was computed before a failing clip is kept."""
        self._done = 0
        try:
            evals, online = runner.evaluate_online(self._sequence(source, name), self.backbone, options=options,
                                                   on_clip=self._count)
        except runner.EvaluationStopped as exc:
            return JobResult(exc.evals, exc.online, [str(exc)])
        except (Vi3Error, ValueError, OSError) as err:
            return JobResult(errors=[str(err)])
        return JobResult(evals, online)

    def _count(self, done: int) -> None:
        self._done = done


@dataclass(frozen=True)
class _Task:
    job: int
    clip: int | None  # None: the whole (chained) sequence


def evaluate(jobs: list[Job], *, backbone: Callable[[], Backbone], open_sequence: Callable[[str], Sequence],
             cpus_per_task: float = 1.0, gpus_per_task: float = 0.0, retries: int = 2,
             on_progress: Callable[[int], None] | None = None,
             on_event: Callable[[str], None] | None = None) -> RunReport:
    """Evaluate ``jobs`` on the connected Ray cluster (``connect``) with as many workers as it has room for
    (``cpus_per_task`` CPUs and ``gpus_per_task`` GPUs each; at most one per task). ``backbone()`` builds a worker's
    backbone and ``open_sequence(source)`` opens an input (both run on the workers: they must pickle, e.g. module
    functions or ``functools.partial`` of them). ``on_progress(n)``: n clips finished so far (evaluated or failed);
    ``on_event(line)``: a worker died and its task runs again, or a worker could not be replaced. Raises
    ClusterUnavailable when no worker can start (too few resources, the backbone cannot be built)."""
    ray = import_ray()
    tasks = [_Task(j, None) if job.chained else _Task(j, k) for j, job in enumerate(jobs)
             for k in ([None] if job.chained else range(len(job.clips)))]
    # Longest sequences first, so that a long one does not start last; clips in their order.
    tasks.sort(key=lambda t: -len(jobs[t.job].clips) if t.clip is None else 0)
    workers = min(len(tasks), _capacity(ray, cpus_per_task, gpus_per_task))
    pool = _Pool(ray, jobs, backbone=backbone, open_sequence=open_sequence, cpus=cpus_per_task, gpus=gpus_per_task,
                 retries=retries, on_progress=on_progress, on_event=on_event)
    try:
        return pool.run(tasks, workers)
    finally:
        pool.stop()


def _capacity(ray: Any, cpus: float, gpus: float) -> int:
    """Workers of ``cpus`` CPUs and ``gpus`` GPUs the cluster has room for; ClusterUnavailable when none."""
    if cpus < 0 or gpus < 0 or cpus + gpus <= 0:
        raise ValueError(f"a worker needs some CPUs or GPUs: got {cpus:g} CPUs and {gpus:g} GPUs per task")
    have = ray.cluster_resources()
    fits = [int(have.get(name, 0.0) / need + 1e-9) for name, need in (("CPU", cpus), ("GPU", gpus)) if need > 0]
    if min(fits) < 1:
        raise ClusterUnavailable(f"the Ray cluster has {have.get('CPU', 0):g} CPUs and {have.get('GPU', 0):g} GPUs; "
                                 f"a worker needs {cpus:g} CPUs and {gpus:g} GPUs")
    return min(fits)


class _Pool:
    """The workers of one run and the loop that feeds them: at most one task in flight per worker, a dead worker
    replaced (its task resubmitted while it has retries left), progress counted in clips."""

    def __init__(self, ray: Any, jobs: list[Job], *, backbone: Callable[[], Backbone],
                 open_sequence: Callable[[str], Sequence], cpus: float, gpus: float, retries: int,
                 on_progress: Callable[[int], None] | None, on_event: Callable[[str], None] | None) -> None:
        self.ray, self.jobs, self.retries = ray, jobs, retries
        self.on_progress, self.on_event = on_progress, on_event or (lambda line: None)
        self.actor_class = ray.remote(concurrency_groups={"progress": 1})(EvalWorker).options(
            num_cpus=cpus, num_gpus=gpus, max_restarts=0, max_task_retries=0)
        self.factories = (backbone, open_sequence)
        self.slots: list = []  # the actor of each slot, None once a slot could not be refilled
        self.where: list[str] = []
        self.workers: list[str] = []
        self.starting: dict = {}  # ready() ref -> slot of a replacement worker
        self.running: dict = {}  # task ref -> (slot, task)
        self.attempts: dict[_Task, int] = {}
        self.outcomes: dict[_Task, JobResult] = {}
        self.retried: list[str] = []
        self.done = 0
        self.chained_done: dict[int, int] = {}  # slot -> clips its running chained task has evaluated

    def _start(self, n: int) -> None:
        self.slots = [self.actor_class.remote(*self.factories) for _ in range(n)]
        try:
            ready = self.ray.get([a.ready.remote() for a in self.slots])
        except self.ray.exceptions.RayError as err:
            raise ClusterUnavailable(f"a Ray worker could not start: {err}") from None
        for where, error in ready:
            if error:
                raise ClusterUnavailable(f"the backbone cannot be built on the Ray worker on {where}: {error}")
        self.where = [where for where, _ in ready]
        self.workers = list(self.where)

    def stop(self) -> None:
        for actor in self.slots:
            if actor is not None:
                self.ray.kill(actor, no_restart=True)

    def run(self, tasks: list[_Task], workers: int) -> RunReport:
        queue = deque(tasks)
        interrupted = False
        try:
            self._start(workers)
            for slot in range(len(self.slots)):
                self._submit(slot, queue)
            while self.running or self.starting:
                chained = any(t.clip is None for _, t in self.running.values())
                ready, _ = self.ray.wait([*self.running, *self.starting], num_returns=1,
                                         timeout=POLL_S if chained and self.on_progress else None)
                for ref in ready:
                    slot = self._started(ref) if ref in self.starting else self._finished(ref, queue)
                    self._submit(slot, queue)
                if chained and self.on_progress:
                    self._poll()
                if not self.running and not self.starting and queue:
                    self._give_up(queue, "no Ray worker is left to run it")
        except KeyboardInterrupt:
            interrupted = True
        return RunReport(self._results(interrupted), self.workers, self.retried, interrupted)

    def _label(self, task: _Task) -> str:
        job = self.jobs[task.job]
        return f"sequence {job.name!r}" if task.clip is None else runner.clip_label(job.name, job.clips[task.clip])

    def _submit(self, slot: int | None, queue: deque) -> None:
        if slot is None or self.slots[slot] is None or not queue:
            return
        task, actor = queue.popleft(), self.slots[slot]
        job = self.jobs[task.job]
        if task.clip is None:
            ref = actor.sequence.remote(job.source, job.name, job.options)
            self.chained_done[slot] = 0
        else:
            ref = actor.clip.remote(job.source, job.name, job.options, job.clips[task.clip])
        self.running[ref] = (slot, task)

    def _finished(self, ref, queue: deque) -> int | None:
        """Record the result of a task; the slot to give work to (None while its replacement starts)."""
        slot, task = self.running.pop(ref)
        self.chained_done.pop(slot, None)
        try:
            outcome = self.ray.get(ref)
        except self.ray.exceptions.RayActorError as err:  # the worker process died: replace it, maybe retry
            tries = self.attempts[task] = self.attempts.get(task, 0) + 1
            why = f"its worker on {self.where[slot]} died ({str(err).splitlines()[0].strip()})"
            self._replace(slot)
            if tries <= self.retries:
                line = f"{self._label(task)}: {why}; running it again ({tries} of {self.retries} retries)"
                self.retried.append(line)
                self.on_event(line)
                queue.appendleft(task)
                return None
            outcome = JobResult(errors=[f"{self._label(task)}: {why}, after {self.retries} retries"])
            slot = None
        except self.ray.exceptions.RayTaskError as err:  # an exception the evaluation does not expect
            cause = err.cause if err.cause is not None else err
            outcome = JobResult(errors=[f"{self._label(task)}: {type(cause).__name__}: {cause}"])
        self.outcomes[task] = outcome
        self._count(len(self.jobs[task.job].clips) if task.clip is None else 1)
        return slot

    def _replace(self, slot: int) -> None:
        self.ray.kill(self.slots[slot], no_restart=True)
        self.slots[slot] = self.actor_class.remote(*self.factories)
        self.starting[self.slots[slot].ready.remote()] = slot

    def _started(self, ref) -> int | None:
        """A replacement worker's ready() came back: the slot when it can work, else None (the slot stays empty)."""
        slot = self.starting.pop(ref)
        try:
            where, error = self.ray.get(ref)
        except self.ray.exceptions.RayError as err:
            where, error = "?", str(err).splitlines()[0]
        if error:
            self.ray.kill(self.slots[slot], no_restart=True)
            self.slots[slot] = None
            self.on_event(f"a replacement Ray worker could not start ({where}): {error}; "
                          f"{sum(a is not None for a in self.slots)} workers left")
            return None
        self.where[slot] = where
        self.workers.append(where)
        return slot

    def _give_up(self, queue: deque, why: str) -> None:
        while queue:
            task = queue.popleft()
            self.outcomes[task] = JobResult(errors=[f"{self._label(task)}: {why}"])
            self._count(len(self.jobs[task.job].clips) if task.clip is None else 1)

    def _count(self, clips: int) -> None:
        self.done += clips
        if self.on_progress:
            self.on_progress(self.done + sum(self.chained_done.values()))

    def _poll(self) -> None:
        """Ask the workers running chained sequences how far they are (answers that take long are skipped)."""
        asked = {self.slots[slot].progress.options(concurrency_group="progress").remote(): slot
                 for slot, task in self.running.values() if task.clip is None}
        if not asked:
            return
        ready, _ = self.ray.wait(list(asked), num_returns=len(asked), timeout=POLL_S)
        for ref in ready:
            try:
                self.chained_done[asked[ref]] = int(self.ray.get(ref))
            except self.ray.exceptions.RayError:
                continue  # the worker died: its task's result says so
        self.on_progress(self.done + sum(self.chained_done.values()))

    def _results(self, interrupted: bool) -> list[JobResult]:
        """One result per job: its tasks' outcomes in clip order; an unfinished job says how far it got."""
        results = []
        for j, job in enumerate(self.jobs):
            parts = [(t.clip or 0, o) for t, o in self.outcomes.items() if t.job == j]
            parts.sort(key=lambda p: p[0])
            res = JobResult([e for _, o in parts for e in o.evals], next((o.online for _, o in parts), None),
                            [e for _, o in parts for e in o.errors])
            finished = len(parts) == (1 if job.chained else len(job.clips))
            if interrupted and not finished:
                res.errors.append(runner.interrupted_note(len(res.evals), len(job.clips)))
            results.append(res)
        return results
