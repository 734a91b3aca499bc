"""Damage real files the way the field does: cut them short, overwrite bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def storage_file(bag: Path) -> Path:
    """The file holding a bag's messages (ROS1: the bag; ROS2: the .db3/.mcap in the folder)."""
    if bag.is_file():
        return bag
    return next(p for p in sorted(bag.iterdir()) if p.suffix in (".db3", ".mcap"))


def cut(path: Path, offset: int) -> Path:
    """Keep the first ``offset`` bytes of ``path`` (power lost while recording)."""
    data = path.read_bytes()
    path.write_bytes(data[:offset])
    return path


def cut_bag(bag: Path, fraction: float) -> int:
    """Cut a bag's storage file at ``fraction`` of its length; the offset used."""
    storage = storage_file(bag)
    offset = int(storage.stat().st_size * fraction)
    cut(storage, offset)
    return offset


def overwrite(path: Path, offsets: np.ndarray, rng: np.random.Generator, length: int = 16) -> Path:
    """Overwrite ``length`` random bytes at each offset (a bad sector, a flaky card)."""
    data = bytearray(path.read_bytes())
    for offset in offsets:
        end = min(int(offset) + length, len(data))
        data[int(offset) : end] = rng.integers(0, 256, end - int(offset), dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    return path


def random_offsets(size: int, n: int, rng: np.random.Generator, start: int = 0) -> np.ndarray:
    """``n`` sorted distinct byte offsets in ``[start, size)``."""
    return np.sort(rng.choice(np.arange(start, size), size=min(n, size - start), replace=False))
