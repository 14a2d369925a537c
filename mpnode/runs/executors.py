"""Where independent tasks run: the one place that opens an executor.

A *scheduler* names it:

* ``None`` or ``"none"``: a local process pool (`concurrent.futures.ProcessPoolExecutor`),
  the embedded default, needing nothing beyond mpnode;
* ``"local"``: a Dask ``LocalCluster`` on this machine, ``workers`` processes of one thread
  each, ``NUMBA_NUM_THREADS=1`` in every worker (one training or trajectory chunk per core);
* ``"tcp://host:8786"`` (any ``scheme://``): the scheduler of a cluster already running
  (``dask scheduler`` / ``dask worker``, dask-jobqueue, dask-kubernetes, ...);
* a path to a scheduler file (``dask scheduler --scheduler-file``, dask-mpi, jobqueue).

Dask (``pip install 'mpnode[dist]'``) is imported only when a scheduler other than the
pool is asked for, so ``import mpnode`` and every command stay as light as without it.
The command line's ``--scheduler`` defaults to the environment variable MPNODE_SCHEDULER
(`default_scheduler`); library calls use the pool unless told otherwise.

Both kinds are used through one `Farm`: ``submit`` returns a `concurrent.futures.Future`
(Dask's client executor wraps its futures in them), so callers wait with
`concurrent.futures.as_completed` / ``wait`` whatever runs the tasks.
"""
import concurrent.futures as cf
import contextlib
import logging
import multiprocessing
import os
import signal

from mpnode.base.errors import InputError

#: the environment variable that sets the command line's default --scheduler
ENV = "MPNODE_SCHEDULER"
INSTALL = "pip install 'mpnode[dist]'"
#: seconds to wait for a scheduler to answer
CONNECT_TIMEOUT = 20


def default_scheduler():
    """The scheduler MPNODE_SCHEDULER names, or None (the local process pool)."""
    return os.environ.get(ENV) or None


def parse_scheduler(value, source="--scheduler"):
    """(kind, target) of a scheduler setting: ("pool", None), ("local", None),
    ("address", "tcp://...") or ("file", path).  InputError for anything else."""
    text = "" if value is None else str(value).strip()
    if text.lower() in ("", "none", "pool"):
        return "pool", None
    if text.lower() == "local":
        return "local", None
    if "://" in text:
        return "address", text
    if os.path.isfile(text):
        return "file", text
    raise InputError(source, text, "is neither 'local', a scheduler address nor an existing scheduler file",
                     "none, local, tcp://HOST:8786 (what `dask scheduler` prints) or the path of a scheduler file")


class Farm:
    """A concurrent.futures executor and what differs between the process pool and Dask.

    kind : "pool" or "dask";  workers : tasks that run at once (Dask: worker threads now)
    """

    def __init__(self, executor, kind, workers, client=None, cluster=None, make_pool=None):
        self.executor, self.kind, self.workers = executor, kind, workers
        self.client, self.cluster, self._make_pool = client, cluster, make_pool

    @property
    def is_dask(self):
        return self.kind == "dask"

    def submit(self, fn, *args):
        """Run fn(*args) somewhere; a concurrent.futures.Future."""
        return self.executor.submit(fn, *args)

    def share(self, obj):
        """What to pass to tasks instead of ``obj`` when many tasks take it: on Dask, ``obj`` is
        sent once to every worker (tasks then receive the object itself); in the pool, ``obj``."""
        if self.client is None:
            return obj
        return self.client.scatter(obj, broadcast=True, hash=False)

    def restart(self):
        """After a worker process of the pool died (BrokenProcessPool): a fresh pool.  On Dask the
        scheduler itself moves a dead worker's tasks to the others (no-op)."""
        if self._make_pool is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)
            self.executor = self._make_pool()

    def close(self):
        if self.client is None:
            self.executor.shutdown(wait=False, cancel_futures=True)
        else:  # closing the client releases (cancels) its tasks that are still queued
            self.executor.shutdown(wait=False)
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _one_numba_thread():
    # runs in each new pool process before numba is imported there: one thread per task
    os.environ["NUMBA_NUM_THREADS"] = "1"


@contextlib.contextmanager
def open_executor(scheduler=None, workers=2, *, one_thread=False, source="--scheduler"):
    """The `Farm` ``scheduler`` names (module docstring), closed on exit.

    workers : pool processes, or LocalCluster worker processes (ignored for a running cluster)
    one_thread : pool processes start with NUMBA_NUM_THREADS=1 (spawned, so numba starts
        fresh): for tasks that each keep a core busy, such as trainings.  LocalCluster workers
        always get it; workers of a cluster you started get what you gave them.
    """
    kind, target = parse_scheduler(scheduler, source)
    if kind == "pool":
        if one_thread:
            def make():
                return cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                              initializer=_one_numba_thread)
        else:
            def make():
                return cf.ProcessPoolExecutor(workers)
        farm = Farm(make(), "pool", workers, make_pool=make)
    else:
        farm = _open_dask(kind, target, workers, source, scheduler)
    try:
        yield farm
    finally:
        farm.close()


def _open_dask(kind, target, workers, source, value):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise InputError(source, value, "asks for a Dask scheduler but Dask is not installed", INSTALL) from None
    cluster = None
    try:
        if kind == "local":
            with _sigint_ignored():  # the workers inherit it: Ctrl-C stops the client, which closes them
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, env={"NUMBA_NUM_THREADS": "1"},
                                       silence_logs=logging.ERROR)
            client = Client(cluster)
        elif kind == "address":
            client = Client(target, timeout=CONNECT_TIMEOUT)
        else:
            client = Client(scheduler_file=target, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError) as e:
        if cluster is not None:
            cluster.close()
        raise InputError(source, value, f"no Dask scheduler answers ({e})",
                         "the address `dask scheduler` printed, with the scheduler running") from None
    if not client.nthreads():
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT * 6)
    threads = sum(client.nthreads().values())
    # pure=False: the same call twice is two tasks (a rerun is a rerun, never a cached result)
    return Farm(client.get_executor(pure=False), "dask", max(1, threads), client=client, cluster=cluster)


@contextlib.contextmanager
def _sigint_ignored():
    try:
        before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def map_chunks(farm, fn, job, chunks, keep):
    """Run ``fn(job, chunk)`` for every chunk on ``farm`` (or here, in order, when farm is None)
    and call ``keep(chunk, result)`` as each finishes.  ``job`` is sent once per worker
    (Farm.share).  On any error or Ctrl-C the chunks not started are cancelled."""
    if farm is None:
        for chunk in chunks:
            keep(chunk, fn(job, chunk))
        return
    shared = farm.share(job)
    futures = {farm.submit(fn, shared, c): c for c in chunks}
    try:
        for fut in cf.as_completed(futures):
            keep(futures[fut], fut.result())
    except BaseException:
        for fut in futures:
            fut.cancel()
        raise


def chunk_ranges(n, workers, most):
    """range(0, n) in pieces: about four per worker (so the last ones balance), at most ``most`` long."""
    size = max(1, min(most, -(-n // (4 * workers))))
    return [range(i, min(i + size, n)) for i in range(0, n, size)]
