"""Manifests a hostile or careless user writes: ids that are paths, shared folders, encodings.

No manifest may make ``batch`` write outside ``--out``: every case is refused before a
session runs (the out folder is not even created), and the CLI says so in one line, exit 2.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from pathlib import Path

import pytest
from test_cli_foundation import run_cli

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.pipeline.batch import SessionSpec, load_manifest, run_batch, session_folder

HEADER = "id,bag,orchard,date\n"


def _toml(tmp_path: Path, *sessions: str) -> Path:
    path = tmp_path / "sessions.toml"
    path.write_text(
        "".join(f'[[session]]\nbag = "b.mcap"\ndate = 2025-04-01\n{s}\n' for s in sessions)
    )
    return path


@pytest.mark.parametrize(
    "session_id",
    [
        "/tmp/elsewhere",
        "../../x",
        "a/b",
        "..",
        ".",
        "a\\b",
        "line\nbreak",
        "tab\tid",
        "",
        ".hidden",
        "x" * 129,
    ],
)
def test_an_id_that_is_not_a_folder_name_is_refused(tmp_path, session_id):
    manifest = _toml(tmp_path, f'orchard = "o"\nid = {json.dumps(session_id)}')  # a TOML string
    with pytest.raises(ConfigError, match="cannot name a folder"):
        load_manifest(manifest)


def test_an_orchard_name_with_separators_gives_a_safe_default_id(tmp_path):
    manifest = _toml(tmp_path, 'orchard = "../../North block/7"', 'orchard = "/abs"')
    ids = [s.session_id for s in load_manifest(manifest)]
    assert ids == ["North-block-7-2025-04-01", "abs-2025-04-01"]
    for sid in ids:
        assert (
            session_folder(tmp_path / "out", sid).parent
            == (tmp_path / "out" / "sessions").resolve()
        )


def test_two_ids_naming_one_folder_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="'same' appears twice"):
        load_manifest(_toml(tmp_path, 'orchard = "o"\nid = "same"', 'orchard = "p"\nid = "same"'))
    with pytest.raises(ConfigError, match="'Same' names the folder of 'same'"):
        load_manifest(_toml(tmp_path, 'orchard = "o"\nid = "same"', 'orchard = "p"\nid = "Same"'))
    # the default ids of two orchards whose names differ only in separators
    with pytest.raises(ConfigError, match="appears twice"):
        load_manifest(_toml(tmp_path, 'orchard = "a/b"', 'orchard = "a b"'))


def test_run_batch_refuses_specs_built_in_code_before_writing(tmp_path):
    """Specs that never went through a manifest are checked too, before ``out`` exists."""
    spec = SessionSpec("../escape", tmp_path / "b.mcap", "o", dt.date(2025, 4, 1))
    with pytest.raises(ConfigError, match="cannot name a folder"):
        run_batch([spec], tmp_path / "out")
    twins = [SessionSpec(sid, tmp_path / "b.mcap", "o", dt.date(2025, 4, 1)) for sid in ("a", "A")]
    with pytest.raises(ConfigError, match="names the folder of 'a'"):
        run_batch(twins, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_link_planted_under_sessions_is_not_followed(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "out" / "sessions").mkdir(parents=True)
    os.symlink(outside, tmp_path / "out" / "sessions" / "s1")
    with pytest.raises(InputError, match="resolves outside"):
        session_folder(tmp_path / "out", "s1")


def test_csv_manifests_from_spreadsheets(tmp_path):
    """Excel's UTF-8 with BOM and UTF-16 read; extra cells and bad bytes name the file and row."""
    rows = "s1,b.mcap,o,2025-04-01\n"
    for name, data in {
        "bom.csv": b"\xef\xbb\xbf" + (HEADER + rows).encode(),
        "utf16.csv": (HEADER + rows).encode("utf-16"),
    }.items():
        (tmp_path / name).write_bytes(data)
        [spec] = load_manifest(tmp_path / name)
        assert (spec.session_id, spec.orchard, spec.date) == ("s1", "o", dt.date(2025, 4, 1))
    (tmp_path / "extra.csv").write_text(HEADER + rows + "s2,b.mcap,o,2025-05-01,oops\n")
    with pytest.raises(
        ConfigError, match=r"extra.csv: session 2 \(line 3\) has 5 cells, the header 4"
    ):
        load_manifest(tmp_path / "extra.csv")
    (tmp_path / "latin.csv").write_bytes((HEADER + "s1,b.mcap,Höhe,2025-04-01\n").encode("latin-1"))
    with pytest.raises(
        InputError, match=r"latin.csv: not UTF-8 text \(line 2, byte 31: b'\\xf6'\)"
    ):
        load_manifest(tmp_path / "latin.csv")


def test_cli_refuses_an_escaping_manifest_in_one_line(tmp_path):
    target = tmp_path / "victim"
    target.mkdir()
    (target / "trees.csv").write_text("keep me\n")
    manifest = _toml(tmp_path, f'orchard = "o"\nid = "{target}"')
    result = run_cli("batch", str(manifest), "--out", str(tmp_path / "out"))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("error: ") and "sessions.toml" in lines[0], lines
    assert (target / "trees.csv").read_text() == "keep me\n"
    assert not (tmp_path / "out").exists()


def test_fuzzed_ids_and_manifest_bytes_give_a_folder_inside_out_or_a_named_error(tmp_path):
    """Seeded fuzz: ids drawn from separators, dots, control and non-ASCII characters; CSV
    manifests of random bytes and random cuts of a good one. Each gives a session folder that
    is a child of OUT/sessions, or a ConfigError/InputError naming the manifest."""
    import random

    rng = random.Random(27)
    alphabet = list("aZ09._-/\\:~ $*?\"'") + ["..", "\x00", "\x1b", "\n", "é", "\u202e", "…"]
    sessions = (tmp_path / "out" / "sessions").resolve()
    for k in range(300):
        sid = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 12)))
        manifest = _toml(
            tmp_path,
            f"orchard = {json.dumps(sid)}\nid = {json.dumps(sid)}"
            if k % 2
            else f"orchard = {json.dumps(sid)}",
        )
        try:
            specs = load_manifest(manifest)
        except InputError as exc:  # ConfigError is an InputError
            assert str(manifest) in str(exc)
            continue
        folder = session_folder(tmp_path / "out", specs[0].session_id)
        assert folder.parent == sessions, (sid, folder)
    good = (HEADER + "s1,b.mcap,o,2025-04-01\ns2,b.mcap,o,2025-05-01\n").encode()
    blobs = [bytes(rng.randrange(256) for _ in range(rng.randint(1, 200))) for _ in range(100)]
    blobs += [good[:cut] for cut in range(len(good))]
    for i, blob in enumerate(blobs):
        path = tmp_path / f"m{i}.csv"
        path.write_bytes(blob)
        try:
            for spec in load_manifest(path):
                assert session_folder(tmp_path / "out", spec.session_id).parent == sessions
        except InputError as exc:
            assert str(path) in str(exc), exc
