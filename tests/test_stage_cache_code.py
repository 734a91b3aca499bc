"""The stage cache's keys follow the code: an edited or upgraded library recomputes stages."""

from __future__ import annotations

from pathlib import Path

import pytest


def _package(root: Path, body: str) -> Path:
    (root / "pkg" / "sub").mkdir(parents=True)
    (root / "pkg" / "__init__.py").write_text("")
    (root / "pkg" / "sub" / "stage.py").write_text(body)
    (root / "pkg" / "notes.txt").write_text("not code")
    return root / "pkg"


def test_source_fingerprint_changes_with_a_source_file_only(tmp_path: Path) -> None:
    from canopy_kit.core.cache import source_fingerprint

    a = _package(tmp_path / "a", "X = 1\n")
    b = _package(tmp_path / "b", "X = 1\n")
    c = _package(tmp_path / "c", "X = 2\n")
    assert source_fingerprint([a]) == source_fingerprint([b])  # where it lies does not count
    assert source_fingerprint([a]) != source_fingerprint([c])
    (b / "notes.txt").write_text("edited")
    assert source_fingerprint([a]) == source_fingerprint([b])  # only Python sources count
    (b / "sub" / "stage.py").rename(b / "sub" / "other.py")
    assert source_fingerprint([a]) != source_fingerprint([b])  # a moved module counts


def test_a_stage_key_changes_with_the_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """The same stage and settings under other code: another key, so a cached result of the
    older code is not taken (the pipeline's cache: canopy_kit.pipeline.compute)."""
    import canopy_kit.core.cache as cache

    before = cache.stage_key("segment", {"eps": 0.8})
    assert before == cache.stage_key("segment", {"eps": 0.8})
    monkeypatch.setattr(cache, "code_fingerprint", lambda: "edited library")
    assert cache.stage_key("segment", {"eps": 0.8}) != before
