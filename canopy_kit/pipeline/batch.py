"""Many sessions at once on Dask distributed, each finished session written to the orchard store.

``run_batch(load_manifest("sessions.toml"), "out/")`` starts a ``LocalCluster`` (or joins an
existing scheduler), runs one task per session (the whole pipeline, outputs in
``out/sessions/<id>/``), retries tasks that fail for a transient reason (a worker lost, out
of memory) and reports a session whose input is bad without stopping the others. Finished
sessions go into ``out/orchard.duckdb`` in date order per orchard, one transaction each.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import os
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from canopy_kit.core.extras import needs_extra
from canopy_kit.errors import CanopyKitError, ConfigError, InputError

Progress = Callable[[str, float, float], None]
SESSION_KEYS = {
    "id",
    "bag",
    "orchard",
    "date",
    "preset",
    "drone_images",
    "truth",
    "report",
    "stream",
    "set",
    "rig",
}
# A session id names one folder under OUT/sessions/: a name, never a path.
SESSION_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
#: How long ``--scheduler`` is tried (Dask retries a refused connection) before giving up.
SCHEDULER_TIMEOUT = "20s"


@dataclass
class SessionSpec:
    """One line of a manifest: a bag, the orchard it covers, its date and how to run it."""

    session_id: str
    bag: Path
    orchard: str
    date: dt.date
    preset: str = "adaptive"
    overrides: dict[str, Any] = field(default_factory=dict)
    drone_images: Path | None = None
    truth: Path | None = None
    report: bool = True  # False: trees, metrics and config only (no map, no HTML report)
    stream: bool = False  # streaming mode (canopy_kit.streaming)


@dataclass
class SessionOutcome:
    """What one task returned: the per-tree table or why the session failed."""

    session_id: str
    orchard: str
    date: dt.date
    ok: bool
    out_dir: str
    trees: pd.DataFrame | None = None
    error: str | None = None
    summary: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    worker: str = ""


@dataclass
class BatchReport:
    """Every session's outcome, what the store made of it, and the batch's timing."""

    out_dir: Path
    store: Path | None
    outcomes: dict[str, SessionOutcome]
    ingests: dict[str, dict[str, Any]]
    failures: dict[str, str]
    skipped: list[str]
    wall_s: float
    n_workers: int
    scheduler: str
    store_upgrade: dict[str, Any] | None = None  # what opening an older store upgraded

    @property
    def ok(self) -> bool:
        return not self.failures

    def to_dict(self) -> dict[str, Any]:
        """Plain data for ``batch.json`` (per-tree tables left out)."""
        return {
            "out_dir": str(self.out_dir),
            "store": str(self.store) if self.store else None,
            "scheduler": self.scheduler,
            "n_workers": self.n_workers,
            "wall_s": self.wall_s,
            "sessions": {
                k: {
                    **{f: v for f, v in asdict(o).items() if f != "trees"},
                    "date": o.date.isoformat(),
                }
                for k, o in self.outcomes.items()
            },
            "ingests": self.ingests,
            "failures": self.failures,
            "skipped": self.skipped,
            **({"store_upgrade": self.store_upgrade} if self.store_upgrade else {}),
        }


# -- manifest -------------------------------------------------------------------------------
def load_manifest(path: str | Path, default_rig: str | Path | None = None) -> list[SessionSpec]:
    """Sessions listed in a TOML (``[[session]]`` tables) or CSV (one row each) manifest.

    Relative paths are relative to the manifest's folder. Top-level TOML keys (``preset``,
    ``orchard``, ``report``, ``stream``, ``rig``, ``[set]``) are defaults for every session;
    ``default_rig`` is the rig file of sessions that name none.
    """
    from canopy_kit.config import read_toml

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: manifest does not exist")
    if path.suffix.lower() == ".csv":
        entries = _csv_entries(path)
        defaults: dict[str, Any] = {}
    else:
        data = read_toml(path)
        entries = data.pop("session", [])
        defaults = data
        unknown = sorted(set(defaults) - (SESSION_KEYS - {"id", "bag", "date"}))
        if unknown:
            raise ConfigError(f"{path}: unknown top-level key {unknown[0]!r}")
    if not entries:
        raise InputError(f"{path}: manifest lists no session")
    if default_rig is not None:
        defaults.setdefault(
            "rig",
            str(Path(default_rig).resolve()) if Path(default_rig).exists() else str(default_rig),
        )
    specs = [_spec(path, i, {**defaults, **entry}) for i, entry in enumerate(entries, 1)]
    check_distinct_folders(specs, str(path))
    return specs


def check_distinct_folders(specs: list[SessionSpec], where: str) -> None:
    """A ConfigError when two sessions would share a folder (also where case is ignored)."""
    seen: dict[str, str] = {}
    for s in specs:
        folder = s.session_id.casefold()
        if folder in seen:
            same = (
                "appears twice"
                if seen[folder] == s.session_id
                else f"names the folder of {seen[folder]!r}"
            )
            raise ConfigError(f"{where}: session id {s.session_id!r} {same}")
        seen[folder] = s.session_id


def _csv_entries(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV manifest: UTF-8 (with or without Excel's BOM) or UTF-16 with a BOM."""
    raw = path.read_bytes()
    encoding = "utf-16" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
    try:
        text = raw.decode(encoding)
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise InputError(
            f"{path}: not {encoding.split('-sig')[0].upper()} text (line {line}, byte "
            f"{exc.start}: {raw[exc.start : exc.start + 1]!r}); save the manifest as UTF-8"
        ) from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    entries = []
    for number, row in enumerate(reader, 1):
        if None in row:  # more cells than the header has columns
            raise ConfigError(
                f"{path}: session {number} (line {reader.line_num}) has "
                f"{len(reader.fieldnames or []) + len(row[None])} cells, the header "
                f"{len(reader.fieldnames or [])} columns ({', '.join(reader.fieldnames or [])})"
            )
        entries.append({k.strip(): v for k, v in row.items() if v not in (None, "")})
    return entries


def check_session_id(session_id: str, where: str) -> str:
    """``session_id`` when it can name a folder under ``OUT/sessions/``, else a ConfigError.

    Letters, digits, ``.``, ``_`` and ``-``, starting with a letter or digit: no separator,
    no ``..``, nothing absolute, no control character, so no manifest writes outside --out."""
    if not SESSION_ID.fullmatch(session_id):
        raise ConfigError(
            f"{where}: session id {session_id!r} cannot name a folder: use letters, "
            "digits, '.', '_' and '-', starting with a letter or digit (at most 128)"
        )
    return session_id


def default_session_id(orchard: str, date: dt.date) -> str:
    """``ORCHARD-DATE`` with every run of characters a folder name cannot hold made ``-``."""
    name = re.sub(r"[^A-Za-z0-9._-]+", "-", orchard)[:100].strip("-._")
    return f"{name or 'orchard'}-{date.isoformat()}"


def session_folder(out_root: str | Path, session_id: str) -> Path:
    """``OUT/sessions/<id>``, checked to lie inside ``OUT/sessions``."""
    sessions = Path(out_root).resolve() / "sessions"
    folder = (sessions / check_session_id(session_id, str(out_root))).resolve()
    if folder.parent != sessions:  # e.g. a symbolic link planted under sessions/
        raise InputError(f"{folder}: session folder resolves outside {sessions}")
    return folder


def _spec(path: Path, number: int, entry: dict[str, Any]) -> SessionSpec:
    from canopy_kit.config import merge, nested_settings, parse_settings

    where = f"{path}: session {number}"
    unknown = sorted(set(entry) - SESSION_KEYS)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {unknown[0]!r} (known: {', '.join(sorted(SESSION_KEYS))})"
        )
    for key in ("bag", "date", "orchard"):
        if key not in entry:
            raise ConfigError(f"{where}: no {key!r}")
    date = entry["date"]
    if isinstance(date, dt.datetime):
        date = date.date()
    elif not isinstance(date, dt.date):
        try:
            date = dt.date.fromisoformat(str(date))
        except ValueError:
            raise ConfigError(f"{where}: date {entry['date']!r} is not YYYY-MM-DD") from None
    overrides = entry.get("set", {})
    if isinstance(overrides, str):  # CSV: "section.key=value; section.key=value"
        overrides = parse_settings(overrides.split(";"), f"{where}: set")
    elif not isinstance(overrides, dict):
        raise ConfigError(f"{where}: 'set' must be a table of overrides")
    overrides = merge({}, nested_settings(overrides))

    def resolve(value: Any) -> Path | None:
        if value is None:
            return None
        p = Path(str(value)).expanduser()
        return p if p.is_absolute() else (path.parent / p)

    if "rig" in entry:  # a shipped rig's name, or a rig file relative to the manifest
        from canopy_kit.config.rig import rig_overrides, rig_preset_names

        rig = str(entry["rig"])
        overrides = merge(
            overrides, rig_overrides(rig if rig in rig_preset_names() else resolve(rig))
        )

    orchard = str(entry["orchard"])
    session_id = (
        check_session_id(str(entry["id"]), where)
        if "id" in entry
        else default_session_id(orchard, date)
    )
    return SessionSpec(
        session_id,
        resolve(entry["bag"]),
        orchard,
        date,
        str(entry.get("preset", "adaptive")),
        overrides,
        resolve(entry.get("drone_images")),
        resolve(entry.get("truth")),
        _flag(entry.get("report", True), where, "report"),
        _flag(entry.get("stream", False), where, "stream"),
    )


def _flag(value: Any, where: str, name: str) -> bool:
    if isinstance(value, bool):
        return value
    if str(value).strip().lower() in ("true", "1", "yes"):
        return True
    if str(value).strip().lower() in ("false", "0", "no"):
        return False
    raise ConfigError(f"{where}: {name} must be true or false, got {value!r}")


# -- one session (runs on a worker) ---------------------------------------------------------
def process_session(
    spec: SessionSpec, out_root: str, mapping_threads: int = 1, token: str = ""
) -> SessionOutcome:
    """Run one session's pipeline; bad input is returned as a failed outcome (not retried),
    naming the stage. ``token`` (one per batch) marks the session's trail on disk
    (:mod:`canopy_kit.pipeline.session_log`): a session whose worker crashed is not run again."""
    import socket

    from canopy_kit.config import load_preset
    from canopy_kit.pipeline.session_log import (
        SessionTrail,
        crash_message,
        own_worker_process,
        read_trail,
    )

    out = session_folder(out_root, spec.session_id)
    wall = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    earlier = read_trail(out, token) if token else None
    if earlier is not None and earlier["signal"]:
        return SessionOutcome(
            spec.session_id,
            spec.orchard,
            spec.date,
            False,
            str(out),
            error=f"WorkerCrash: {spec.bag}: {crash_message(earlier)}; not run again "
            "(the same input crashes the same code)",
            worker=worker,
        )
    trail = SessionTrail(out, token or "-", own_process=own_worker_process())
    try:
        with trail:
            config = load_preset(spec.preset, spec.overrides)
            config.mapping.workers = 1  # a Dask worker is daemonic: no child processes
            if mapping_threads > 0:
                config.mapping.threads = mapping_threads
            results = _run_one(spec, config, out, trail.progress)
    except CanopyKitError as exc:
        message = str(exc) if str(spec.bag) in str(exc) else f"{spec.bag}: {exc}"
        stage = f" in stage {trail.stage!r}" if trail.stage else ""
        return SessionOutcome(
            spec.session_id,
            spec.orchard,
            spec.date,
            False,
            str(out),
            error=f"{type(exc).__name__}{stage}: {message}",
            wall_s=time.perf_counter() - wall,
            worker=worker,
        )
    m = results.metrics
    summary = {
        "n_trees": m.get("n_trees"),
        "warnings": m.get("warnings", []),
        "mode": "stream" if spec.stream else "batch",
    }
    return SessionOutcome(
        spec.session_id,
        spec.orchard,
        spec.date,
        True,
        str(out),
        results.trees,
        summary=summary,
        wall_s=time.perf_counter() - wall,
        worker=worker,
    )


def _run_one(spec: SessionSpec, config: Any, out: Path, progress: Progress | None = None) -> Any:
    from canopy_kit import pipeline

    if spec.stream:
        from canopy_kit.streaming import run_stream

        return run_stream(config, spec.bag, out, progress=progress, orchard=spec.orchard)
    if spec.report:
        return pipeline.run(
            config,
            spec.bag,
            out,
            drone_images=spec.drone_images,
            truth=spec.truth,
            progress=progress,
            orchard=spec.orchard,
        )
    from canopy_kit.results.provenance import provenance

    started, t0 = time.time(), time.perf_counter()
    ctx, cache = pipeline.compute(
        config, spec.bag, out, spec.drone_images, spec.truth, progress=progress
    )
    prov = provenance(
        spec.bag, config.name, started, time.perf_counter() - t0, spec.orchard, spec.drone_images
    )
    return _write_tables(ctx, cache, out, prov)


def _write_tables(ctx: Any, cache: Any, out: Path, prov: dict[str, Any] | None = None) -> Any:
    """The per-tree table, metrics and config only (a batch that needs no report)."""
    from canopy_kit.core.atomic import atomic_write_text
    from canopy_kit.results.outputs import Results, run_metrics, write_tree_tables

    metrics = run_metrics(ctx, ctx.table)
    metrics["stage_timings"] = cache.timings
    if prov:
        metrics["provenance"] = prov
    # segmentation.json and crowns among them: `canopy-kit evaluate` scores the session by footprints
    files = write_tree_tables(ctx, ctx.table, out, prov)
    files["metrics.json"] = atomic_write_text(
        out / "metrics.json", json.dumps(metrics, indent=2, default=str) + "\n"
    )
    return Results(out, ctx.table, metrics, files, list(metrics.get("warnings", [])))


# -- the batch ------------------------------------------------------------------------------
def run_batch(
    sessions: list[SessionSpec],
    out: str | Path,
    scheduler: str | None = None,
    n_workers: int | None = None,
    retries: int = 2,
    store: str | Path | None = None,
    match: Any = None,
    mapping_threads: int = 1,
    skip_stored: bool = True,
    progress: Progress | None = None,
    on_session: Callable[[SessionOutcome], None] | None = None,
) -> BatchReport:
    """Process ``sessions`` on Dask (one task each) and store them; see the module docstring.

    ``scheduler`` is the address of a running Dask scheduler (``tcp://host:8786``); without
    it a ``LocalCluster`` of ``n_workers`` single-threaded processes is started. ``store``
    defaults to ``out/orchard.duckdb``; pass ``False``-like ``""`` to skip storing.
    """
    from canopy_kit.store import MatchSettings, OrchardStore

    out = Path(out)
    check_distinct_folders(sessions, "batch")
    for spec in sessions:  # before anything runs: no session may write outside ``out``
        session_folder(out, spec.session_id)
    out.mkdir(parents=True, exist_ok=True)
    report = progress or (lambda *_: None)
    store_path = out / "orchard.duckdb" if store is None else (Path(store) if store else None)
    db = OrchardStore(store_path) if store_path is not None else None
    upgraded = db.upgrade.as_dict() if db is not None and db.upgrade is not None else None
    wall = time.perf_counter()
    skipped = [
        s.session_id
        for s in sessions
        if db is not None and skip_stored and db.has_session(s.session_id)
    ]
    todo = [s for s in sessions if s.session_id not in skipped]
    outcomes: dict[str, SessionOutcome] = {}
    ingests: dict[str, dict[str, Any]] = {}
    failures: dict[str, str] = {}
    order = _ingest_order(todo)
    client, cluster = _connect(scheduler, n_workers or min(len(todo), os.cpu_count() or 1) or 1)
    try:
        n_live = len(client.scheduler_info().get("workers", {}))
        report("sessions", 0, len(todo))
        if todo:
            _collect(
                client,
                todo,
                out,
                retries,
                mapping_threads,
                outcomes,
                failures,
                report,
                on_session,
                lambda: _ingest_ready(
                    db, order, outcomes, ingests, failures, match or MatchSettings()
                ),
            )
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
        if db is not None:
            db.close()
    result = BatchReport(
        out,
        store_path,
        outcomes,
        ingests,
        failures,
        skipped,
        time.perf_counter() - wall,
        n_live,
        scheduler or "LocalCluster",
        upgraded,
    )
    from canopy_kit.core.atomic import atomic_write_text

    atomic_write_text(
        out / "batch.json", json.dumps(result.to_dict(), indent=2, default=str) + "\n"
    )
    return result


def _connect(scheduler: str | None, n_workers: int) -> tuple[Any, Any]:
    import logging

    with needs_extra("batch"):
        from distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout=SCHEDULER_TIMEOUT), None
        except (OSError, TimeoutError) as exc:
            raise InputError(
                f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})"
            ) from None
    cluster = LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.ERROR,
    )
    return Client(cluster), cluster


def _collect(
    client: Any,
    todo: list[SessionSpec],
    out: Path,
    retries: int,
    mapping_threads: int,
    outcomes: dict[str, SessionOutcome],
    failures: dict[str, str],
    report: Progress,
    on_session: Callable[[SessionOutcome], None] | None,
    ingest: Callable[[], None],
) -> None:
    with needs_extra("batch"):
        from distributed import as_completed

    from canopy_kit.pipeline.session_log import crash_message, read_trail

    token = f"{os.getpid()}-{time.time_ns()}"  # marks this batch's session trails
    futures = {
        client.submit(
            process_session,
            spec,
            str(out.resolve()),
            mapping_threads,
            token,
            key=f"canopy-kit-session-{spec.session_id}-{time.time_ns()}",
            retries=retries,
            pure=False,
        ): spec
        for spec in todo
    }
    for n, future in enumerate(as_completed(futures), 1):
        spec = futures[future]
        try:
            outcome = future.result()
        except Exception as exc:  # the task itself died: a lost worker, memory, a bug
            folder = session_folder(out, spec.session_id)
            why = crash_message(read_trail(folder, token))
            outcome = SessionOutcome(
                spec.session_id,
                spec.orchard,
                spec.date,
                False,
                str(folder),
                error=f"{type(exc).__name__}: {spec.bag}: {why} ({exc})",
            )
        outcomes[spec.session_id] = outcome
        if not outcome.ok:
            failures[spec.session_id] = outcome.error or "failed"
        ingest()
        report("sessions", n, len(todo))
        if on_session is not None:
            on_session(outcome)


def _ingest_order(todo: list[SessionSpec]) -> dict[str, list[SessionSpec]]:
    order: dict[str, list[SessionSpec]] = {}
    for spec in sorted(todo, key=lambda s: (s.date, s.session_id)):
        order.setdefault(spec.orchard, []).append(spec)
    return order


def _ingest_ready(
    db: Any,
    order: dict[str, list[SessionSpec]],
    outcomes: dict[str, SessionOutcome],
    ingests: dict[str, dict[str, Any]],
    failures: dict[str, str],
    match: Any,
) -> None:
    """Store every finished session whose orchard's earlier sessions are all settled."""
    from canopy_kit.store import SessionRecord

    if db is None:
        return
    for specs in order.values():
        while specs and specs[0].session_id in outcomes:
            spec = specs.pop(0)
            outcome = outcomes[spec.session_id]
            if not outcome.ok or outcome.trees is None:
                continue
            record = SessionRecord(
                spec.session_id,
                spec.orchard,
                spec.date,
                str(spec.bag),
                spec.preset,
                outcome.out_dir,
                outcome.summary,
            )
            try:
                ingests[spec.session_id] = db.ingest(record, outcome.trees, match).summary()
            except CanopyKitError as exc:
                failures[spec.session_id] = f"store: {type(exc).__name__}: {exc}"
