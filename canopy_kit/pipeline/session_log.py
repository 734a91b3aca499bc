"""A batch session's trail on disk, so that a worker that dies still says where and why.

While a session runs, ``out/sessions/<id>/worker.log`` holds the batch's token, each
pipeline stage as it starts and, should the process die of a signal in compiled code
(SIGSEGV, SIGABRT from a C++ assertion, SIGFPE, SIGBUS, SIGILL), Python's fault handler
report and whatever the compiled code wrote to stderr. The client reads it when Dask
reports the task lost (measured: a C++ assertion on a NaN gyro sample killed four workers
in turn, and the batch said only ``KilledWorker``). A session that crashed so is not run
again in the same batch: the same input crashes the same code. The file is removed when
the session ends without a crash.
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
from collections.abc import Callable
from pathlib import Path

LOG_NAME = "worker.log"
SIGNALS = {
    "Segmentation fault": "SIGSEGV",
    "Aborted": "SIGABRT",
    "Floating point exception": "SIGFPE",
    "Bus error": "SIGBUS",
    "Illegal instruction": "SIGILL",
}
Progress = Callable[[str, float, float], None]


class SessionTrail:
    """Writes the trail of one session run (use as a context manager around the run)."""

    def __init__(self, folder: Path, token: str, own_process: bool = False) -> None:
        """``own_process``: the session has the process to itself (a Dask worker process of
        one thread), so the fault handler and stderr may point at the trail meanwhile."""
        self.path = Path(folder) / LOG_NAME
        self.token = token
        self.own_process = own_process
        self.stage = ""
        self._fh = None
        self._saved_stderr: int | None = None
        self._handler_was_on = False

    def __enter__(self) -> SessionTrail:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("w", buffering=1)
        self._fh.write(f"batch {self.token}\n")
        if self.own_process:
            self._handler_was_on = faulthandler.is_enabled()
            faulthandler.enable(self._fh, all_threads=False)
            self._saved_stderr = os.dup(2)  # a C++ assertion writes its reason there, then aborts
            os.dup2(self._fh.fileno(), 2)
        return self

    def progress(self, label: str, *_: float) -> None:
        """A pipeline progress callback: each new stage label goes into the trail."""
        if label != self.stage and self._fh is not None:
            self.stage = label
            self._fh.write(f"stage {label}\n")

    def __exit__(self, *exc: object) -> None:
        if self.own_process:
            faulthandler.disable()
            if self._handler_was_on:
                faulthandler.enable()
        if self._saved_stderr is not None:
            os.dup2(self._saved_stderr, 2)
            os.close(self._saved_stderr)
        if self._fh is not None:
            self._fh.close()
        with contextlib.suppress(OSError):
            self.path.unlink()


def read_trail(folder: Path, token: str) -> dict[str, str] | None:
    """What the trail of this batch (``token``) says: ``stage``, ``signal``, ``cause``; None
    when there is none (the session never started, or ended without a crash)."""
    path = Path(folder) / LOG_NAME
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    if not lines or lines[0] != f"batch {token}":
        return None
    out = {"stage": "", "signal": "", "cause": ""}
    for line in lines[1:]:
        if line.startswith("stage "):
            out["stage"] = line[6:]
        elif line.startswith("Fatal Python error: "):
            kind = line.removeprefix("Fatal Python error: ").strip()
            out["signal"] = SIGNALS.get(kind, kind)
        elif not out["cause"] and _says_why(line):
            out["cause"] = line.strip()[:300]
    return out


def _says_why(line: str) -> bool:
    text = line.strip()
    return (
        bool(text)
        and not text.startswith(
            ("File ", "Current thread", "Thread ", "Extension modules", "Stack (most recent")
        )
        and ("failed" in text.lower() or "error" in text.lower() or "assert" in text.lower())
    )


def crash_message(trail: dict[str, str] | None) -> str:
    """One line on how the worker died, from :func:`read_trail`."""
    if trail is None:
        return "the worker process died before the session started (or left no trail)"
    where = f" during stage {trail['stage']!r}" if trail["stage"] else " before its first stage"
    if trail["signal"]:
        cause = f": {trail['cause']}" if trail["cause"] else ""
        return (
            f"the worker process died of {trail['signal']}{where} (a crash in compiled code{cause})"
        )
    return (
        f"the worker process died{where} without a fault report (killed: SIGKILL, e.g. out of "
        "memory, or a lost machine)"
    )


def own_worker_process() -> bool:
    """Is this a worker process of its own with one thread (not the client's process)?"""
    import multiprocessing as mp

    if mp.current_process().name == "MainProcess":
        return False
    try:
        from distributed import get_worker

        return get_worker().state.nthreads == 1
    except (ImportError, ValueError, AttributeError):
        return False
