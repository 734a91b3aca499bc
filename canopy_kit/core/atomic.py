"""Atomic output: write to a temporary name in the target folder, then rename.

An interrupted run never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` on success.

    The temporary name keeps the final suffix (``suffix`` overrides it), so libraries
    that choose a format by extension (laspy, open3d) still work. On any exception,
    Ctrl-C (KeyboardInterrupt) included, the temporary file is removed: the final name
    holds the old file or the new one, never a part, and no temporary is left behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tail = ".tmp" + (suffix if suffix is not None else path.suffix)
    while True:
        tmp_path = path.parent / f".{path.name}.{secrets.token_hex(6)}{tail}"
        try:
            # 0o666 less the umask, as for any new file; O_EXCL: never another's file
            os.close(os.open(tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue  # a name taken by another writer: never remove that one
        except BaseException:
            # Interrupted (Ctrl-C) between the file's creation and the end of the call.
            with contextlib.suppress(FileNotFoundError):
                tmp_path.unlink()
            raise
        break
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write bytes to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text to ``path`` atomically and return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def json_default(value: Any) -> Any:
    """``json.dumps`` fallback: numpy scalars and arrays as Python values, anything else as text."""
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def to_json(data: Any, indent: int | None = 2) -> str:
    """``data`` as JSON text with a final newline (numpy values and paths converted)."""
    return json.dumps(data, indent=indent, default=json_default) + "\n"


def atomic_write_json(path: str | Path, data: Any, indent: int | None = 2) -> Path:
    """Write ``data`` as JSON to ``path`` atomically and return the path."""
    return atomic_write_text(path, to_json(data, indent))
