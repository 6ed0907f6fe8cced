"""Where offline work runs: in this process, on a local process pool, or on a Dask cluster.

The offline plane (a plan's candidate scoring, the experiment bench's seeds, the fault
campaign's cases, the analysis' grid) is many independent tasks. ``open_pool`` gives one
``WorkPool`` for all of them, behind the standard ``concurrent.futures.Executor``:

- ``workers=1``: the tasks run here, one after another (no process, nothing to pickle);
- ``workers=N`` (default: every core this process may use): a local process pool of N;
- ``scheduler="tcp://HOST:PORT"``: the tasks go to a Dask distributed cluster
  (``Client.get_executor()``). Dask is imported only then; it is the ``cluster`` extra.

What makes the result independent of where and how widely the work ran is the caller's part
of the contract: a task is a top-level function of picklable data only (no open file, no path
a worker would have to read, no random generator shared between tasks), and ``WorkPool.map``
returns the results in the order of the inputs, whatever order they finished in.

Cancelling (Ctrl-C, or any error) cancels every task not yet started and stops the local
workers, so nothing is left running: local workers ignore SIGINT (a terminal sends it to the
whole process group) and are terminated by the pool, which is the one that knows they exist;
a worker whose owner was killed outright ends by itself. Each worker leads a session of its
own, and the stop goes to the whole session: a process the worker started (``import mujoco``
with GLFW as its renderer, which the user may choose, runs a helper of GLFW's to probe its
library) ends with it rather than outlive it and write
its own traceback on the owner's stderr into a pipe nobody reads any more.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import contextlib
import importlib
import logging
import os
import re
import resource
import signal
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from multiprocessing import get_context
from multiprocessing.process import BaseProcess
from types import TracebackType
from typing import Any, TypeVar

from handctl.errors import ConfigError, HandctlError
from handctl.progress import Progress, say

T = TypeVar("T")
R = TypeVar("R")

#: s, how long a terminated local worker gets to exit before it is killed
TERMINATE_GRACE_S = 2.0
#: s, how long a cancelled local pool's manager thread gets to see its workers gone (it
#: ends the running tasks' futures as it does): a bound for a hung thread, not a pace
MANAGER_GRACE_S = 30.0
#: s, how often a local worker checks that the process that started it is still there
OWNER_POLL_S = 0.5
#: s, how long each step of opening a Dask cluster may take: the whole handshake with the
#: scheduler, a first worker to be there, and every worker to answer the version check
CONNECT_TIMEOUT_S = 10.0
#: s: how often a map with no task back looks at whether its cluster still has a worker, and
#: how long one may be without any (a worker restarting) before the work is given up
IDLE_CHECK_S = 2.0
NO_WORKER_S = 30.0
#: s: the longest one question to the scheduler is waited for, and the longest a scheduler
#: that answers none is (frozen, or its machine or the network hung with the connection
#: open): Dask's own questions wait for ever, and a plan sat at "0/24" for as long
SCHEDULER_ANSWER_S = 5.0
SCHEDULER_SILENT_S = 30.0
#: a scheduler address: scheme, host (a name, IPv4 or a bracketed IPv6) and port, all required
_SCHEDULER = re.compile(r"^(tcp|tls|ws|wss)://([A-Za-z0-9._-]+|\[[0-9A-Fa-f:.]+\]):(\d{1,5})$")
_SCHEDULER_FORM = (
    "a Dask scheduler address like tcp://HOST:8786 (tcp, tls, ws or wss; a port 1-65535)"
)
#: the schemes whose connection is TLS, set up from Dask's own configuration
_TLS_SCHEMES = ("tls", "wss")
#: the loggers a Dask client reports its lost connection on (each has a level of its own)
_DASK_CLIENT_LOGGERS = ("distributed", "distributed.client", "distributed.utils")
#: workers a message names before it says how many more
_WORKERS_NAMED = 3


class SchedulerError(ConfigError):
    """A ``--scheduler`` that cannot be used: the address, what was expected of it, and why
    it fell short, whole. The why is Dask's own text or ours, and a user needs all of it
    (``ConfigError`` shortens what it found, which would cut it mid-word)."""

    def __init__(self, address: str, expected: str, reason: str) -> None:
        super().__init__("--scheduler", "", expected, address)
        self.reason = reason
        self.args = (f"{self.args[0]}: {reason}",)


class ClusterLostError(HandctlError):
    """The Dask scheduler went away while work ran on it: every result not yet back is lost
    with it, so the work as a whole failed (a failed result, not bad input: the cluster was
    usable when the work began). ``when`` and ``then`` are the caller's to say: what was under
    way, and what came of it."""

    def __init__(self, address: str, when: str = "while the work ran", then: str = "") -> None:
        self.address = address
        super().__init__(
            f"--scheduler {address}: the Dask scheduler was lost {when} "
            f"(the connection to it closed){'; ' + then if then else ''}"
        )


class WorkerMemoryError(HandctlError):
    """A task that ran out of memory on a Dask worker: the worker's memory, on its machine,
    not this host's. A ``MemoryError`` of a task reached the command as it was, which said
    "this host ran out of memory ... raise the process's limit (ulimit -v)", sending the
    user to the wrong machine (an outside audit)."""

    def __init__(self, address: str, worker: str, found: str) -> None:
        self.address = address
        self.worker = worker
        super().__init__(
            f"the Dask cluster at {address}: a task ran out of memory on its worker {worker} "
            f"({found}): that worker's memory, not this host's. Give the cluster's workers "
            "more (dask worker --memory-limit, or fewer --nworkers on that machine), and see "
            "the worker's log"
        )


class _OnDaskWorker:
    """A task as a Dask worker runs it: what it raises says which worker it ran on, which
    Dask does not tell the client. Pickled by reference (this module is importable on every
    worker: the version check saw to it), with the task's own function inside."""

    def __init__(self, fn: Callable[[Any], Any], address: str) -> None:
        self.fn = fn
        self.address = address
        # the task's own name, which Dask keys its tasks by (its dashboard, a worker's log)
        self.__name__ = getattr(fn, "__name__", type(fn).__name__)

    def __call__(self, item: Any) -> Any:
        try:
            return self.fn(item)
        except MemoryError as exc:
            raise WorkerMemoryError(self.address, _this_worker(), _said(exc)) from None
        except HandctlError:
            raise  # the same on any worker: bad input is the input's, wherever it ran
        except Exception as exc:
            if type(exc).__name__ == "FatalError" and "allocate memory" in str(exc):
                # MuJoCo's own allocator out of memory, as the command says it of its own
                raise WorkerMemoryError(self.address, _this_worker(), _said(exc)) from None
            # the worker's traceback ends in the command's: this note with it
            exc.add_note(
                f"(raised by a task on the worker {_this_worker()} of the Dask cluster at "
                f"{self.address})"
            )
            raise


def _this_worker() -> str:
    """The address and name of the Dask worker this runs on (``_named``), from inside a task."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):  # not in a worker: no name to give
        return "(unknown)"
    return _named(str(worker.address), {"name": worker.name})


def _said(exc: BaseException) -> str:
    """An exception as one line says it: its type, and its text if it has one."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


#: the most local workers per core a pool starts (more share the cores and only cost memory)
WORKERS_PER_CORE = 4


def available_cores() -> int:
    """Cores this process may run on (its affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


class InlineExecutor(cf.Executor):
    """Runs each task when it is submitted: the one-worker case, and a debugger's friend."""

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> cf.Future[R]:
        future: cf.Future[R] = cf.Future()
        future.set_running_or_notify_cancel()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # KeyboardInterrupt and SystemExit go straight up
            future.set_exception(exc)
        return future


def start_resource_tracker() -> None:
    """multiprocessing's resource tracker started now, with the terminal's other signals
    held back in it: it shares the terminal's process group, and Ctrl-\\ (SIGQUIT) killed
    it, which printed a "process died unexpectedly" and five KeyError tracebacks at the
    end of a plan Ctrl-\\ had stopped cleanly; Ctrl-Z stopped it. (It holds back SIGINT and
    SIGTERM itself.) Blocked signals stay blocked across its exec, and are never delivered."""
    from multiprocessing import resource_tracker

    if threading.current_thread() is not threading.main_thread():
        resource_tracker.ensure_running()
        return
    held = {signal.SIGQUIT, signal.SIGTSTP, signal.SIGHUP}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _start_worker(owner: int) -> None:
    """A local worker leaves Ctrl-C to the pool's owner, who stops it; its session is its own,
    so that it is stopped with whatever it started; and it ends, with all of that, when the
    owner is gone without stopping it (killed), rather than run its task to the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.setsid()

    def watch() -> None:
        while os.getppid() == owner:
            time.sleep(OWNER_POLL_S)
        os.killpg(0, signal.SIGKILL)

    threading.Thread(target=watch, name="handctl-owner-watch", daemon=True).start()


def _stop_worker(process: BaseProcess, signum: int) -> None:
    """``signum`` to the worker's session: the worker and every process it started. A worker
    that has not reached its initializer yet has no session (and has started nothing): it
    alone gets the signal. One already gone (the pool's own thread may have reaped it as it
    died) is no error, as it is none for ``Process.terminate``."""
    pid = process.pid
    if pid is None:  # never started
        return
    try:
        os.killpg(pid, signum)
    except ProcessLookupError:
        with contextlib.suppress(ProcessLookupError):
            if process.is_alive():
                os.kill(pid, signum)


class WorkPool:
    """One executor for offline work, with an ordered, cancellable ``map``."""

    def __init__(
        self,
        executor: cf.Executor,
        workers: int,
        where: str,
        close: Callable[[bool], None],
        lost: Callable[[], ClusterLostError | None] = lambda: None,
        cpu_counted: str = "this process and its local workers",
        idle: Callable[[], HandctlError | str | None] = lambda: None,
        task: Callable[[Callable[[Any], Any]], Callable[[Any], Any]] = lambda fn: fn,
    ) -> None:
        self.executor = executor
        self.workers = workers
        self.where = where
        self.cpu_counted = cpu_counted  # whose CPU a ``Stopwatch`` around this pool counts
        self._close = close
        self._lost = lost
        #: asked while no task comes back: why the work cannot go on, if it cannot (a
        #: cluster whose workers are all gone, its scheduler still up, waited for ever), or
        #: a line to say once of why it waits (a cluster whose workers are all paused)
        self._idle = idle
        #: what a task's function is sent to the workers as (a Dask worker's names itself
        #: in what the task raises)
        self._task = task
        self._closed = False
        self.tasks_run = 0  # tasks whose results came back (what a rate is counted in)

    def map(
        self, fn: Callable[[T], R], items: Sequence[T], progress: Progress | None = None
    ) -> list[R]:
        """``[fn(x) for x in items]``, run by the pool; results in the order of ``items``.

        The first task to fail fails the whole map (the rest are cancelled), and its
        exception is raised here; ``progress`` advances as tasks finish, in any order. A
        cluster lost meanwhile cancels every task: that is a ``ClusterLostError`` naming it,
        not the first cancelled future's bare ``CancelledError``."""
        if isinstance(self.executor, InlineExecutor):  # one by one, so progress moves
            results = []
            for item in items:
                results.append(fn(item))
                self.tasks_run += 1
                if progress is not None:
                    progress.advance()
            return results
        run = self._task(fn)
        futures: list[cf.Future[R]] = []
        try:
            # inside: a cluster's client that gave up on its scheduler before this map (lost
            # between two) refuses the first submission, which is the cluster lost too
            futures.extend(self.executor.submit(run, item) for item in items)
            pending = set(futures)
            while pending:
                # in rounds of IDLE_CHECK_S, each O(tasks left), between which the pool is
                # asked whether the work can still go on
                try:
                    for future in cf.as_completed(pending, timeout=IDLE_CHECK_S):
                        pending.discard(future)
                        future.result()  # raises the task's exception at once
                        if progress is not None:
                            progress.advance()
                except TimeoutError:
                    self._waited(progress)
            self.tasks_run += len(futures)
            return [f.result() for f in futures]
        except BaseException as exc:
            for f in futures:
                f.cancel()
            if isinstance(exc, Exception) and (lost := self._lost()) is not None:
                raise lost from None
            if isinstance(exc, cf.process.BrokenProcessPool):
                # one line, as a lost cluster is said: the pool's own traceback said nothing
                # a user can act on
                raise HandctlError(
                    f"a local worker process {_how_a_worker_ended(self.executor)}: the work "
                    "cannot go on"
                ) from None
            if type(exc).__name__ == "KilledWorker":  # distributed's, not imported here
                # the cluster's own word for a task whose workers died under it again and
                # again (out of memory, a crash): said as "an internal error, a bug in
                # handctl" with a traceback (an outside audit)
                raise HandctlError(
                    f"{self.where}: workers died under a task again and again, and Dask gave "
                    f"it up ({exc}); the workers' own logs say why (out of memory, a crash)"
                ) from None
            raise

    def _waited(self, progress: Progress | None) -> None:
        """A round of the map with no task back: the pool asked whether the work can go on
        (raised if not), what it says of why it waits said, and the progress shown."""
        why = self._idle()
        if isinstance(why, HandctlError):
            raise why from None
        if why is not None:
            # said once, where "none done for 4:30" alone never said why
            (progress.note if progress is not None else say)(why)
        if progress is not None:
            progress.tick()

    def close(self, cancel: bool = False) -> None:
        """Release the workers; with ``cancel``, stop what is still running first."""
        if not self._closed:
            self._closed = True
            self._close(cancel)

    def __enter__(self) -> WorkPool:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        _exc: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.close(cancel=kind is not None)


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    ended = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + ended.ru_utime + ended.ru_stime


class Stopwatch:
    """Wall and CPU time since it was made, for a report of what offline work cost. The CPU
    is this process's and that of its children which have ended: a local pool's workers once
    the pool is closed, not a cluster's workers (they run elsewhere)."""

    def __init__(self) -> None:
        self._wall = time.monotonic()
        self._cpu = _cpu_s()

    def read(self) -> tuple[float, float]:
        """(wall s, CPU s) since the stopwatch was made."""
        return time.monotonic() - self._wall, _cpu_s() - self._cpu


def check_scheduler(address: str) -> str:
    """The scheduler's address as Dask takes it, or a ``ConfigError`` naming the option.

    Everything the address alone shows is checked here, before anything is imported or
    connected: Dask's own parsing would only fail once connecting (a missing port, an
    ``inproc://`` address, which is only meaningful inside the one process that holds that
    cluster), after its retries, with a traceback."""
    match = _SCHEDULER.match(address)
    if not match or not 1 <= int(match.group(3)) <= 65535:
        raise ConfigError("--scheduler", "", _SCHEDULER_FORM, address)
    return address


def check_pool_options(
    workers: int | None, scheduler: str | None, *, offers_scheduler: bool = True
) -> None:
    """``--workers`` and ``--scheduler`` as ``open_pool`` takes them, or a ``ConfigError``
    naming the option, before anything is started or connected: one rule for every command
    and tool that offers them. ``offers_scheduler``: whether the caller has a
    ``--scheduler`` to point a user at (``bench.py plan`` has none)."""
    if workers is not None and workers < 1:
        raise ConfigError("--workers", "", "at least 1 worker", workers)
    if scheduler is not None:
        check_scheduler(scheduler)
        if workers is not None:
            # here, not in each caller: the bench's experiment took --workers 999 beside
            # --scheduler without a word where the plan refused it (an outside audit)
            raise ConfigError(
                "--workers",
                "",
                "no --workers with --scheduler (the cluster's workers are started on their "
                "machines)",
                workers,
            )
        return
    cores = available_cores()
    if workers is not None and workers > WORKERS_PER_CORE * cores:
        # each worker is a process with its own simulated hand; thousands of them ran the
        # machine out of memory (or of processes) before the first task ended
        cluster = "; a cluster takes --scheduler" if offers_scheduler else ""
        raise ConfigError(
            "--workers",
            "",
            f"at most {WORKERS_PER_CORE * cores} workers ({WORKERS_PER_CORE} per core this "
            f"process may run on, {cores}: more only share the same cores, each with its own "
            f"simulated hand's memory{cluster})",
            workers,
        )


def open_pool(
    workers: int | None = None, scheduler: str | None = None, *, offers_scheduler: bool = True
) -> WorkPool:
    """A pool of ``workers`` local processes (default: every core), or the Dask cluster whose
    scheduler is at ``scheduler`` (then ``workers`` is the cluster's business, and refused).
    ``offers_scheduler`` as ``check_pool_options`` takes it."""
    check_pool_options(workers, scheduler, offers_scheduler=offers_scheduler)
    if scheduler is not None:
        return _dask_pool(scheduler)
    cores = available_cores()
    count = workers if workers is not None else cores
    if count == 1:
        return WorkPool(InlineExecutor(), 1, "this process", lambda _cancel: None)
    # spawn, not fork: a worker starts from the installed package alone, as a cluster's does,
    # and inherits no thread, lock or open file of the caller
    start_resource_tracker()
    pool = cf.ProcessPoolExecutor(
        max_workers=count,
        mp_context=get_context("spawn"),
        initializer=_start_worker,
        initargs=(os.getpid(),),
    )

    def close(cancel: bool) -> None:
        if not cancel:
            pool.shutdown(wait=True)
            return
        processes = list(getattr(pool, "_processes", {}).values())
        # taken before the shutdown, which lets go of it (it was None when looked for after)
        manager = getattr(pool, "_executor_manager_thread", None)
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            _stop_worker(process, signal.SIGTERM)
        for process in processes:
            process.join(TERMINATE_GRACE_S)
            if process.is_alive():
                _stop_worker(process, signal.SIGKILL)
                process.join()
        # The pool's manager thread closes its wake-up pipe once it sees the workers gone; at
        # exit, concurrent.futures wakes every such thread through that pipe, and one still
        # closing it races the wake-up (EBADF: "Exception ignored ... Bad file descriptor"
        # printed after a Ctrl-C'd plan on a loaded machine). Waited for here, it is closed.
        # Waiting for it also ends the futures of the tasks that were running (failed, their
        # workers gone): a close looked for it after the shutdown, found nothing to wait for,
        # and returned with futures still pending.
        if manager is not None:
            manager.join(MANAGER_GRACE_S)

    return WorkPool(pool, count, f"{count} local processes", close)


#: What ended a local worker, by the signal that did, in the words of the line that says so.
_ENDED_BY = {
    signal.SIGKILL: "was killed (SIGKILL: the kernel's out-of-memory killer, a hard CPU time "
    "limit, or kill -9)",
    signal.SIGXCPU: "ran out of the CPU time its limit allows (SIGXCPU; ulimit -t)",
    signal.SIGSEGV: "crashed (SIGSEGV)",
    signal.SIGBUS: "crashed (SIGBUS)",
    signal.SIGABRT: "crashed (SIGABRT)",
}


def _how_a_worker_ended(executor: object) -> str:
    """What ended the local worker whose loss broke the pool, from its processes' exit
    statuses: once one is gone the pool ends the others with SIGTERM, so any other status is
    the cause (a CPU time limit, the OOM killer, a crash). A user's own SIGTERM, or a status
    not yet known, is said as before."""
    processes: list[BaseProcess] = list((getattr(executor, "_processes", None) or {}).values())
    deadline = time.monotonic() + TERMINATE_GRACE_S  # one grace for all, not one each
    # Until every status is known, not one join each: the pool's manager thread joins the
    # same processes, and a join that loses the race to reap one returns at once with its
    # status not yet set (the other thread sets it a moment later), which said "ended
    # abruptly" of a worker killed by SIGKILL, now and then on a loaded machine.
    while any(p.exitcode is None for p in processes) and time.monotonic() < deadline:
        for process in processes:
            process.join(max(0.0, min(0.05, deadline - time.monotonic())))
        time.sleep(0.005)
    for process in processes:
        code = process.exitcode
        if code is None or code in (0, -signal.SIGTERM):
            continue
        if code > 0:
            return f"exited with status {code}"
        try:
            sig = signal.Signals(-code)
        except ValueError:
            return f"was ended by signal {-code}"
        return _ENDED_BY.get(sig, f"was ended by {sig.name}")
    return "ended abruptly (killed, or out of memory)"


def _dask_pool(address: str) -> WorkPool:
    """The cluster at ``address``, checked before any work goes to it: a scheduler that
    answers Dask's handshake, at least one worker, and handctl, at this version, importable on
    every worker (a worker without it cannot even read a task: Dask only logs that on the
    worker, and the work waits for ever)."""
    try:
        distributed: Any = importlib.import_module("distributed")
    except ImportError:
        raise ConfigError(
            "--scheduler",
            "",
            "Dask distributed installed (pip install 'handctl[cluster]')",
            address,
        ) from None
    security = _security(distributed, address)
    _greet(distributed, address, security)
    try:
        client = distributed.Client(
            address, timeout=CONNECT_TIMEOUT_S, set_as_default=False, security=security
        )
    except (OSError, TimeoutError) as exc:  # it answered a moment ago: gone since
        raise SchedulerError(address, "a reachable Dask scheduler", str(exc)) from None
    try:
        _check_workers(client, address)
    except BaseException:
        client.close()
        raise
    # pure=False: every submission runs (a pure task of equal inputs would be shared, which is
    # correct but makes a repeated candidate cost nothing and the counts lie)
    executor = client.get_executor(pure=False)
    try:
        workers = _workers_now(client)
    except TimeoutError:  # it answered the version check a moment ago
        client.close()
        raise SchedulerError(
            address, "a Dask scheduler that answers", f"none in {SCHEDULER_ANSWER_S:g} s"
        ) from None

    # A connection that breaks is logged by the client's background sender with a traceback
    # as it breaks, which can be before ``lost`` is first asked (a scheduler killed under a
    # loaded plan): the error raised there says it in one line, so that logger, which logs
    # nothing else, is held from the start
    batched = logging.getLogger("distributed.batched")
    quiet: list[tuple[logging.Logger, int]] = [(batched, batched.level)]
    batched.setLevel(logging.CRITICAL + 1)

    # The client's giving up on a scheduler lost between two maps is logged as it gives up,
    # before any map asks: the next map's ``ClusterLostError`` says it in one line
    gave_up = _GaveUp()
    client_logger = logging.getLogger("distributed.client")
    client_logger.addFilter(gave_up)

    def close(cancel: bool) -> None:
        try:
            # a client that gave up on its scheduler cancels nothing more there (the
            # scheduler took its tasks with it), and said so with a second traceback
            with contextlib.suppress(distributed.client.ClosedClientError):
                executor.shutdown(wait=not cancel)
            client.close()
        finally:
            client_logger.removeFilter(gave_up)
            for logger, level in quiet:
                logger.setLevel(level)

    def lost() -> ClusterLostError | None:
        # the client cancels every future the moment its connection closes, then tries to
        # reconnect ("connecting") and gives up ("closed")
        if client.status == "running":
            return None
        # its giving up, or being closed while it tries, is logged with a traceback: the
        # error raised here says it all, in one line, so the log is held until it is closed
        if len(quiet) == 1:
            for name in _DASK_CLIENT_LOGGERS:
                logger = logging.getLogger(name)
                quiet.append((logger, logger.level))
                logger.setLevel(logging.CRITICAL + 1)
        return ClusterLostError(address)

    return WorkPool(
        executor,
        workers,
        f"the Dask cluster at {address} ({workers} worker{'' if workers == 1 else 's'})",
        close,
        lost,
        cpu_counted="this process only, not the cluster's workers",
        idle=_Idle(client, address),
        task=lambda fn: _OnDaskWorker(fn, address),
    )


class _GaveUp(logging.Filter):
    """Holds back Dask's client's "Failed to reconnect to scheduler ..., closing client":
    the map that finds its cluster gone says so (``ClusterLostError``), and a scheduler lost
    after the last map cost nothing."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Failed to reconnect to scheduler")


class _Idle:
    """Asked while a map on a cluster has no task back: why the work cannot go on, if it
    cannot. A cluster without a worker for ``NO_WORKER_S`` (its tasks would wait for one for
    ever), one whose workers are all there but none running (paused: Dask pauses a worker
    whose memory passes its pause threshold) for as long, or a scheduler that answers
    nothing for ``SCHEDULER_SILENT_S``. A cluster whose workers have just all stopped
    running is said once, and once again when one runs again."""

    def __init__(self, client: Any, address: str) -> None:
        self.client = client
        self.address = address
        self.without: float | None = None  # when the cluster was first seen without a worker
        self.halted: float | None = None  # when its workers were first seen none running
        self.silent: float | None = None  # when the scheduler first did not answer

    def __call__(self) -> HandctlError | str | None:
        address = self.address
        try:
            statuses = _worker_statuses(self.client)
        except TimeoutError:
            self.silent = time.monotonic() if self.silent is None else self.silent
            if time.monotonic() - self.silent < SCHEDULER_SILENT_S:
                return None
            return HandctlError(
                f"--scheduler {address}: the Dask scheduler has not answered for "
                f"{SCHEDULER_SILENT_S:g} s (frozen, or its machine or the network hung): the "
                "work is given up; nothing was written"
            )
        except Exception:  # the scheduler gone: ``lost`` says so
            return None
        self.silent = None
        if statuses:
            self.without = None
            return self._halted(statuses)
        self.halted = None
        if self.without is None:
            self.without = time.monotonic()
        if time.monotonic() - self.without < NO_WORKER_S:
            return None
        return HandctlError(
            f"--scheduler {address}: the Dask cluster has had no worker for {NO_WORKER_S:g} s "
            "(they ended, or lost the scheduler): its tasks would wait for one for ever, and "
            "the work is given up"
        )

    def _halted(self, statuses: list[str]) -> HandctlError | str | None:
        """A cluster with workers none of which runs: a paused worker counted as a worker,
        and a plan on a cluster whose one worker was paused (its memory above Dask's pause
        threshold) said "none done for 4:30" for ever, never why (an outside audit)."""
        if "running" in statuses:
            was, self.halted = self.halted, None
            return f"the Dask cluster at {self.address}: a worker runs again" if was else None
        how = _none_running(statuses)
        if self.halted is None:
            self.halted = time.monotonic()
            return f"the Dask cluster at {self.address}: {how}: no task runs until one runs again"
        if time.monotonic() - self.halted < NO_WORKER_S:
            return None
        return HandctlError(
            f"--scheduler {self.address}: the Dask cluster has had no running worker for "
            f"{NO_WORKER_S:g} s, {how}: its tasks would wait for one for ever, and the work is "
            "given up"
        )


def _none_running(statuses: list[str]) -> str:
    """What the workers of these statuses, none of them running, are doing, said whole."""
    counts = Counter(statuses)
    if len(counts) > 1:
        which = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
        how = f"none of its {len(statuses)} workers is running ({which})"
    elif len(statuses) == 1:
        how = f"its one worker is {statuses[0]}"
    else:
        how = f"its {len(statuses)} workers are all {statuses[0]}"
    if "paused" in counts:
        how += (
            " (Dask pauses a worker whose memory passes its pause threshold, "
            "distributed.worker.memory.pause)"
        )
    return how


def _worker_statuses(client: Any) -> list[str]:
    """The status of each worker the scheduler knows of now (``running``, ``paused``, ...),
    asked with a timeout (``TimeoutError`` past ``SCHEDULER_ANSWER_S``):
    ``Client.scheduler_info`` waits for its answer for ever."""
    info = client.sync(client.scheduler.identity, n_workers=-1, callback_timeout=SCHEDULER_ANSWER_S)
    return [str(worker.get("status", "running")) for worker in info.get("workers", {}).values()]


def _workers_now(client: Any) -> int:
    """How many workers the scheduler knows of now (``_worker_statuses``)."""
    return len(_worker_statuses(client))


def _security(distributed: Any, address: str) -> Any:
    """Dask's TLS settings for a ``tls://`` or ``wss://`` address, from Dask's own
    configuration (``distributed.comm.tls.*``, or ``DASK_DISTRIBUTED__COMM__TLS__...``), the
    one the scheduler and workers are started with: handctl adds no options of its own for
    them. Without a CA and a client certificate, Dask would fail only once connecting."""
    security = distributed.Security()  # reads the configuration
    if address.split("://", 1)[0] not in _TLS_SCHEMES:
        return security
    tls_vars = (
        "DASK_DISTRIBUTED__COMM__TLS__CA_FILE, DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT "
        "and DASK_DISTRIBUTED__COMM__TLS__CLIENT__KEY (docs/scale.md)"
    )
    try:
        context = security.get_connection_args("client")["ssl_context"]
    except (OSError, ValueError) as exc:  # a file named there missing, or not a cert or key
        # ssl's errors do not say which file: the settings are named with the reason
        files = ", ".join(
            f"{what} {getattr(security, attr) or '(not set)'}" for what, attr, _ in _TLS_SETTINGS
        )
        raise SchedulerError(
            address,
            f"Dask's TLS settings usable: {tls_vars}",
            f"{type(exc).__name__}: {exc} (of {files})",
        ) from None
    if context is None:
        # Dask makes no context unless both the CA file and the client certificate are set
        # (the key may be in the certificate's file): which is missing, by both its names,
        # where "no CA file and client certificate" left the user to guess
        unset = [
            f"the {what} ({setting}, {_dask_env(setting)})"
            for what, attr, setting in _TLS_SETTINGS[:2]
            if not getattr(security, attr)
        ]
        raise SchedulerError(
            address,
            f"Dask's TLS settings for a TLS address: {tls_vars}",
            f"{' and '.join(unset)} {'is' if len(unset) == 1 else 'are'} not set in Dask's "
            "configuration",
        )
    return security


#: Dask's TLS settings for a client: what a message calls each, its attribute of
#: ``distributed.Security`` and its key in Dask's configuration
_TLS_SETTINGS = (
    ("CA file", "tls_ca_file", "distributed.comm.tls.ca-file"),
    ("client cert", "tls_client_cert", "distributed.comm.tls.client.cert"),
    ("client key", "tls_client_key", "distributed.comm.tls.client.key"),
)


def _dask_env(setting: str) -> str:
    """The environment variable that sets a key of Dask's configuration."""
    return "DASK_" + setting.upper().replace(".", "__").replace("-", "_")


def _greet(distributed: Any, address: str, security: Any) -> None:
    """Dask's whole handshake with the scheduler, and its answer to who it is, within
    ``CONNECT_TIMEOUT_S``. Dask's own client bounds only its connection: a port that accepts
    and never answers (a bare listening socket), or answers in another protocol (the
    dashboard's HTTP on 8787, next to the scheduler's 8786), keeps it waiting for ever."""

    async def identify() -> Any:
        comm = await distributed.comm.connect(
            address, timeout=CONNECT_TIMEOUT_S, **security.get_connection_args("client")
        )
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    expected = f"a Dask scheduler that answers within {CONNECT_TIMEOUT_S:g} s"
    host, port = _host_and_port(address)
    try:
        # Dask retries a name that does not resolve or a port nobody listens on until its
        # timeout; both are known in milliseconds
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        # UnicodeError: a name with an empty label (10.0.0..5) fails IDNA encoding before
        # any lookup, and was said as an internal error with a traceback (an outside audit)
        raise SchedulerError(address, expected, f"{host} does not resolve ({exc})") from None
    try:
        with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
            pass
    except ConnectionRefusedError as exc:
        raise SchedulerError(address, expected, f"nothing listens there ({exc})") from None
    except OSError:
        pass  # unreachable for now, or slow: Dask's own connect says, within its bound
    try:
        answer = asyncio.run(asyncio.wait_for(identify(), CONNECT_TIMEOUT_S))
    except TimeoutError:
        raise SchedulerError(
            address, expected, f"no answer to Dask's handshake in {CONNECT_TIMEOUT_S:g} s"
        ) from None
    except OSError as exc:  # the connection itself
        raise SchedulerError(address, expected, str(exc) or type(exc).__name__) from None
    except Exception as exc:  # whatever a peer speaking another protocol makes Dask raise
        # (an allocation of exabytes, a buffer too short: its answer read as Dask's frames)
        reason = f"its answer is not Dask's ({type(exc).__name__}: {exc})"
        raise SchedulerError(address, expected, reason) from None
    if not isinstance(answer, dict) or answer.get("type") != "Scheduler":
        kind = answer.get("type") if isinstance(answer, dict) else type(answer).__name__
        raise SchedulerError(address, expected, f"it is a Dask {kind}, not a scheduler")


def _host_and_port(address: str) -> tuple[str, int]:
    """The host (brackets off an IPv6 one) and port of an address ``check_scheduler`` took."""
    match = _SCHEDULER.match(address)
    assert match is not None, address  # checked before any connection is tried
    return match.group(2).strip("[]"), int(match.group(3))


#: MuJoCo (first, to be named if it is what fails) and the modules of a plan's and the
#: experiment bench's tasks: what a worker imports to read one, checked before any goes out.
#: Not the fault campaign's or the LP grid's: scipy and the recorder they import cost each
#: worker some 50 MB more, which a worker with a memory limit may not have to spare
TASK_MODULES = ("mujoco", "handctl.planning.phase_task", "handctl.harness.seed_run")


def _handctl_version() -> Callable[[], str]:
    """A function that imports handctl and what a task imports, and gives handctl's version,
    the digest of its code and MuJoCo's version, made here so that it is pickled by value (it
    is no module's attribute): by reference, a worker without handctl could not even unpickle
    it, and would report that as a Dask error, not this one."""
    modules = TASK_MODULES

    def version() -> str:
        import hashlib
        import importlib
        from pathlib import Path

        import handctl

        # MuJoCo's OpenGL off in the worker's process, as ``main`` turns it off in handctl's
        # own, before anything imports MuJoCo: a worker never runs ``main``, and one started
        # with ``MUJOCO_GL=osmesa`` on a machine without OSMesa died of its first task (its
        # ``import mujoco`` raised while the task was unpickled), which the plan could only
        # report 30 s later as a cluster without workers (an outside audit). Here, on the
        # workers this check reaches, and not at ``import handctl``: that turned it off for
        # every program that imports handctl, whose own MuJoCo rendering then failed
        handctl.mujoco_opengl_off()

        root = Path(handctl.__file__).parent
        digest = hashlib.sha256()
        for path in sorted(root.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(path.relative_to(root).as_posix().encode() + b"\0")
                digest.update(path.read_bytes())
        ours = f"handctl {handctl.__version__} (code {digest.hexdigest()[:12]})"
        # imported, not read from the package's metadata: a MuJoCo installed whose import
        # fails passed, and the worker died of its first task (an outside audit)
        for name in modules:
            try:
                importlib.import_module(name)
            except Exception as exc:
                return f"{ours}, but {name} does not import ({type(exc).__name__}: {exc})"
        return f"{ours}, mujoco {importlib.import_module('mujoco').__version__}"

    return version


def _named(worker: str, info: dict[str, Any]) -> str:
    """A worker's address, and its name where it has one of its own (``dask worker --name``,
    a ``LocalCluster``'s number): what its log and its machine's process list show."""
    name = str(info.get("name", worker))
    return worker if name == worker else f"{worker} (name {name})"


def _some(said: list[str]) -> str:
    """The first ``_WORKERS_NAMED`` of ``said``, and how many more."""
    more = len(said) - _WORKERS_NAMED
    return "; ".join(said[:_WORKERS_NAMED]) + (f"; and {more} more" if more > 0 else "")


def _ask_each_worker(client: Any, address: str) -> dict[str, Any]:
    """Each worker's answer to the version check (its exception, if it raised), every worker
    asked on its own, all at once, within ``CONNECT_TIMEOUT_S``. One question to them all
    timed out as a whole: one frozen worker (SIGSTOP, its machine hung) hid the answers the
    others gave, and the plan was refused "no answer from its workers", never which (an
    outside audit). A worker that does not answer is named, with how many did."""
    try:
        info = client.sync(
            client.scheduler.identity, n_workers=-1, callback_timeout=CONNECT_TIMEOUT_S
        )
    except TimeoutError:
        raise SchedulerError(
            address, "a Dask scheduler that answers", f"none in {CONNECT_TIMEOUT_S:g} s"
        ) from None
    workers: dict[str, dict[str, Any]] = dict(info.get("workers", {}))
    version = _handctl_version()

    async def ask(worker: str) -> Any:
        try:
            # asynchronous: the question itself, to await here in the client's own loop
            question = client.run(version, workers=[worker], on_error="return", asynchronous=True)
            answer = await asyncio.wait_for(question, CONNECT_TIMEOUT_S)
        except TimeoutError:
            return None
        except Exception as exc:  # the scheduler's own question to it failed (gone since)
            return exc
        return answer.get(worker, KeyError(f"{worker} is no longer in the cluster"))

    async def ask_all() -> list[Any]:
        return list(await asyncio.gather(*(ask(worker) for worker in workers)))

    answers = dict(zip(workers, client.sync(ask_all), strict=True))
    silent = [_named(w, workers[w]) for w, answer in sorted(answers.items()) if answer is None]
    if silent:
        raise SchedulerError(
            address,
            "a Dask cluster whose workers answer",
            f"{len(workers) - len(silent)} of {len(workers)} workers answered the version check "
            f"in {CONNECT_TIMEOUT_S:g} s; no answer from {_some(silent)} (frozen, or its "
            "machine or the network hung)",
        )
    return answers


def _check_workers(client: Any, address: str) -> None:
    """At least one worker, and this handctl on every one, before any task goes out."""

    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except TimeoutError:
        # Dask waits for a running worker: one there but paused was said as none
        try:
            statuses = _worker_statuses(client)
        except TimeoutError:
            statuses = []
        raise SchedulerError(
            address,
            "a Dask cluster with at least one worker",
            f"none running in {CONNECT_TIMEOUT_S:g} s: {_none_running(statuses)}"
            if statuses
            else f"none in {CONNECT_TIMEOUT_S:g} s",
        ) from None
    answers = _ask_each_worker(client, address)
    # the version alone let a worker on another checkout of the same version plan with
    # other code, which changed the recipe without a word: its code's digest, and MuJoCo's
    ours = _handctl_version()()
    wrong = []
    for worker, answer in sorted(answers.items()):
        if isinstance(answer, BaseException):
            wrong.append(f"{worker}: {type(answer).__name__}: {answer}")
        elif answer != ours:
            wrong.append(f"{worker}: {answer}")
    if wrong:
        raise SchedulerError(
            address,
            f"{ours}, importable, on every worker of the cluster",
            f"{len(wrong)} of {len(answers)} workers have not: {_some(wrong)}",
        )
