"""Forked workers (``canopy_kit.core.parallel``): results, errors and progress come back to the parent."""

from __future__ import annotations

import os

import pytest

from canopy_kit.core.parallel import run_forked
from canopy_kit.errors import InputError, ProcessingError


def _square_pid(x: int, tick) -> tuple[int, int]:
    tick()
    return x * x, os.getpid()


def _fail_or_die(x: int, tick) -> None:
    if x == 0:
        raise InputError("scan 17: no x field")
    os._exit(3)


def test_run_forked_returns_results_in_job_order_from_other_processes() -> None:
    seen = []
    out = run_forked(
        _square_pid, [3, 1, 2], "squares", 3, lambda label, n, total: seen.append((label, n, total))
    )
    assert [r[0] for r in out] == [9, 1, 4]
    assert os.getpid() not in {r[1] for r in out}
    assert seen[-1] == ("squares", 3, 3)


def test_a_worker_error_or_death_reaches_the_parent() -> None:
    with pytest.raises(InputError, match="scan 17: no x field"):
        run_forked(_fail_or_die, [0], "map", 1)
    with pytest.raises(ProcessingError, match="map: worker 0 ended without a result"):
        run_forked(_fail_or_die, [1], "map", 1)


def _square_or_fail_in_parent(job: tuple[int, int], tick) -> tuple[int, int]:
    x, parent = job
    if x < 0 and os.getpid() == parent:
        raise InputError("stretch 0: scan 5 has no points")
    tick()
    return x * x, os.getpid()


def test_the_first_job_can_run_in_the_parent_while_the_others_fork() -> None:
    me = os.getpid()
    seen = []
    out = run_forked(
        _square_or_fail_in_parent,
        [(3, me), (1, me), (2, me)],
        "squares",
        3,
        lambda label, n, total: seen.append((label, n, total)),
        first_in_parent=True,
    )
    assert [r[0] for r in out] == [9, 1, 4]
    assert out[0][1] == me
    assert me not in {r[1] for r in out[1:]} and out[1][1] != out[2][1]
    assert seen[-1] == ("squares", 3, 3)
    # An error in the parent's own job is raised; the forked workers are not left behind.
    import multiprocessing as mp

    with pytest.raises(InputError, match="stretch 0: scan 5 has no points"):
        run_forked(
            _square_or_fail_in_parent, [(-1, me), (2, me)], "squares", 2, first_in_parent=True
        )
    assert not [p for p in mp.active_children() if p.is_alive()]


def _die_or_wait(job: int, tick) -> int:
    import time

    if job == 1:
        os._exit(9)  # a worker killed while the parent works
    for _ in range(200):
        time.sleep(0.05)
        tick()
    return job


def test_a_worker_killed_while_the_parent_works_stops_the_parents_job() -> None:
    import time

    start = time.monotonic()
    with pytest.raises(ProcessingError, match="squares: worker 1 ended without a result"):
        run_forked(_die_or_wait, [0, 1], "squares", 201, first_in_parent=True)
    assert time.monotonic() - start < 8  # not the parent's whole 10 s job


def _large_result(x: int, tick) -> dict:
    import numpy as np

    tick()
    rng = np.random.default_rng(x)
    return {"xyz": rng.normal(size=(200_000, 3)), "ring": rng.integers(0, 128, 200_000, np.uint16)}


def _handover_folders() -> set[str]:
    from canopy_kit.core import parallel

    if not os.path.isdir(parallel.SHARED_MEMORY_DIR):
        return set()
    return {n for n in os.listdir(parallel.SHARED_MEMORY_DIR) if n.startswith("canopy-kit-")}


@pytest.mark.parametrize("shared", [True, False])
def test_results_come_back_equal_through_shared_memory_or_the_pipe(monkeypatch, shared) -> None:
    import numpy as np

    from canopy_kit.core import parallel

    if shared and parallel._handover_dir() is None:
        pytest.skip("no /dev/shm with 1 GiB free on this machine")
    if not shared:
        monkeypatch.setattr(parallel, "SHARED_MEMORY_DIR", "/nonexistent-shm")
    before = _handover_folders()
    statuses = []
    received = parallel._received
    monkeypatch.setattr(parallel, "_received", lambda m: statuses.append(m[0]) or received(m))
    out = run_forked(_large_result, [1, 2], "big", 2)
    assert statuses == (["file", "file"] if shared else ["ok", "ok"])
    for x, got in zip([1, 2], out, strict=True):
        want = _large_result(x, lambda: None)
        np.testing.assert_array_equal(got["xyz"], want["xyz"])
        np.testing.assert_array_equal(got["ring"], want["ring"])
        assert got["ring"].dtype == np.uint16
    assert _handover_folders() == before  # nothing left behind


def _large_or_fail(x: int, tick) -> dict:
    if x == 0:
        raise InputError("scan 3: truncated")
    return _large_result(x, tick)


def test_a_failed_run_leaves_no_handed_over_results_behind() -> None:
    before = _handover_folders()
    with pytest.raises(InputError, match="scan 3: truncated"):
        run_forked(_large_or_fail, [1, 0, 2], "big", 3)
    assert _handover_folders() == before
