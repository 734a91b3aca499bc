"""A stage cache keyed by a hash of each stage's inputs and settings.

Re-running after a parameter change recomputes only the stages whose key changed (and those
after them, whose keys include the upstream key). Every key includes a hash of the code that
computes the stages (:func:`code_fingerprint`): after an upgrade, or an edit of the library,
no stage comes from the cache of older code. Entries are pickles written atomically, so
an interrupted run never leaves a half-written entry; the next run resumes from the last
complete stage.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import pickle
import time
from collections.abc import Callable
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, TypeVar

from canopy_kit.core.atomic import atomic_path
from canopy_kit.core.parallel import cpu_seconds

T = TypeVar("T")
CACHE_VERSION = 4  # 2: segmentations keep a LAS class per point; 3: and their canopy band;
# 4: modules moved into packages (pickled classes name their module)


def fingerprint(path: str | Path) -> dict[str, Any]:
    """Identity of an input file or folder: resolved path, sizes and modification times."""
    p = Path(path).resolve()
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
        return {
            "path": str(p),
            "files": [
                (str(f.relative_to(p)), f.stat().st_size, f.stat().st_mtime_ns) for f in files
            ],
        }
    st = p.stat()
    return {"path": str(p), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _canonical(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        return _canonical(asdict(value))
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def source_fingerprint(roots: list[Path]) -> str:
    """Hash of the Python sources (paths relative to their root, and contents) under
    ``roots``."""
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:20]


@functools.cache
def code_fingerprint() -> str:
    """Hash of the code of the stages: the ``canopy_kit`` package and the ``ground_truth``
    package beside it (found without importing it)."""
    roots = [Path(__file__).resolve().parents[1]]
    spec = importlib.util.find_spec("ground_truth")
    if spec is not None and spec.origin is not None:
        roots.append(Path(spec.origin).resolve().parent)
    return source_fingerprint(roots)


def stage_key(stage: str, *parts: Any) -> str:
    """Hash of a stage name, everything its result depends on and the code that computes it."""
    key = [CACHE_VERSION, code_fingerprint(), stage, _canonical(list(parts))]
    text = json.dumps(key, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class StageCache:
    """Pickled stage results in ``root``, one file per (stage, key)."""

    def __init__(self, root: str | Path | None, enabled: bool = True) -> None:
        self.root = Path(root) if root is not None else None
        self.enabled = enabled and root is not None
        self.hits: list[str] = []
        self.misses: list[str] = []
        self.timings: dict[str, dict[str, float]] = {}

    def _path(self, stage: str, key: str) -> Path:
        assert self.root is not None
        return self.root / f"{stage}-{key}.pkl"

    def get_or_compute(self, stage: str, key: str, compute: Callable[[], T]) -> T:
        """The cached result of ``stage`` for ``key``, computing and storing it when absent."""
        if self.enabled:
            path = self._path(stage, key)
            if path.exists():
                try:
                    with path.open("rb") as fh:
                        value = pickle.load(fh)
                    self.hits.append(stage)
                    return value
                except Exception:  # stale or damaged entry (pickle raises many types): recompute
                    path.unlink(missing_ok=True)
        wall, cpu = time.perf_counter(), cpu_seconds()
        value = compute()
        self.timings[stage] = {"wall_s": time.perf_counter() - wall, "cpu_s": cpu_seconds() - cpu}
        self.misses.append(stage)
        if self.enabled:
            for old in self.root.glob(f"{stage}-*.pkl"):
                old.unlink(missing_ok=True)  # keep one entry per stage
            with atomic_path(self._path(stage, key)) as tmp, tmp.open("wb") as fh:
                pickle.dump(value, fh, protocol=pickle.HIGHEST_PROTOCOL)
        return value
