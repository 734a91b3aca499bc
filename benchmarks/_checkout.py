"""Run a benchmark's own child mode in a fresh process, with another checkout's code.

Shared by the benchmarks that compare this code with another checkout (``--against DIR``,
e.g. ``git worktree add /tmp/old <rev>``): the child is this same script, with ``code``'s
``canopy_kit`` first on the path (before the editable install), and prints its result as
JSON on its last line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def child_json(argv: list[str], code: Path | None = None, what: str = "child") -> dict:
    """``python *argv`` in a fresh process; its last stdout line as JSON, with ``load``: the
    load average around the run."""
    env = None
    if code is not None:
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(code), os.environ.get("PYTHONPATH")])),
        }
    load = os.getloadavg()[0]
    out = subprocess.run(
        [sys.executable, *argv], capture_output=True, text=True, check=False, env=env
    )
    if out.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{out.stderr[-3000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["load"] = 0.5 * (load + os.getloadavg()[0])
    return result
