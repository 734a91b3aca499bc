"""A seeded fuzz of the point-cloud file readers (LAS, LAZ, PLY, PCD) and ``canopy-kit info``.

Small valid files get every header field set to 0, its maximum and a random value, are cut
at many byte positions (inside the header, inside VLRs, at and inside record boundaries) and
get random bytes changed (tests/bad_inputs/fuzz.py). Each damaged file is read by info's
``describe_path`` and by ``read_cloud`` (what the pipeline and the CLI read with) in a worker
process limited to 1 GiB of address space and 10 s a case, one worker per format family;
a few cases also go through the real ``canopy-kit info`` command under the same limits.

The property: an InputError naming the file in one line (exit 2 and one ``error:`` line for
the command), or a result whose bounds are finite; and a file that lost bytes never gives a
result without a warning.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bad_inputs import fuzz
from bad_inputs.clouds import grid_points, las_bytes, pcd_bytes, ply_bytes
from test_cli_foundation import cli_command

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(TESTS)]), "COLUMNS": "400"}


def _limits() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (fuzz.MEMORY_LIMIT, fuzz.MEMORY_LIMIT))


def _run_worker(cases: list[fuzz.Case], folder: Path) -> dict[str, dict]:
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, case in enumerate(cases):
        name = f"{i:04d}{case.suffix}"
        (folder / name).write_bytes(case.data)
        entries.append({"id": case.id, "file": name})
    (folder / "cases.json").write_text(json.dumps(entries))
    proc = subprocess.run(
        [sys.executable, "-m", "bad_inputs.fuzz", str(folder)],
        cwd=TESTS,
        env=ENV,
        capture_output=True,
        text=True,
        check=False,
        timeout=30 + 2 * len(cases),
    )
    results = {r["id"]: r for r in map(json.loads, proc.stdout.splitlines())}
    done = len(results)
    assert proc.returncode == 0 and done == len(cases), (
        f"worker exit {proc.returncode} after {done} of {len(cases)} cases (next: "
        f"{cases[done].id if done < len(cases) else '-'}): {proc.stderr[-2000:]}"
    )
    return results


def _violations(case: fuzz.Case, result: dict, path: str) -> list[str]:
    bad = []
    if result["seconds"] > fuzz.CASE_SECONDS:
        bad.append(f"took {result['seconds']:.1f} s")
    for step in ("describe", "read"):
        got = result[step]
        if got["outcome"] == "other":
            bad.append(f"{step}: {got['message']}")
        elif got["outcome"] == "input_error":
            if "\n" in got["message"] or path not in got["message"]:
                bad.append(f"{step}: message not one line naming the file: {got['message']!r}")
        else:
            if not got["finite"]:
                bad.append(f"{step}: non-finite bounds")
            if case.cut and not got["warnings"]:
                bad.append(f"{step}: a cut file read without a warning")
    return bad


def _check(cases: list[fuzz.Case], tmp_path: Path) -> dict[str, dict]:
    results = _run_worker(cases, tmp_path / "cases")
    failures = []
    for i, case in enumerate(cases):
        path = str(tmp_path / "cases" / f"{i:04d}{case.suffix}")
        failures += [f"{case.id}: {v}" for v in _violations(case, results[case.id], path)]
    assert not failures, f"{len(failures)} of {len(cases)} cases:\n" + "\n".join(failures[:40])
    return results


def _kinds(results: dict[str, dict]) -> dict[str, int]:
    """How many cases read (``ok``) and how many were refused (``input_error``)."""
    out: dict[str, int] = {}
    for r in results.values():
        out[r["read"]["outcome"]] = out.get(r["read"]["outcome"], 0) + 1
    return out


def test_fuzz_las(tmp_path: Path) -> None:
    cases = fuzz.las_cases(np.random.default_rng(20))
    results = _check(cases, tmp_path)
    kinds = _kinds(results)
    assert kinds.get("ok", 0) > 30 and kinds.get("input_error", 0) > 60, kinds  # not vacuous
    assert max(r["peak_kib"] for r in results.values()) < fuzz.MEMORY_LIMIT // 1024


def test_fuzz_laz(tmp_path: Path) -> None:
    pytest.importorskip("lazrs")
    cases = fuzz.laz_cases(np.random.default_rng(21))
    kinds = _kinds(_check(cases, tmp_path))
    assert kinds.get("ok", 0) > 5 and kinds.get("input_error", 0) > 30, kinds


def test_fuzz_ply_pcd(tmp_path: Path) -> None:
    cases = fuzz.ply_pcd_cases(np.random.default_rng(22))
    kinds = _kinds(_check(cases, tmp_path))
    assert kinds.get("ok", 0) > 50 and kinds.get("input_error", 0) > 50, kinds


# -- through the command a user runs ------------------------------------------------------------


def _cli_files(root: Path) -> list[tuple[str, Path, bool]]:
    """(case, file, cut) for the command-line cases: the findings of the hostile-user report."""
    rng = np.random.default_rng(23)
    ints = grid_points(2000)
    las = las_bytes(ints, offset=(300000.0, 4100000.0, 50.0))
    files = {
        "las-valid": (las, False),
        "las-vlr-bomb": (b"LASF" + rng.integers(0, 256, 3000, dtype=np.uint8).tobytes(), False),
        "las-count-1e8": (las_bytes(ints, point_count=100_000_000), False),
        "las-record-65535": (las_bytes(ints, record_length=65535), False),
        "las-scale-1e-300": (las_bytes(ints, scale=1e-300), False),
        "las-cut-at-record": (las[: 227 + 1234 * 20], True),
        "las-zero-header-bounds": (las_bytes(ints, header_bounds=((0, 0, 0), (0, 0, 0))), False),
        "ply-face-before-vertex": (
            ply_bytes(
                ints * 0.01,
                before=(
                    ("face", 500, "property list uchar int vertex_indices", b"\x03" + b"\0" * 12),
                ),
            ),
            False,
        ),
        "ply-valid-ascii": (ply_bytes(ints * 0.01, "ascii"), False),
        "pcd-compressed-0-bytes": (
            pcd_bytes(ints * 0.01, "binary_compressed", sizes=(0, 32000)),
            False,
        ),
        "pcd-binary-cut": (pcd_bytes(ints * 0.01, "binary")[:-100], True),
    }
    out = []
    for name, (data, cut) in files.items():
        suffix = "." + name.split("-")[0]
        path = root / f"{name}{suffix}"
        path.write_bytes(data)
        out.append((name, path, cut))
    return out


def test_info_command_on_hostile_files(tmp_path: Path) -> None:
    failures = []
    for name, path, cut in _cli_files(tmp_path):
        try:
            proc = subprocess.run(
                [*cli_command(), "info", "--json", str(path)],
                env=ENV,
                capture_output=True,
                text=True,
                timeout=fuzz.CASE_SECONDS,
                preexec_fn=_limits,
                check=False,
            )
        except subprocess.TimeoutExpired:
            failures.append(f"{name}: over {fuzz.CASE_SECONDS} s")
            continue
        lines = proc.stderr.strip().splitlines()
        if proc.returncode == 2:
            if len(lines) != 1 or not lines[0].startswith("error: ") or str(path) not in lines[0]:
                failures.append(f"{name}: stderr {proc.stderr!r}")
            continue
        if proc.returncode != 0 or lines:
            failures.append(f"{name}: exit {proc.returncode}, stderr {proc.stderr[-500:]!r}")
            continue
        facts = json.loads(proc.stdout)
        if not np.isfinite(facts["bounds"]["min"] + facts["bounds"]["max"]).all():
            failures.append(f"{name}: bounds {facts['bounds']}")
        if cut and not facts["warnings"]:
            failures.append(f"{name}: cut file without a warning")
    assert not failures, "\n".join(failures)


def test_info_plain_output_shows_true_bounds_and_warnings(tmp_path: Path) -> None:
    cases = {name: path for name, path, _ in _cli_files(tmp_path)}
    proc = subprocess.run(
        [*cli_command(), "info", str(cases["las-zero-header-bounds"])],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lo = grid_points(2000).min(axis=0) * 0.01
    assert f"{lo[0]:.3f}" in proc.stdout and "warning: " in proc.stdout
    assert "disagree with the points'" in proc.stdout
