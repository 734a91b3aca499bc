"""Run jobs in forked worker processes with a shared progress count.

Fork, not spawn: a forked child starts from the parent's memory (the trajectory, the
config) without re-importing ``__main__``, so scripts and notebooks work unchanged. Any
exception in a child comes back to the parent and is raised there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from canopy_kit.errors import ProcessingError

Tick = Callable[[], None]


def _child(function: Callable[[Any, Tick], Any], job: Any, counter, conn) -> None:
    def tick() -> None:
        with counter.get_lock():
            counter.value += 1

    try:
        conn.send(("ok", function(job, tick)))
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

    ctx = mp.get_context("fork")
    counter = ctx.Value("i", 0)
    skip = 1 if first_in_parent else 0  # jobs[skip + i] runs in procs[i]
    forked = jobs[skip:]
    pipes = [ctx.Pipe(duplex=False) for _ in forked]
    procs = [
        ctx.Process(target=_child, args=(function, job, counter, send), daemon=True)
        for job, (_, send) in zip(forked, pipes)
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
                    results[i] = recv.recv()
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
