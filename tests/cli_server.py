"""``canopy-kit`` commands run in forked children of a process that imported the library once.

A command's process spends seconds importing the library (scikit-learn and SciPy through the
estimators' base classes, numba, pandas) before it reads its first input: the bad-input
catalogue runs 85 commands, most of them ending in an ``error:`` line moments later. This
server imports what the commands import once, then for each request forks a child that runs
the console script's own entry point (``canopy_kit.cli.main``) with its standard output and
error in files, and reports the child's exit status. Each command still runs in a process of
its own with a fresh interpreter state from the fork; only the imports are shared. The
console script itself is run by tests/test_cli_foundation.py.

Protocol (one JSON object a line): request ``{"args": [...], "stdout": path, "stderr": path,
"timeout": s}`` on standard input, answer ``{"returncode": n}`` on standard output (a child
still running after ``timeout`` seconds is killed: a negative code, as from subprocess).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

#: What the commands import before their first check (measured with ``-X importtime``).
PRELOAD = (
    "canopy_kit.cli",
    "canopy_kit.cli.common",
    "canopy_kit.config.rig",
    "canopy_kit.io.pcap_drive",
    "canopy_kit.io.clouds",
    "canopy_kit.mapping.pipeline",
    "canopy_kit.pipeline",
    "canopy_kit.volume",
)


def _child(request: dict) -> int:
    """Run one command in this (forked) process; its exit status."""
    outputs = ((0, os.devnull, os.O_RDONLY), (1, request["stdout"], os.O_WRONLY))
    for fd, path, mode in (*outputs, (2, request["stderr"], os.O_WRONLY)):
        target = os.open(path, mode | (os.O_CREAT | os.O_TRUNC if fd else 0), 0o644)
        os.dup2(target, fd)  # the requests' pipe is no longer the child's standard input
        os.close(target)
    sys.argv = ["canopy-kit", *request["args"]]
    from canopy_kit.cli import main

    try:
        main()
        code = 0
    except SystemExit as exc:  # as the interpreter does at exit
        if exc.code is None:
            code = 0
        elif isinstance(exc.code, int):
            code = exc.code
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:
        import traceback

        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    return code


def serve() -> None:
    """Answer requests until standard input closes (single-threaded, so forking is safe)."""
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                code = _child(request)
            finally:
                os._exit(code)
        print(json.dumps({"returncode": _wait(pid, float(request["timeout"]))}), flush=True)


def _wait(pid: int, timeout: float) -> int:
    """The exit code of child ``pid``, killed after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
        time.sleep(0.02)


class CliServer:
    """One server process started with ``env`` added to this one's environment; ``run(args)``
    like ``subprocess.run(canopy-kit args)`` (one command at a time, so one server per
    thread for parallel commands)."""

    def __init__(self, workdir: Path, env: dict[str, str] | None = None) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._n = 0
        self._lock = threading.Lock()
        self.process = subprocess.Popen(
            [sys.executable, __file__],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {}), "PYTHONPATH": os.pathsep.join(sys.path)},
        )
        self._ready = False  # the imports run while the caller starts other servers

    def run(self, args: list[str], timeout: float = 600):
        """The command's ``subprocess.CompletedProcess`` (text output)."""
        with self._lock:
            if not self._ready:
                assert json.loads(self.process.stdout.readline()) == {"ready": True}
                self._ready = True
            self._n += 1
            out = self.workdir / f"{self._n}.out"
            err = self.workdir / f"{self._n}.err"
            request = {"args": args, "stdout": str(out), "stderr": str(err), "timeout": timeout}
            self.process.stdin.write(json.dumps(request) + "\n")
            self.process.stdin.flush()
            answer = json.loads(self.process.stdout.readline())
        return subprocess.CompletedProcess(
            ["canopy-kit", *args],
            answer["returncode"],
            out.read_text(errors="replace"),
            err.read_text(errors="replace"),
        )

    def close(self) -> None:
        """Stop the server (it exits when its standard input closes)."""
        self.process.stdin.close()
        self.process.wait(timeout=60)


if __name__ == "__main__":
    serve()
