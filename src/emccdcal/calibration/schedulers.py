"""Where the tiles run: here on threads, in local processes, or as tasks on a Dask cluster (a scheduler reached, or refused in one line, before any work), each tile kept as it finishes."""

from __future__ import annotations

import contextlib
import functools
import os

from .._util import install_hint, one_line
from .._util import progress as progress_bar
from ..errors import OptionError
from ..runstore import RunInterrupted
from .tiles import run_tile


def _return_freed_memory() -> None:
    """Give the memory a finished tile freed back to the system (glibc only).

    A tile's large temporary arrays are freed into the allocator's per-thread arenas;
    without this the resident memory of a long run creeps up with the number of tiles.
    """
    try:
        _libc().malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to do
        pass


@functools.lru_cache(maxsize=1)
def _libc():
    import ctypes
    import ctypes.util

    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def _execute(jobs, scheduler, progress, workers=1):
    """Run tile jobs here, in order, in ``workers`` local processes or on a Dask cluster as
    they finish: (job, arrays). ``progress(n)`` is told of every n pixels done (as they
    are fitted, here)."""
    if scheduler is None:
        for job in jobs:
            arrays = run_tile(job, progress)
            _return_freed_memory()
            yield job, arrays
        return
    if isinstance(scheduler, str) and scheduler == LOCAL_PROCESSES:
        yield from _in_processes(jobs, progress, workers)
        return
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise OptionError(
            "running on a Dask cluster needs the 'dask' extra: " + install_hint("dask")
        ) from None
    if isinstance(scheduler, Client):
        client = scheduler
    else:
        # Reached before a client is made: a client that fails half-made lingers, and
        # closing it at exit waits a minute. Ours is never the process's default either.
        _reach_or_refuse(scheduler)
        try:
            client = Client(scheduler, timeout="30s", set_as_default=False)
        except (ValueError, TypeError, OSError) as exc:  # gone since it was reached
            raise OptionError(
                f"scheduler {scheduler!r}: no Dask scheduler reached ({one_line(exc)})"
            ) from None
    try:
        futures = {client.submit(run_tile, job, pure=False): job for job in jobs}
        # as_completed waits on the loop of the client it is given, else on the process's
        # default client: ours is not one (a caller's may not exist)
        yield from _as_finished(
            futures, functools.partial(as_completed, loop=client.loop), progress
        )
    finally:
        if client is not scheduler:
            client.close()


def _as_finished(futures, as_completed, progress):
    """(job, arrays) of ``futures`` ({future: job}) as each finishes (``as_completed``
    of Dask or of concurrent.futures); ``progress`` told of each one's pixels."""
    for future in as_completed(futures):
        job = futures[future]
        arrays = future.result()
        progress(job.n_pixels)
        yield job, arrays


#: ``scheduler`` that runs the tiles in local processes (one tile each, one thread each).
LOCAL_PROCESSES = "processes"
#: ``scheduler`` that runs the tiles here, on threads, whatever the sensor.
LOCAL_THREADS = "threads"
#: The smallest sensor (pixels) whose tiles a run sends to local processes by itself:
#: below it, starting the processes (each imports the package) costs more than the
#: threads lose (docs/benchmarks.md, "Threads and processes").
PROCESSES_FROM_PIXELS = 4096


def choose_scheduler(scheduler, n_pixels, n_tiles, workers, device):
    """The scheduler a run uses: the caller's, with :data:`LOCAL_THREADS` as None (here,
    on threads), or where the caller gave none, :func:`default_scheduler`'s."""
    if scheduler is None:
        return default_scheduler(n_pixels, n_tiles, workers, device)
    if isinstance(scheduler, str) and scheduler == LOCAL_THREADS:
        return None
    return scheduler


def default_scheduler(n_pixels, n_tiles, workers, device):
    """Where a run's tiles go when the caller does not say: local processes
    (:data:`LOCAL_PROCESSES`) where there are at least two tiles for each of two or more
    workers on a sensor of :data:`PROCESSES_FROM_PIXELS` pixels or more, on the CPU;
    else threads here (None). Threads hold the interpreter's lock in the fit's Python
    steps: two reached 0.65 of two cores where two processes reached 0.90. A GPU is
    one device (its blocks are large already), and a daemonic process (a pool's
    worker) may not start processes of its own."""
    import multiprocessing

    if (
        device not in (None, "cpu")
        or workers < 2
        or n_tiles < 2 * workers
        or n_pixels < PROCESSES_FROM_PIXELS
        or multiprocessing.current_process().daemon
    ):
        return None
    return LOCAL_PROCESSES


def _in_processes(jobs, progress, workers):
    """The tiles in ``workers`` fresh processes (spawned: nothing inherited but the jobs),
    as they finish. Threads share one interpreter, whose lock the fit's Python steps
    hold; processes do not, so a sensor's tiles use every core.

    The workers leave Ctrl-C to this process, which ends them at once (a pool that
    waited for their tiles took a minute to stop), and each ends itself when this
    process dies (a SIGKILL here left them running)."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    with _without_main_script():
        pool = context.Pool(workers, initializer=_worker_start, initargs=(os.getpid(),))
    try:
        for index, arrays in pool.imap_unordered(_indexed_tile, enumerate(jobs)):
            progress(jobs[index].n_pixels)
            yield jobs[index], arrays
        pool.close()
    finally:
        pool.terminate()  # a no-op once closed and done; else the tiles still running go
        pool.join()


@contextlib.contextmanager
def _without_main_script():
    """While the workers are spawned, the caller's script is not theirs to run.

    A spawned process imports the parent's ``__main__`` script before its task; a
    user's script that calls :func:`~emccdcal.calibrate` at its top level (no
    ``if __name__ == "__main__":`` guard, as a notebook's exported cells have none)
    would start the whole calibration again in every worker. The workers need only
    emccdcal, so a bare ``__main__`` stands in for the script while they start."""
    import sys
    import types

    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is None:
            del sys.modules["__main__"]
        else:
            sys.modules["__main__"] = main


def _indexed_tile(item):
    """``(index, run_tile(job))`` of ``(index, job)``: which tile finished, in a worker."""
    index, job = item
    return index, run_tile(job)


def _worker_start(parent: int) -> None:
    """A tile worker's start: Ctrl-C is its parent's to handle (it ends the workers), and
    a thread ends the worker within half a second of its parent's death."""
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch():
        import time

        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="emccdcal-parent-watch", daemon=True).start()


def _reach_or_refuse(scheduler) -> None:
    """One line (an OptionError) unless a Dask scheduler answers at ``scheduler`` (and
    the ``dask`` extra is installed), where it is an address: :func:`_reach`."""
    if not isinstance(scheduler, str) or scheduler in (LOCAL_PROCESSES, LOCAL_THREADS):
        return  # here, local processes or a client of the caller's
    try:
        _reach(scheduler)
    except ImportError:
        raise OptionError(
            "running on a Dask cluster needs the 'dask' extra: " + install_hint("dask")
        ) from None
    except (ValueError, TypeError, OSError) as exc:  # not an address, or no one there
        raise OptionError(
            f"scheduler {scheduler!r}: no Dask scheduler reached "
            f"({one_line(exc)}); give its address, tcp://HOST:PORT"
        ) from None


#: Seconds to wait for a scheduler's address to accept a connection, and for its first
#: bytes: a Dask scheduler sends its handshake at once.
_REACH_SECONDS = 5.0


def _reach(address) -> None:
    """Raise ValueError or OSError unless a Dask scheduler answers at ``address`` (within
    seconds): a TCP address must accept a connection and send a Dask handshake's first
    frame (a listener of anything else is refused here, where Dask would read its bytes
    as a length of exabytes); a WebSocket or TLS one must accept a connection; other
    schemes (``inproc://``, of one process; ``ucx://``) cannot be reached from here."""
    import socket
    import struct

    from distributed.comm import parse_address, parse_host_port

    scheme, location = parse_address(str(address))
    if scheme not in ("tcp", "tls", "ws", "wss"):
        raise ValueError(f"a {scheme}:// address is not one this command can reach")
    host, port = parse_host_port(location)
    with socket.create_connection((host, port), timeout=_REACH_SECONDS) as sock:
        if scheme != "tcp":
            return
        head = b""
        try:
            while len(head) < 8:
                more = sock.recv(8 - len(head))
                if not more:
                    break
                head += more
        except TimeoutError:
            pass
    if len(head) < 8:
        raise ValueError(f"what listens there sent no Dask handshake in {_REACH_SECONDS:g} s")
    (size,) = struct.unpack("<Q", head)
    if not 0 < size < 2**20:  # the handshake is a few hundred bytes
        raise ValueError("what listens there is not a Dask scheduler (not its handshake)")


def _run_tiles(jobs, store, scheduler, progress, method, workers=1):
    """Every tile's arrays, in order: those kept by ``store`` and the computed ones."""
    done = {}
    if store is not None:
        wanted = {job.key for job in jobs}
        done = {key: store.load_tile(key) for key in store.tiles() if key in wanted}
    total = sum(job.n_pixels for job in jobs)
    bar = progress_bar(enabled=progress, desc=f"calibrating ({method})", unit="px", total=total)
    bar.update(sum(job.n_pixels for job in jobs if job.key in done))
    try:
        for job, arrays in _execute(
            [j for j in jobs if j.key not in done], scheduler, bar.update, workers
        ):
            if store is not None:
                store.save_tile(job.key, arrays)
            done[job.key] = arrays
    except KeyboardInterrupt:
        if store is None:
            raise
        raise RunInterrupted(
            f"interrupted: {len(store.tiles())} of {len(jobs)} tiles kept in {store.out}; "
            "run the same command with --resume to continue"
        ) from None
    finally:
        bar.close()
    return [done[job.key] for job in jobs]


#: Register lengths ``stages="auto"`` tries: steps of √2 from 128 to 4096 stages.
