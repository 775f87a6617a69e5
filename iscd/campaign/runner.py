"""The runner over Dask distributed: one call per item on the workers, results in order.

:class:`Runner` starts a :class:`distributed.LocalCluster` (worker processes, one thread
each, BLAS/OpenMP/Numba threads 1) or connects to an existing scheduler
(``tcp://HOST:8786``), prints the dashboard's address, and :meth:`Runner.map` submits one
task per item, shows progress (tqdm over the futures with done/failed counts and the ETA;
one line per task when stderr is not a terminal) and gives the results in the items'
order. Only the items (small: paths and numbers) and the results travel through the
scheduler. Ctrl-C cancels what has not finished and closes the cluster; what the tasks
wrote stays as they left it (:mod:`iscd.campaign.tasks` renames outputs when complete).
"""

from __future__ import annotations

import importlib.util
import logging
import os
import sys
import uuid
from typing import Any, Callable, Sequence

from iscd.core.errors import UserError

SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                     "NUMBA_NUM_THREADS": "1"}
"""Environment of every LocalCluster worker: one BLAS/OpenMP/Numba thread (one core each)."""
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
}
"""Dask settings of the LocalCluster the runner starts (its scheduler, nannies and workers).

Its background work, costless while one worker leaves a core free, takes from the tasks
when the workers fill the cores: with the defaults each idle worker process used 0.03 of a
core here and the client's process (scheduler, nannies) 0.04 -- the workers' statistical
profiler samples the task's stack every 10 ms, an event-loop tick every 20 ms, the system
and memory monitors several times a second -- together about a twentieth of this 2-core
machine. With these: 0.004 per worker, 0.01 for the client's process. What is given up:
the dashboard's Profile page stays empty, its system page updates every 2 s, a blocked
event loop is noticed within 0.5 s, a worker's memory checked every second. An existing
cluster (``--scheduler``) keeps its own settings."""
CONNECT_TIMEOUT_S = 10.0
"""How long to try an existing scheduler before giving up, s."""
WORKERS_TIMEOUT_S = 60.0
"""How long an existing scheduler may take to show a worker, s."""

Say = Callable[[str], None]


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def quiet_logs() -> None:
    """distributed's (and tornado's) loggers to errors only: the runner says what matters."""
    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] in ("distributed", "tornado", "bokeh")]
    for name in names + ["distributed", "tornado"]:
        logging.getLogger(name).setLevel(logging.ERROR)


def warm_worker() -> None:
    """Import the decoder and load its compiled kernels in this (worker) process."""
    import iscd.decode.stream  # noqa: F401
    from iscd.core.jit import warm_up

    warm_up()


def default_workers() -> int:
    """Workers of the default LocalCluster: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def check_address(addr: str, given: str) -> None:
    """Raise UserError (one line naming ``--scheduler given``) unless ``addr`` is a scheduler
    address distributed can connect to: a known scheme other than inproc and, for tcp/tls/ws/wss, HOST:PORT
    with a port in 1..65535. Checked before the Client is made: a Client that fails on
    its address leaves an object whose clean-up prints a traceback after 20 s."""
    from distributed.comm import get_address_host_port, parse_address
    from distributed.comm.registry import get_backend

    try:
        scheme, _ = parse_address(addr)
        get_backend(scheme)
        if scheme == "inproc":
            raise ValueError("inproc:// is a scheduler in this process only")
        if scheme in ("tcp", "tls", "ws", "wss"):
            _, port = get_address_host_port(addr)
            if not 0 < int(port) < 65536:
                raise ValueError(f"port {port} is not in 1..65535")
    except (ValueError, TypeError) as e:
        raise UserError(f"--scheduler {given}: not a scheduler address ({' '.join(str(e).split())}); "
                        "expected e.g. tcp://HOST:8786") from None


class Runner:
    """Dask client (and LocalCluster) for a campaign or an ``iscd eval`` sweep.

    Parameters
    ----------
    workers : int, optional
        LocalCluster worker processes (default :func:`default_workers`); not with ``scheduler``.
    scheduler : str, optional
        Address of a running scheduler (``tcp://HOST:8786``): its workers run the tasks
        (they must have iscd installed and see the same paths).
    say : callable
        Where the runner's lines go (default stderr), with the prefix ``prog``.
    prog : str
        Prefix of the lines (``iscd campaign``).
    verbose : bool
        Keep distributed's own log lines.
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None, *, say: Say = _stderr,
                 prog: str = "iscd campaign", verbose: bool = False) -> None:
        if workers is not None and scheduler is not None:
            raise UserError("--workers and --scheduler exclude each other (an existing cluster has its own workers)")
        if workers is not None and workers < 1:
            raise UserError(f"--workers: expected at least 1 worker, got {workers}")
        self.workers = workers
        self.scheduler = scheduler
        self.say = say
        self.prog = prog
        self.verbose = verbose
        self.cluster: Any = None
        self.client: Any = None
        self.n_workers = 0
        """workers when the runner started (a LocalCluster's, or those of the scheduler)"""

    def __enter__(self) -> "Runner":
        from distributed import Client

        if not self.verbose:  # after the import: distributed sets its loggers' levels when imported
            quiet_logs()

        if self.scheduler:
            addr = self.scheduler
            if "://" not in addr:
                addr = f"tcp://{addr}"
            check_address(addr, self.scheduler)
            try:
                self.client = Client(addr, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
            except (OSError, TimeoutError, ValueError) as e:
                raise UserError(f"--scheduler {self.scheduler}: cannot connect: {' '.join(str(e).split()) or type(e).__name__}") from None
            try:
                self.client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
            except (TimeoutError, OSError):
                self.close()
                raise UserError(f"--scheduler {self.scheduler}: no worker joined within {WORKERS_TIMEOUT_S:g} s") from None
            n = self.n_workers = len(self.client.scheduler_info(n_workers=-1).get("workers", {}))
            self.say(f"{self.prog}: scheduler {addr}, {n} worker(s); dashboard: {self.client.dashboard_link}")
            return self
        import dask
        from distributed import LocalCluster

        n = self.n_workers = self.workers or default_workers()
        dashboard = ":0"  # a free port (without bokeh only its health routes: no dashboard)
        has_dashboard = importlib.util.find_spec("bokeh") is not None
        # the workers' Numba/BLAS pools: one thread (env=, which the nannies set in the
        # workers before they start, and the BLAS variables in this process's environment
        # while they are started, restored afterwards). Never this process's
        # NUMBA_NUM_THREADS: Numba rereads it at every compilation and refuses to compile
        # once its thread pool was launched with another value ("Cannot set
        # NUMBA_NUM_THREADS to a different value once the threads have been launched": a
        # full test run after a campaign test)
        blas = {k: v for k, v in SINGLE_THREAD_ENV.items() if k != "NUMBA_NUM_THREADS"}
        saved = {k: os.environ.get(k) for k in blas}
        os.environ.update(blas)
        try:
            # distributed is imported (its defaults loaded) before the settings are set: a
            # set before that import would drop the whole "distributed" section on exit
            with dask.config.set(LOCAL_CLUSTER_CONFIG):  # the nannies hand it to the workers
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                            dashboard_address=dashboard, env=dict(SINGLE_THREAD_ENV),
                                            silence_logs=logging.WARNING if self.verbose else logging.ERROR)
            self.client = Client(self.cluster, set_as_default=False)
        except Exception:
            self.close()
            raise
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        where = self.client.dashboard_link if has_dashboard else "not available (install bokeh for it)"
        self.say(f"{self.prog}: LocalCluster of {n} worker process(es), 1 thread each; dashboard: {where}")
        return self

    def warm_up(self) -> None:
        """Load the decoder and its compiled kernels on every worker (``iscd.core.jit``:
        from the cache, or compiled once), so that the first tasks and the ETA do not
        carry it."""
        self.client.run(warm_worker)

    def describe(self) -> str:
        """'a LocalCluster of N workers' or 'scheduler ADDRESS (N workers)', for reports."""
        if self.scheduler:
            return f"scheduler {self.scheduler} ({self.n_workers} workers)"
        return f"a LocalCluster of {self.n_workers} worker processes"

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the client and the LocalCluster (if this runner started one)."""
        for obj in (self.client, self.cluster):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 - closing after Ctrl-C or a lost scheduler
                    pass
        self.client = self.cluster = None

    def map(self, fn: Callable[..., Any], items: Sequence[Any], *, args: tuple = (), labels: Sequence[str] = (),
            failed: Callable[[Any], str | None] = lambda r: None, desc: str = "tasks",
            on_result: Callable[[int, Any], None] | None = None,
            error_result: Callable[[int, BaseException], Any] | None = None) -> list[Any]:
        """``[fn(item, *args) for item in items]`` on the workers, in the items' order.

        Parameters
        ----------
        fn : callable
            Importable on the workers (a module-level function) or picklable by cloudpickle.
        items : sequence
            One task each; small (paths, numbers, configs): no frame data.
        args : tuple
            Further arguments of every call.
        labels : sequence of str
            A name per item for the progress lines (default its index).
        failed : callable
            ``failed(result)`` -> one line of error for a result that counts as failed, else None.
        desc : str
            The progress bar's label.
        on_result : callable, optional
            ``on_result(index, result)`` as each task finishes (in the order they finish).
        error_result : callable, optional
            ``error_result(index, exception)`` -> the result of a task that raised or whose
            worker died (distributed's KilledWorker after its retries); without it the
            exception is raised here.

        Returns
        -------
        list
            The results in the items' order. A task that raised re-raises here unless
            ``error_result`` is given (the campaign's tasks return a failed result instead of
            raising; a worker that dies under one is such an error).
        """
        from distributed import as_completed
        from tqdm import tqdm

        if not items:
            return []
        labels = list(labels) or [str(i) for i in range(len(items))]
        run = uuid.uuid4().hex[:8]
        futures = [self.client.submit(fn, item, *args, key=f"{desc}-{run}-{i}", pure=False)
                   for i, item in enumerate(items)]
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[Any] = [None] * len(items)
        done = bad = 0
        bar = tqdm(total=len(items), unit="task", desc=desc, disable=None, file=sys.stderr)
        try:
            for fut in as_completed(futures, loop=self.client.loop):
                i = index[fut.key]
                try:
                    res = fut.result()
                except Exception as e:  # noqa: BLE001 - a task's exception, a lost worker
                    if error_result is None:
                        raise
                    res = error_result(i, e)
                out[i] = res
                err = failed(res)
                done += 1
                bad += err is not None
                bar.set_postfix(done=done, failed=bad, refresh=False)
                bar.update(1)
                if bar.disable:  # no terminal (a log, CI): one line per task
                    self.say(f"{self.prog}: [{done}/{len(items)}] {labels[i]}: "
                             f"{'failed: ' + err if err is not None else 'ok'}")
                if on_result is not None:
                    on_result(i, res)
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        finally:
            bar.close()
        return out

