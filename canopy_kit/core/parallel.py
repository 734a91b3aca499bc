"""Run jobs in forked worker processes with a shared progress count.

Fork, not spawn: a forked child starts from the parent's memory (the trajectory, the
config) without re-importing ``__main__``, so scripts and notebooks work unchanged. Any
exception in a child comes back to the parent and is raised there. Results come back in a
file on the memory-backed ``/dev/shm`` where it has room, else through a pipe.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import suppress
from typing import Any

from canopy_kit.errors import ProcessingError

Tick = Callable[[], None]


# A result is handed over in a file of this memory-backed folder when there is one with room
# (tmpfs: a copy at memory speed) instead of through the pipe: the map pass's partial map of
# 166 MB took 0.52 s through a pipe and 0.18 s through /dev/shm, on the run's critical path.
SHARED_MEMORY_DIR = "/dev/shm"
MIN_FREE_SHARED_MEMORY = 1 << 30


def _handover_dir() -> str | None:
    """A fresh private folder on the memory-backed file system for the workers' results, or
    None (results go through the pipes) when there is none or it has less than 1 GiB free."""
    import os
    import tempfile

    try:
        st = os.statvfs(SHARED_MEMORY_DIR)
        if st.f_bavail * st.f_frsize < MIN_FREE_SHARED_MEMORY:
            return None
        return tempfile.mkdtemp(prefix="canopy-kit-", dir=SHARED_MEMORY_DIR)
    except OSError:
        return None


def _send_result(conn, result: Any, handover: str | None, index: int) -> None:
    """Send ``("ok", result)``: pickled into a file of ``handover`` and its path sent, or
    through the pipe when there is no folder or the file could not be written (full)."""
    import os
    import pickle

    if handover is not None:
        path = os.path.join(handover, f"result-{index}.pickle")
        try:
            with open(path, "wb") as fh:
                pickle.dump(result, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except OSError:
            with suppress(OSError):
                os.unlink(path)
        else:
            conn.send(("file", path))
            return
    conn.send(("ok", result))


def _received(message: tuple[str, Any]) -> tuple[str, Any]:
    """A worker's message, with a result handed over in a file read back (and removed)."""
    import os
    import pickle

    status, value = message
    if status != "file":
        return message
    try:
        with open(value, "rb") as fh:
            return "ok", pickle.load(fh)
    finally:
        os.unlink(value)


def _child(
    function: Callable[[Any, Tick], Any], job: Any, counter, conn, handover: str | None, index: int
) -> None:
    def tick() -> None:
        with counter.get_lock():
            counter.value += 1

    try:
        _send_result(conn, function(job, tick), handover, index)
    except BaseException as exc:  # report any failure to the parent instead of dying silently
        conn.send(("error", exc))
    finally:
        conn.close()


def cpu_seconds() -> float:
    """CPU time of this process and of its finished child processes (the workers)."""
    import os

    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def worker_count(setting: int, most: int) -> int:
    """Processes to use: ``setting`` (0: one per core), at most ``most``, and 1 inside a
    daemonic process (a Dask or multiprocessing worker may not have children)."""
    import multiprocessing as mp
    import os

    if mp.current_process().daemon:
        return 1
    wanted = setting if setting > 0 else (os.cpu_count() or 1)
    return max(1, min(wanted, most))


def run_forked(
    function: Callable[[Any, Tick], Any],
    jobs: list[Any],
    label: str,
    total: int,
    progress: Callable[[str, float, float], None] | None = None,
    first_in_parent: bool = False,
) -> list[Any]:
    """``[function(job, tick) for job in jobs]``, one forked process per job.

    ``tick()`` advances the progress count reported as ``progress(label, count, total)``.
    With ``first_in_parent`` the first job runs in this process while the others run in
    theirs: one process fewer, and its result (a partial map of ~100 MB, say) never
    crosses a pipe.
    """
    import multiprocessing as mp
    import shutil

    ctx = mp.get_context("fork")
    counter = ctx.Value("i", 0)
    skip = 1 if first_in_parent else 0  # jobs[skip + i] runs in procs[i]
    forked = jobs[skip:]
    pipes = [ctx.Pipe(duplex=False) for _ in forked]
    handover = _handover_dir()  # removed with whatever a worker left in it, come what may
    procs = [
        ctx.Process(target=_child, args=(function, job, counter, send, handover, i), daemon=True)
        for i, (job, (_, send)) in enumerate(zip(forked, pipes))
    ]
    for proc in procs:
        proc.start()
    results: list = [None] * len(forked)
    finished = False
    try:
        own = []
        if first_in_parent:

            def tick() -> None:
                with counter.get_lock():
                    counter.value += 1
                if progress:
                    progress(label, counter.value, total)
                killed = [i for i, p in enumerate(procs) if p.exitcode not in (None, 0)]
                if killed:  # a worker killed (out of memory, a signal): no use finishing ours
                    raise ProcessingError(
                        f"{label}: worker {killed[0] + skip} ended without a result "
                        f"(exit code {procs[killed[0]].exitcode})"
                    )

            own = [("ok", function(jobs[0], tick))]
        while any(r is None for r in results):
            for i, (recv, _) in enumerate(pipes):
                if results[i] is None and recv.poll(0.2):
                    results[i] = _received(recv.recv())
            if progress:
                progress(label, counter.value, total)
            dead = [
                i
                for i, p in enumerate(procs)
                if results[i] is None and not p.is_alive() and not pipes[i][0].poll()
            ]
            if dead:
                raise ProcessingError(
                    f"{label}: worker {dead[0] + skip} ended without a result "
                    f"(exit code {procs[dead[0]].exitcode})"
                )
        finished = True
    finally:
        for proc in procs:
            if not finished:  # an error here: the others' results are not wanted
                proc.terminate()
            proc.join(timeout=5)
            if proc.is_alive():
                proc.terminate()
        if handover is not None:
            shutil.rmtree(handover, ignore_errors=True)
    for status, value in results:
        if status == "error":
            raise value
    return [value for _, value in own + results]


def run_jobs(
    function: Callable[[Any, Tick], Any],
    jobs: list[Any],
    label: str,
    total: int,
    progress: Callable[[str, float, float], None] | None = None,
    first_in_parent: bool = False,
) -> list[Any]:
    """:func:`run_forked`, or in this process when there is a single job."""
    if len(jobs) != 1:
        return run_forked(function, jobs, label, total, progress, first_in_parent)
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress:
            progress(label, done, total)

    return [function(jobs[0], tick)]
