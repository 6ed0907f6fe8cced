"""The one executor of offline work: results in input order whatever order tasks finish in, a
failing task fails the map, cancelling stops the local workers, bad options are named."""

from __future__ import annotations

import contextlib
import http.server
import io
import logging
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from multiprocessing import resource_tracker
from pathlib import Path
from typing import Any

import psutil
import pytest

import handctl
from handctl import executor
from handctl.errors import ConfigError, HandctlError
from handctl.executor import (
    ClusterLostError,
    Stopwatch,
    WorkPool,
    available_cores,
    check_scheduler,
    open_pool,
)
from handctl.progress import Progress

from ..conftest import ROOT

#: a process that opens a pool of two, keeps both workers busy, says their ids and waits
OWNER = """
import os, sys, time
from handctl.executor import open_pool
from tests.unit.test_executor import sleep_long
pool = open_pool(2)
futures = [pool.executor.submit(sleep_long, i) for i in range(2)]
import psutil
me = psutil.Process()
while len([c for c in me.children() if 'spawn_main' in ' '.join(c.cmdline())]) < 2:
    time.sleep(0.1)
print(' '.join(str(c.pid) for c in me.children()), flush=True)
time.sleep(600)
"""


def later_first(item: tuple[int, int]) -> tuple[int, int]:
    """Task ``i`` of ``n`` waits longer the earlier it is: they finish in reverse order."""
    i, n = item
    time.sleep(0.05 * (n - i))
    return i, os.getpid()


def fail_on_three(i: int) -> int:
    if i == 3:
        raise ValueError("task 3 cannot")
    return i


def sleep_long(_: int) -> int:
    time.sleep(120.0)
    return 0


def start_a_helper_and_sleep(pid_file: str) -> int:
    """A task that starts a process of its own, as ``import mujoco`` does (GLFW's probe), says
    its pid and goes on working."""
    helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    with open(pid_file + ".part", "w") as out:
        out.write(str(helper.pid))
    os.replace(pid_file + ".part", pid_file)
    time.sleep(120.0)
    return helper.pid


def spin(seconds: float) -> float:
    """Burn ``seconds`` of CPU in the worker."""
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass
    return seconds


def test_the_stopwatch_counts_a_closed_local_pool_s_workers() -> None:
    """``handctl plan`` reports its CPU time with this: what the workers burnt is in it once
    the pool is closed, though this process itself only waited."""
    clock = Stopwatch()
    own = time.process_time()
    with open_pool(2) as pool:
        pool.map(spin, [0.4, 0.4])
    _, cpu = clock.read()
    assert cpu >= 0.8
    assert time.process_time() - own < 0.8  # it is not this process's own


@pytest.mark.parametrize("workers", [1, 2])
def test_results_come_in_input_order(workers: int) -> None:
    import io

    out = io.StringIO()
    with open_pool(workers) as pool:
        bar = Progress("t", 6, stream=out, terminal=False)
        results = pool.map(later_first, [(i, 6) for i in range(6)], bar)
        bar.close()
    assert [i for i, _ in results] == list(range(6))
    assert out.getvalue().splitlines()[-1].startswith("t: 6/6 in ")
    pids = {pid for _, pid in results}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids)


def nap(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def test_a_map_waiting_on_a_slow_task_still_shows_its_progress(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The progress was shown only when a task ended: piped, a plan stalled on a paused
    worker wrote nothing for forty seconds. The map's idle checks show it too (here every
    0.2 s, a line due every 0.5 s)."""
    import io

    from handctl import executor, progress

    monkeypatch.setattr(executor, "IDLE_CHECK_S", 0.2)
    monkeypatch.setattr(progress, "PLAIN_EVERY_S", 0.5)
    out = io.StringIO()
    with open_pool(2) as pool:
        bar = Progress("t", 2, stream=out, terminal=False)
        assert pool.map(nap, [0.0, 2.5], bar) == [0.0, 2.5]
        bar.close()
    lines = out.getvalue().splitlines()
    assert any(line.startswith("t: 1/2 (50 %), ") and "none done for" in line for line in lines)
    assert lines[-1].startswith("t: 2/2 in ")


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_task_fails_the_map(workers: int) -> None:
    with open_pool(workers) as pool, pytest.raises(ValueError, match="task 3 cannot"):
        pool.map(fail_on_three, list(range(8)))


def test_cancelling_stops_the_local_workers() -> None:
    # multiprocessing's resource tracker is this interpreter's, not the pool's: started at
    # the first spawn and left running until the interpreter ends. Counted as a worker, it
    # failed this test whenever the test was the first in its process to spawn one.
    resource_tracker.ensure_running()
    me = psutil.Process()
    before = {p.pid for p in me.children(recursive=True)}
    pool = open_pool(2)
    futures = [pool.executor.submit(sleep_long, i) for i in range(4)]
    workers = [p for p in me.children(recursive=True) if p.pid not in before]
    assert len(workers) >= 2
    pool.close(cancel=True)
    _, alive = psutil.wait_procs(workers, timeout=10.0)
    assert alive == []
    assert all(f.cancelled() or f.done() for f in futures)


def test_cancelling_stops_what_the_workers_started(tmp_path: Path) -> None:
    """A process a task started must not outlive its worker: orphaned, it would go on writing
    to the owner's stderr (a traceback of its own) after the owner said it was interrupted."""
    pid_files = [tmp_path / f"helper{i}" for i in range(2)]
    pool = open_pool(2)
    try:
        for path in pid_files:
            pool.executor.submit(start_a_helper_and_sleep, str(path))
        deadline = time.monotonic() + 120.0
        while not all(p.exists() for p in pid_files) and time.monotonic() < deadline:
            time.sleep(0.05)
        helpers = [psutil.Process(int(p.read_text())) for p in pid_files]
    finally:
        pool.close(cancel=True)
    _, alive = psutil.wait_procs(helpers, timeout=10.0)
    assert alive == [], [p.pid for p in alive]


def test_default_is_every_core_this_process_may_use() -> None:
    with open_pool() as pool:
        assert pool.workers == available_cores() == len(os.sched_getaffinity(0))


def test_bad_options_are_named() -> None:
    with pytest.raises(ConfigError, match=r"--workers: expected at least 1 worker, found 0"):
        open_pool(0)
    most = executor.WORKERS_PER_CORE * available_cores()
    with pytest.raises(
        ConfigError, match=rf"--workers: expected at most {most} workers .* found {most + 1}"
    ):
        open_pool(most + 1)
    with pytest.raises(ConfigError, match=r"memory\)") as raised:  # a caller without one
        open_pool(most + 1, offers_scheduler=False)
    assert "--scheduler" not in str(raised.value)
    with pytest.raises(
        ConfigError,
        match=r"--scheduler: expected a Dask scheduler address like tcp://HOST:8786 "
        r"\(tcp, tls, ws or wss; a port 1-65535\), found 'localhost:8786'",
    ):
        check_scheduler("localhost:8786")
    assert check_scheduler("tcp://10.0.0.5:8786") == "tcp://10.0.0.5:8786"


def test_workers_with_a_scheduler_are_refused_for_every_caller() -> None:
    """The plan refused --workers beside --scheduler, but the bench's experiment and the
    fault campaign took it (--workers 999 too) and ignored it: the rule is the pool's, before
    anything is connected (nothing listens at this address)."""
    with pytest.raises(
        ConfigError, match=r"^--workers: expected no --workers with --scheduler .*, found 2$"
    ):
        open_pool(2, "tcp://127.0.0.1:1")


def test_an_unreachable_scheduler_is_named() -> None:
    """Nothing listens on the port: known at once and said whole after the address (cut to a
    length, Dask's reason was cut mid-word; and it came only after its retries)."""
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]  # free again once closed, and nothing listens there
    with pytest.raises(ConfigError) as raised:
        open_pool(scheduler=f"tcp://127.0.0.1:{port}")
    found = f"found 'tcp://127.0.0.1:{port}': "
    assert str(raised.value).startswith(
        "--scheduler: expected a Dask scheduler that answers within 10 s, " + found
    )
    assert str(raised.value).split(found)[1].startswith("nothing listens there (")


def test_a_scheduler_host_that_does_not_resolve_is_named_at_once() -> None:
    """Dask retried the name until its timeout and then said it timed out connecting."""
    pytest.importorskip("distributed")
    with pytest.raises(ConfigError) as raised:
        open_pool(scheduler="tcp://no-such-host.invalid:8786")  # .invalid never resolves
    assert "found 'tcp://no-such-host.invalid:8786': no-such-host.invalid does not resolve (" in (
        str(raised.value)
    )
    # a name with an empty label fails its IDNA encoding before any lookup: an internal
    # error with a traceback (an outside audit)
    with pytest.raises(ConfigError) as raised:
        open_pool(scheduler="tcp://10.0.0..5:8786")
    assert "found 'tcp://10.0.0..5:8786': 10.0.0..5 does not resolve (" in str(raised.value)


def test_workers_end_when_their_owner_is_killed() -> None:
    with subprocess.Popen(
        [sys.executable, "-c", OWNER], cwd=ROOT, stdout=subprocess.PIPE, text=True
    ) as owner:
        try:
            assert owner.stdout is not None
            pids = [int(x) for x in owner.stdout.readline().split()]
            workers = [psutil.Process(pid) for pid in pids]
            assert len(workers) >= 2
            owner.send_signal(signal.SIGKILL)
            owner.wait(timeout=30)
            _, alive = psutil.wait_procs(workers, timeout=20.0)
            assert alive == []
        finally:
            if owner.poll() is None:
                owner.kill()


def test_one_worker_advances_the_progress_task_by_task() -> None:
    import io

    bar = Progress("t", 4, stream=io.StringIO(), terminal=False)
    seen: list[int] = []

    def task(i: int) -> int:
        seen.append(bar.done)
        return i

    with open_pool(1) as pool:
        assert pool.map(task, [0, 1, 2, 3], bar) == [0, 1, 2, 3]
    bar.close()  # the process's active progress: left open, it took later tests' notes
    assert seen == [0, 1, 2, 3]
    assert pool.tasks_run == 4


# -- a Dask cluster that cannot be used, or is lost -------------------------------------------
#: A scheduler and one worker in one process (threads), which says its address: killing the
#: process loses the scheduler, and leaves no worker process behind.
ONE_PROCESS_CLUSTER = """
import time
from distributed import LocalCluster
cluster = LocalCluster(
    n_workers=1, threads_per_worker=1, processes=False, protocol="tcp", dashboard_address=":0",
    scheduler_port=0,
)
print(cluster.scheduler_address, flush=True)
time.sleep(600)
"""


def mark_and_sleep(path: str) -> int:
    """A task that says it has started, then works on (until its worker is gone)."""
    Path(path).write_text("started")
    time.sleep(120.0)
    return 0


def _open_in_thread(address: str) -> BaseException | None:
    """What ``open_pool`` raised for ``address``, or ``None``; it must not wait for ever."""
    raised: list[BaseException] = []

    def attempt() -> None:
        try:
            open_pool(scheduler=address).close()
        except BaseException as exc:
            raised.append(exc)

    thread = threading.Thread(target=attempt, daemon=True)
    thread.start()
    thread.join(120.0)
    assert not thread.is_alive(), f"open_pool({address!r}) still waiting"
    return raised[0] if raised else None


@pytest.mark.parametrize(
    "address",
    ["tcp://127.0.0.1", "inproc://x", "tcp://127.0.0.1:99999", "tcp://127.0.0.1:0", "ucx://h:1"],
)
def test_an_address_dask_cannot_use_is_refused_by_its_form(address: str) -> None:
    """Dask would take these and fail only once connecting, after its retries."""
    with pytest.raises(ConfigError, match=r"^--scheduler: expected a Dask scheduler address"):
        check_scheduler(address)


def test_addresses_of_every_accepted_form_pass() -> None:
    for address in ("tcp://[::1]:8786", "tls://sched.lan:8786", "ws://h:1", "wss://h:65535"):
        assert check_scheduler(address) == address


def test_a_tls_address_without_dask_s_tls_settings_is_refused_at_once() -> None:
    pytest.importorskip("distributed")
    with pytest.raises(ConfigError) as raised:
        open_pool(scheduler="tls://127.0.0.1:9")
    assert str(raised.value).startswith("--scheduler: expected Dask's TLS settings")
    assert "DASK_DISTRIBUTED__COMM__TLS__CA_FILE" in str(raised.value)
    assert "found 'tls://127.0.0.1:9'" in str(raised.value)
    assert str(raised.value).endswith(
        ": the CA file (distributed.comm.tls.ca-file, DASK_DISTRIBUTED__COMM__TLS__CA_FILE) and "
        "the client cert (distributed.comm.tls.client.cert, "
        "DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT) are not set in Dask's configuration"
    )


def test_a_tls_address_with_one_of_dask_s_tls_settings_missing_names_it(tmp_path: Path) -> None:
    """ "no CA file and client certificate" was said whichever of the two was missing, with
    the three settings after it: the one not set is named (an outside audit)."""
    pytest.importorskip("distributed")
    import dask.config

    ca = tmp_path / "ca.pem"
    ca.write_text("not read: the settings are refused before any file is")
    with (
        dask.config.set({"distributed.comm.tls.ca-file": str(ca)}),
        pytest.raises(ConfigError) as raised,
    ):
        open_pool(scheduler="tls://127.0.0.1:9")
    assert str(raised.value).endswith(
        ": the client cert (distributed.comm.tls.client.cert, "
        "DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT) is not set in Dask's configuration"
    )


def _self_signed(tmp_path: Path) -> tuple[str, str]:
    """A certificate (its own CA) and its key, for 127.0.0.1."""
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [
            *("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2"),
            *("-keyout", str(key), "-out", str(cert), "-subj", "/CN=localhost"),
            *("-addext", "subjectAltName=IP:127.0.0.1"),
        ],
        check=True,
        capture_output=True,
    )
    return str(cert), str(key)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="makes its certificate with openssl")
def test_a_tls_cluster_is_used_through_dask_s_own_tls_settings(tmp_path: Path) -> None:
    """What docs/scale.md says to set for tls:// is all it takes; a file it names that is not
    there is refused, named."""
    distributed = pytest.importorskip("distributed")
    import dask.config

    cert, key = _self_signed(tmp_path)
    roles = {
        f"tls_{role}_{part}": path
        for role in ("scheduler", "worker", "client")
        for part, path in (("cert", cert), ("key", key))
    }
    security = distributed.Security(tls_ca_file=cert, require_encryption=True, **roles)
    settings = {
        "distributed.comm.tls.ca-file": cert,
        "distributed.comm.tls.client.cert": cert,
        "distributed.comm.tls.client.key": key,
    }
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        protocol="tls",
        security=security,
        dashboard_address=":0",
        scheduler_port=0,
    ) as cluster:
        address = cluster.scheduler_address
        with dask.config.set(settings), open_pool(scheduler=address) as pool:
            assert pool.map(abs, [-1, -2]) == [1, 2]
        missing = str(tmp_path / "missing.pem")
        with (
            dask.config.set({**settings, "distributed.comm.tls.ca-file": missing}),
            pytest.raises(ConfigError) as raised,
        ):
            open_pool(scheduler=address)
    assert str(raised.value).startswith("--scheduler: expected Dask's TLS settings usable")
    assert f"FileNotFoundError: [Errno 2] No such file or directory (of CA file {missing}" in str(
        raised.value
    )


class _Http(http.server.BaseHTTPRequestHandler):
    def log_message(self, *_: object) -> None:  # not on the test's stderr
        pass


@pytest.mark.parametrize("peer", ["listen only", "http"])
def test_a_port_that_does_not_speak_dask_is_refused(
    peer: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A socket that accepts and never answers, or a server of another protocol (a cluster's
    dashboard is HTTP, on the port next to the scheduler's): refused, not waited on."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 2.0)  # neither ever answers Dask
    with contextlib.ExitStack() as stack:
        if peer == "http":
            server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Http)
            threading.Thread(target=server.serve_forever, daemon=True).start()
            stack.callback(server.server_close)
            stack.callback(server.shutdown)
            port = server.server_address[1]
        else:
            listener = stack.enter_context(socket.socket())
            listener.bind(("127.0.0.1", 0))
            listener.listen()
            port = listener.getsockname()[1]
        raised = _open_in_thread(f"tcp://127.0.0.1:{port}")
    assert isinstance(raised, ConfigError), raised
    assert str(raised).startswith(
        f"--scheduler: expected a Dask scheduler that answers within 2 s, "
        f"found 'tcp://127.0.0.1:{port}': "
    )


def test_a_scheduler_without_workers_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)  # none will ever come
    with distributed.LocalCluster(
        n_workers=0, processes=False, protocol="tcp", dashboard_address=":0", scheduler_port=0
    ) as cluster:
        raised = _open_in_thread(cluster.scheduler_address)
    assert isinstance(raised, ConfigError), raised
    assert "expected a Dask cluster with at least one worker" in str(raised)


#: worker preloads: one that makes handctl unimportable, one that gives it another version
NO_HANDCTL = """
import importlib.abc, sys
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "handctl":
            raise ModuleNotFoundError(f"No module named {name!r}")
sys.meta_path.insert(0, Refuse())
for name in [n for n in sys.modules if n.split(".")[0] == "handctl"]:
    del sys.modules[name]
"""
OTHER_VERSION = "import handctl\nhandctl.__version__ = '0.0.1'\n"
#: handctl of this version from another copy of its code (``OTHER`` is where)
OTHER_CODE = """
import sys
sys.path.insert(0, OTHER)
for name in [n for n in sys.modules if n.split(".")[0] == "handctl"]:
    del sys.modules[name]
"""

#: a worker whose MuJoCo is installed (its package metadata there) but does not import
NO_MUJOCO = """
import importlib.abc, sys
class Broken(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "mujoco":
            raise ImportError("libmujoco.so: cannot open shared object file")
sys.meta_path.insert(0, Broken())
for name in [n for n in sys.modules if n.split(".")[0] == "mujoco"]:
    del sys.modules[name]
"""


@pytest.mark.parametrize(
    ("preload", "found"),
    [
        pytest.param(NO_HANDCTL, "ModuleNotFoundError: No module named 'handctl'", id="none"),
        pytest.param(
            NO_MUJOCO,
            ", but mujoco does not import (ImportError: libmujoco.so: cannot open",
            id="no mujoco",
        ),
        pytest.param(OTHER_VERSION, ": handctl 0.0.1 (code ", id="another version"),
        pytest.param(OTHER_CODE, f": handctl {handctl.__version__} (code ", id="other code"),
    ],
)
def test_a_cluster_whose_worker_lacks_this_handctl_is_refused(
    tmp_path: Path, preload: str, found: str
) -> None:
    """A worker without handctl cannot read a task: Dask logs it there and the work waits for
    ever. It is found before any task goes out, and named. So is a worker of this version
    running other code (a stale checkout: the version string stays as it is between
    commits), which planned with that code and changed the recipe without a word (an outside
    probe: one torque scaled by 1.05 on the worker). So is a worker whose MuJoCo is installed
    but does not import: its version was read from the package's metadata, and the worker
    died of its first task (an outside audit)."""
    distributed = pytest.importorskip("distributed")

    if preload is OTHER_CODE:
        other = tmp_path / "other"
        shutil.copytree(
            Path(handctl.__file__).parent,
            other / "handctl",
            ignore=shutil.ignore_patterns("__pycache__"),
        )
        changed = other / "handctl" / "planning" / "episode.py"
        changed.write_text(changed.read_text() + "\n# another checkout\n")
        preload = f"OTHER = {str(other)!r}\n{OTHER_CODE}"
    script = tmp_path / "preload.py"
    script.write_text(preload)
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        scheduler_port=0,
        preload=[str(script)],
    ) as cluster:
        raised = _open_in_thread(cluster.scheduler_address)
        (worker,) = cluster.scheduler.workers
    assert isinstance(raised, ConfigError), raised
    message = str(raised)
    assert message.startswith(f"--scheduler: expected handctl {handctl.__version__} (code "), (
        message
    )
    assert "importable, on every worker" in message
    assert f"1 of 1 workers have not: {worker}" in message
    assert found in message


def test_a_worker_that_does_not_answer_the_check_is_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One of two workers frozen (SIGSTOP; its machine hung): the check asked them all in
    one question, which timed out as a whole, and the plan was refused "no answer from its
    workers" without naming which, the other's answer thrown away (an outside audit). Each
    is asked on its own; the frozen one is named, with how many answered."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        protocol="tcp",
        dashboard_address=":0",
        scheduler_port=0,
    ) as cluster:
        address = cluster.scheduler_address
        open_pool(scheduler=address).close()  # both answer: what a task imports, imported
        with distributed.Client(address, set_as_default=False) as client:
            pids: dict[str, int] = client.run(os.getpid)
        frozen, pid = sorted(pids.items())[0]
        name = cluster.scheduler.workers[frozen].name
        # the other answers in some 0.05 s: a bound a hundred times that is no race
        monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 5.0)
        os.kill(pid, signal.SIGSTOP)
        try:
            raised = _open_in_thread(address)
        finally:
            os.kill(pid, signal.SIGCONT)
    assert isinstance(raised, ConfigError), raised
    assert str(raised) == (
        f"--scheduler: expected a Dask cluster whose workers answer, found '{address}': 1 of 2 "
        f"workers answered the version check in 5 s; no answer from {frozen} (name {name}) "
        "(frozen, or its machine or the network hung)"
    )


def out_of_memory_on_one(i: int) -> int:
    """A task whose allocation fails on its worker, as one past the worker's memory does."""
    if i == 1:
        raise MemoryError("injected")
    return i


def test_a_task_out_of_memory_on_a_worker_names_the_worker_not_this_host() -> None:
    """A task's ``MemoryError`` on a cluster worker reached the command as it was, which
    said "this host ran out of memory ... raise the process's limit (ulimit -v)" (an outside
    audit): the memory was the worker's. Said as the worker's, naming it and the cluster;
    any other error of a task names them in a note its traceback ends with."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        dashboard_address=":0",
        scheduler_port=0,
    ) as cluster:
        address = cluster.scheduler_address
        ((worker, state),) = cluster.scheduler.workers.items()
        with open_pool(scheduler=address) as pool:
            with pytest.raises(executor.WorkerMemoryError) as raised:
                pool.map(out_of_memory_on_one, [0, 1, 2])
            with pytest.raises(ValueError, match=r"^task 3 cannot") as other:
                pool.map(fail_on_three, [3])
    assert (raised.value.address, raised.value.worker) == (address, f"{worker} (name {state.name})")
    assert str(raised.value) == (
        f"the Dask cluster at {address}: a task ran out of memory on its worker {worker} (name "
        f"{state.name}) (MemoryError: injected): that worker's memory, not this host's. Give "
        "the cluster's workers more (dask worker --memory-limit, or fewer --nworkers on that "
        "machine), and see the worker's log"
    )
    assert other.value.__notes__ == [
        f"(raised by a task on the worker {worker} (name {state.name}) of the Dask cluster at "
        f"{address})"
    ]


def _raised_when_killed(
    open_it: Callable[[], WorkPool], started: Path, kill: Callable[[], None]
) -> list[BaseException]:
    """What a map of one long task on the pool ``open_it`` opens raised once ``kill`` ended
    what ran it, the task having started; the map must end, not wait for ever."""
    raised: list[BaseException] = []

    def work() -> None:
        try:
            with open_it() as pool:
                pool.map(mark_and_sleep, [str(started)])
        except BaseException as exc:
            raised.append(exc)

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120.0
    while not started.exists() and time.monotonic() < deadline and thread.is_alive():
        time.sleep(0.05)
    assert started.exists(), raised
    kill()
    thread.join(120.0)
    assert not thread.is_alive()
    return raised


@contextlib.contextmanager
def _one_process_cluster() -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``ONE_PROCESS_CLUSTER`` started, and its scheduler's address; killed at the end (a
    stopped process all the same)."""
    with subprocess.Popen(
        [sys.executable, "-c", ONE_PROCESS_CLUSTER], cwd=ROOT, stdout=subprocess.PIPE, text=True
    ) as cluster:
        try:
            assert cluster.stdout is not None
            yield cluster, cluster.stdout.readline().strip()
        finally:
            cluster.kill()


def test_a_scheduler_lost_while_the_work_runs_is_named(tmp_path: Path) -> None:
    """The client cancels every task when its scheduler goes: that is the cluster lost, said
    as such, not the first task's bare ``CancelledError``."""
    pytest.importorskip("distributed")
    started = tmp_path / "started"
    with _one_process_cluster() as (cluster, address):
        raised = _raised_when_killed(lambda: open_pool(scheduler=address), started, cluster.kill)
    assert len(raised) == 1 and isinstance(raised[0], ClusterLostError), raised
    assert str(raised[0]) == (
        f"--scheduler {address}: the Dask scheduler was lost while the work ran "
        "(the connection to it closed)"
    )


class _Records(logging.Handler):
    """What a logger logged, kept to be looked at."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_a_scheduler_lost_between_two_maps_is_named_in_one_line() -> None:
    """A scheduler lost before a map, long enough for the client to give up on it (10 s):
    the map's first submission raised Dask's ``ClosedClientError``, the pool's close a
    second one as it cancelled, and Dask logged its "Failed to reconnect" error before
    either (an outside audit). The cluster lost, said once; the close is quiet (a second
    error from it would be what ``pytest.raises`` sees)."""
    pytest.importorskip("distributed")
    said = _Records()
    client_logger = logging.getLogger("distributed.client")
    client_logger.addHandler(said)
    try:
        with _one_process_cluster() as (cluster, address):
            pool = open_pool(scheduler=address)
            with pytest.raises(ClusterLostError) as raised, pool:  # closed as cancelled
                assert pool.map(abs, [-1, -2]) == [1, 2]
                cluster.kill()
                cluster.wait()
                client: Any = pool.executor._client  # type: ignore[attr-defined]
                deadline = time.monotonic() + 120.0
                while client.status != "closed" and time.monotonic() < deadline:
                    time.sleep(0.1)
                assert client.status == "closed"  # it gave up: the case of the audit
                pool.map(abs, [-3])
    finally:
        client_logger.removeHandler(said)
    assert str(raised.value) == (
        f"--scheduler {address}: the Dask scheduler was lost while the work ran "
        "(the connection to it closed)"
    )
    assert [r.getMessage() for r in said.records if "reconnect" in r.getMessage()] == []


def test_a_scheduler_that_stops_answering_is_given_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scheduler frozen under the plan (SIGSTOP; its machine hung, the network gone with
    the connection open): Dask's question of how many workers it has waited for ever, and the
    plan sat at "0/24" with its progress line stopped for twelve minutes (an outside probe).
    Given up, said, once it has answered nothing for ``SCHEDULER_SILENT_S``."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "SCHEDULER_ANSWER_S", 0.5)
    monkeypatch.setattr(executor, "SCHEDULER_SILENT_S", 2.0)
    monkeypatch.setattr(executor, "IDLE_CHECK_S", 0.2)
    started = tmp_path / "started"
    with _one_process_cluster() as (cluster, address):
        raised = _raised_when_killed(
            lambda: open_pool(scheduler=address),
            started,
            lambda: os.kill(cluster.pid, signal.SIGSTOP),
        )
    assert len(raised) == 1 and not isinstance(raised[0], ClusterLostError), raised
    assert str(raised[0]) == (
        f"--scheduler {address}: the Dask scheduler has not answered for 2 s (frozen, or its "
        "machine or the network hung): the work is given up; nothing was written"
    )


def test_a_cluster_left_without_workers_is_given_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every worker gone, the scheduler still up: the plan's tasks waited for one for ever,
    without a word. Given up, said, once the cluster has had none for ``NO_WORKER_S``."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "NO_WORKER_S", 1.0)
    monkeypatch.setattr(executor, "IDLE_CHECK_S", 0.2)
    started = tmp_path / "started"
    with distributed.LocalCluster(
        n_workers=0, processes=False, protocol="tcp", dashboard_address=":0", scheduler_port=0
    ) as cluster:
        address = cluster.scheduler_address
        # a worker of its own process, without a nanny to start it again
        command = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--no-nanny"]
        with subprocess.Popen(
            [*command, "--nthreads", "1"], cwd=ROOT, stderr=subprocess.DEVNULL
        ) as worker:
            try:
                raised = _raised_when_killed(
                    lambda: open_pool(scheduler=address), started, worker.kill
                )
            finally:
                if worker.poll() is None:
                    worker.kill()
    assert len(raised) == 1 and not isinstance(raised[0], ClusterLostError), raised
    assert str(raised[0]).startswith(
        f"--scheduler {address}: the Dask cluster has had no worker for 1 s"
    )


def _unwatched_cluster(distributed: Any) -> Any:
    """A one-worker LocalCluster in this process whose memory Dask does not watch
    (``memory_limit=0``): its monitor would otherwise un-pause a worker paused by hand."""
    return distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        dashboard_address=":0",
        scheduler_port=0,
        memory_limit=0,
    )


def _pause(dask_worker: object) -> None:
    """A worker paused as Dask pauses one whose memory passes its pause threshold (run in
    the worker's event loop by ``Client.run``: the status goes to the scheduler from there)."""
    from distributed.core import Status

    dask_worker.status = Status.paused  # type: ignore[attr-defined]


def test_a_cluster_whose_workers_are_all_paused_is_said_and_given_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A paused worker counted as a worker: a plan on a cluster whose one worker was paused
    (``dask worker --memory-limit 120MB``) said "none done for 4:30" every 10 s for ever and
    never why (an outside audit). Said once, and given up, said, once the cluster has had no
    running worker for ``NO_WORKER_S``. The worker is paused through Dask's own status (a
    real one paused by its memory: too slow and too loose a test on a loaded machine), with
    no memory limit, so that Dask's memory monitor does not resume it."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "NO_WORKER_S", 1.0)
    monkeypatch.setattr(executor, "IDLE_CHECK_S", 0.2)
    said = io.StringIO()
    raised: list[BaseException] = []
    with _unwatched_cluster(distributed) as cluster:
        address = cluster.scheduler_address
        pool = open_pool(scheduler=address)  # its worker running: the check passes
        with distributed.Client(address, set_as_default=False) as client:
            client.run(_pause)

        def work() -> None:
            bar = Progress("t", 1, stream=said, terminal=False)
            try:
                with pool:
                    pool.map(later_first, [(0, 1)], bar)
            except BaseException as exc:
                raised.append(exc)
            finally:
                # the process's active progress: left open, it took the notes ``say`` gives
                # in the tests after this one (their stderr was empty)
                bar.close()

        thread = threading.Thread(target=work, daemon=True)
        thread.start()
        thread.join(120.0)
        assert not thread.is_alive(), "the map still waits on a paused worker"
    assert len(raised) == 1 and not isinstance(raised[0], ClusterLostError), raised
    assert str(raised[0]) == (
        f"--scheduler {address}: the Dask cluster has had no running worker for 1 s, its one "
        "worker is paused (Dask pauses a worker whose memory passes its pause threshold, "
        "distributed.worker.memory.pause): its tasks would wait for one for ever, and the work "
        "is given up"
    )
    assert f"the Dask cluster at {address}: its one worker is paused (" in said.getvalue()


def test_a_cluster_whose_one_worker_is_paused_is_not_said_to_have_none(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Dask waits for a running worker: a cluster whose worker was paused was refused as
    one with none."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)
    with _unwatched_cluster(distributed) as cluster:
        with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
            client.run(_pause)
        raised = _open_in_thread(cluster.scheduler_address)
    assert isinstance(raised, ConfigError), raised
    assert str(raised).endswith(
        ": none running in 1 s: its one worker is paused (Dask pauses a worker whose memory "
        "passes its pause threshold, distributed.worker.memory.pause)"
    ), raised


def test_a_local_worker_killed_is_said_in_one_line(tmp_path: Path) -> None:
    """``kill -9`` of a local worker (or the kernel's OOM killer) ended a plan with the
    pool's BrokenProcessPool traceback."""

    def kill_the_workers() -> None:
        workers = [p for p in psutil.Process().children() if "spawn_main" in " ".join(p.cmdline())]
        assert workers
        for process in workers:
            process.kill()

    raised = _raised_when_killed(lambda: open_pool(2), tmp_path / "started", kill_the_workers)
    assert len(raised) == 1 and isinstance(raised[0], HandctlError), raised
    assert str(raised[0]) == (
        "a local worker process was killed (SIGKILL: the kernel's out-of-memory killer, a hard "
        "CPU time limit, or kill -9): the work cannot go on"
    )


def spin_past_a_cpu_limit(_: int) -> int:
    """A task whose worker's CPU time limit runs out one second on: the kernel's SIGXCPU."""
    used = resource.getrusage(resource.RUSAGE_SELF)
    soft = int(used.ru_utime + used.ru_stime) + 1
    resource.setrlimit(resource.RLIMIT_CPU, (soft, soft + 60))
    while True:
        pass


def test_a_local_worker_out_of_its_cpu_time_limit_is_said_so() -> None:
    """A plan under ``ulimit -t`` lost a worker to SIGXCPU and said "killed, or out of
    memory", which sent the user looking for memory; the pool ends the other workers with
    SIGTERM, and that is not the cause either."""
    with pytest.raises(HandctlError) as raised, open_pool(2) as pool:
        pool.map(spin_past_a_cpu_limit, [0, 1])
    assert str(raised.value) == (
        "a local worker process ran out of the CPU time its limit allows (SIGXCPU; ulimit -t): "
        "the work cannot go on"
    )


def test_the_resource_tracker_holds_back_the_terminal_s_signals() -> None:
    """It shares the terminal's process group: Ctrl-\\ killed it, and a plan stopped cleanly
    by it printed "process died unexpectedly" and five KeyError tracebacks (found by an
    outside review). Started by handctl, SIGQUIT, SIGTSTP and SIGHUP are blocked in it. (In a
    process of its own: this one's tracker may have been started by another test.)"""
    script = (
        "import signal\n"
        "from multiprocessing import resource_tracker\n"
        "from handctl.executor import start_resource_tracker\n"
        "start_resource_tracker()\n"
        "pid = resource_tracker._resource_tracker._pid\n"
        "status = open(f'/proc/{pid}/status').read()\n"
        "line = next(x for x in status.splitlines() if x.startswith('SigBlk:'))\n"
        "blocked = int(line.split()[1], 16)\n"
        "held = (signal.SIGQUIT, signal.SIGTSTP, signal.SIGHUP)\n"
        "print(all(blocked >> (s - 1) & 1 for s in held))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=60
    )
    assert done.stdout.strip() == "True", done.stdout + done.stderr


def _die() -> None:
    """A task that takes its worker process down with it, as a crash or the OOM killer does."""
    os._exit(3)


def test_a_task_whose_workers_keep_dying_is_said_in_one_line() -> None:
    """A worker that died under a task again and again (a crash, out of memory) ended a plan
    with Dask's KilledWorker said as an internal error of handctl, with a traceback (an
    outside audit): said as what it is, naming the cluster."""
    distributed = pytest.importorskip("distributed")
    import dask

    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        distributed.LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=True,
            protocol="tcp",
            dashboard_address=":0",
            scheduler_port=0,
        ) as cluster,
    ):
        address = cluster.scheduler_address
        with open_pool(scheduler=address) as pool, pytest.raises(HandctlError) as raised:
            pool.map(lambda _: _die(), [0])
    said = str(raised.value)
    assert said.startswith(f"the Dask cluster at {address} (1 worker): workers died under a ")
    assert said.endswith("the workers' own logs say why (out of memory, a crash)")
