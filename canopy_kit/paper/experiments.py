"""The paper's experiments re-run on simulated orchards, beside the paper's figures.

For every orchard (pistachio, almond; optionally almond-paper) and seed a session is
simulated, then the whole pipeline (:func:`canopy_kit.pipeline.compute`, with its own
LiDAR-inertial mapping) runs it once per segmenter with the preset that sets it up:
``dbscan`` = the paper's pistachio preset (eps 0.8 m, N_min 1300), ``dbscan_spectral`` =
the paper's almond preset (split above 45,000 points, k = 10), ``adaptive`` = canopy-kit's
own (and on request ``dbscan_spectral_scaled`` = the ``almond-scaled`` preset); every
preset measures convex hull and alpha shape (alpha = 0.9 m). Optionally the same runs
on a map built from the true poses separate mapping error from segmentation and volume
error.

Scored against the simulator's truth: segmentation success (:mod:`canopy_kit.evaluate.segmentation_score`,
one-to-one point IoU >= 0.5), and, on the correctly segmented trees, volume errors against
the aerial sphere ground truth as the paper computes it (``pi d^3 / 6`` of the widest true
crown diameter: what a perfect aerial survey gives) and against the true crown volume,
which the paper could not measure.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.errors import CanopyKitError, InputError
from canopy_kit.paper.comparison import PAPER_SEGMENTATION, compare

Progress = Callable[[str, float, float], None]

ORCHARDS = ("pistachio", "almond")
#: Orchards the experiments accept: the defaults and the almond preset calibrated on the
#: paper's DBSCAN figure (docs/SIMULATOR.md).
KNOWN_ORCHARDS = (*ORCHARDS, "almond-paper")
#: Method -> the preset that runs it (presets are in canopy_kit/presets);
#: ``dbscan_spectral_scaled`` is the paper's almond method at our map's scale, on request.
METHOD_PRESETS = {
    "dbscan": "pistachio",
    "dbscan_spectral": "almond",
    "adaptive": "adaptive",
    "dbscan_spectral_scaled": "almond-scaled",
}
#: The methods run unless others are asked for: the paper's two and ours.
DEFAULT_METHODS = ("dbscan", "dbscan_spectral", "adaptive")
MAPPINGS = ("pipeline", "true_poses")
RESULT_FILES = {
    "runs": "experiments_runs.csv",
    "trees": "experiments_trees.csv",
    "comparison": "experiments_comparison.csv",
    "summary": "experiments.json",
}
TREE_COLUMNS = [
    "tree_id",
    "label",
    "segment",
    "n_points",
    "crown_diameter_m",
    "truth_tree_id",
    "truth_label",
    "true_crown_diameter_m",
    "true_crown_volume_m3",
    "true_sphere_volume_m3",
    "aerial_sphere_volume_m3",
    "aerial_diameter_m",
    "volume_flags",
]


#: The settings the committed results (``data/paper/experiments*``) were made with, which
#: are :class:`ExperimentConfig`'s and the CLI's defaults (docs/REPRODUCTION.md).
COMMITTED_SEEDS = (301, 302, 303)
COMMITTED_ROWS = 2
COMMITTED_TREES_PER_ROW = 6


def default_results_dir() -> Path:
    """``data/paper`` of the source checkout this package was imported from."""
    return Path(__file__).resolve().parents[2] / "data" / "paper"


def new_results_dir(root: str | Path = "out", now: datetime | None = None) -> Path:
    """A fresh folder name for new results, ``ROOT/paper-YYYYmmdd-HHMMSS`` (UTC)."""
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%d-%H%M%S")
    return Path(root) / f"paper-{stamp}"


def check_results_dir(out_dir: str | Path, overwrite: bool = False) -> Path:
    """``out_dir`` if results may be written there, else :class:`InputError` naming it.

    Committed data (anything under the checkout's ``data/``) and a folder that already holds
    results are refused unless ``overwrite``.
    """
    out = Path(out_dir)
    if overwrite:
        return out
    data = default_results_dir().parent
    if out.resolve().is_relative_to(data):
        raise InputError(
            f"{out}: refusing to write into the committed data folder {data} "
            f"(give another --out, or --overwrite to replace the committed "
            f"results)"
        )
    held = [name for name in RESULT_FILES.values() if (out / name).exists()]
    if held:
        raise InputError(
            f"{out}: already holds experiment results ({', '.join(held)}); "
            f"give another --out, or --overwrite to replace them"
        )
    return out


@dataclass(frozen=True)
class ExperimentConfig:
    """What to simulate and run: orchards x seeds sessions, each with every method and mapping.

    ``sim_overrides`` go to every simulated session (e.g. ``{"lidar": {"columns": 512}}``);
    ``drone`` also simulates a drone flight and runs the photogrammetry stage, whose sphere
    volumes become a third reference (``aerial``).
    """

    seeds: tuple[int, ...] = COMMITTED_SEEDS
    rows: int = COMMITTED_ROWS
    trees_per_row: int = COMMITTED_TREES_PER_ROW
    orchards: tuple[str, ...] = ORCHARDS
    methods: tuple[str, ...] = DEFAULT_METHODS
    mappings: tuple[str, ...] = ("pipeline",)
    sim_overrides: dict[str, Any] = field(default_factory=dict)
    sensor: str | None = None
    drone: bool = False

    def validate(self) -> None:
        """Raise :class:`InputError` naming the first unusable setting."""
        if not self.seeds:
            raise InputError("experiments: need at least one seed")
        if len(set(self.seeds)) != len(self.seeds):
            raise InputError(f"experiments: seeds repeat ({list(self.seeds)})")
        if self.rows < 1 or self.trees_per_row < 2:
            raise InputError(
                f"experiments: need rows >= 1 and trees per row >= 2, got "
                f"{self.rows} x {self.trees_per_row}"
            )
        for name, given, known in (
            ("orchard", self.orchards, KNOWN_ORCHARDS),
            ("method", self.methods, tuple(METHOD_PRESETS)),
            ("mapping", self.mappings, MAPPINGS),
        ):
            if not given:
                raise InputError(f"experiments: no {name} given")
            bad = [g for g in given if g not in known]
            if bad:
                raise InputError(
                    f"experiments: unknown {name} {bad[0]!r} (known: {', '.join(known)})"
                )

    def n_runs(self) -> int:
        return len(self.orchards) * len(self.seeds) * len(self.mappings) * len(self.methods)


@dataclass
class ExperimentResults:
    """Every run (``runs``), every segmented tree (``trees``), the table beside the paper."""

    config: ExperimentConfig
    runs: pd.DataFrame  # one row per orchard x seed x mapping x method
    trees: pd.DataFrame  # one row per segment of every run, truth columns where matched
    comparison: pd.DataFrame  # one row per orchard x method x mapping, paper columns beside
    paper: dict[str, Any]  # the paper's figures the comparison quotes
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: settings, paper figures, the comparison table and every run."""
        return {
            "config": asdict(self.config),
            "paper": self.paper,
            "seconds": self.seconds,
            "comparison": _records(self.comparison),
            "runs": _records(self.runs),
        }


# -- the paper's figures -----------------------------------------------------------------
def paper_figures(table1: str | Path | None = None) -> dict[str, Any]:
    """Segmentation success as printed, volume statistics recomputed from corrected Table I."""
    from canopy_kit.paper.consistency import check_table1
    from canopy_kit.paper.summary import summarise_table1

    check = check_table1(table1)
    summary = summarise_table1(check, "corrected")
    t = check.corrected
    return {
        "segmentation_success": {f"{o}/{m}": v for (o, m), v in PAPER_SEGMENTATION.items()},
        "volume_source": "Table I (17 pistachio trees, DBSCAN), columns corrected",
        "mape_vs_sphere_pct": {
            "convex_hull": summary.agreement["hull"].mape_pct,
            "alpha_shape": summary.agreement["alpha"].mape_pct,
        },
        "bias_vs_sphere_pct": {
            "convex_hull": summary.agreement["hull"].bias_pct,
            "alpha_shape": summary.agreement["alpha"].bias_pct,
        },
        "max_error_vs_sphere_pct": {
            "convex_hull": float(t["hull_err_pct"].max()),
            "alpha_shape": float(t["alpha_err_pct"].max()),
        },
        "alpha_better_trees": len(summary.claim.alpha_better),
        "n_trees": summary.claim.n_trees,
    }


# -- running -----------------------------------------------------------------------------
@dataclass
class SharedMap:
    """A map handed to further segmenters of the same session: the mapping stage's result
    without its settings, so evaluation does not score the same mapping again."""

    map: Any
    trajectory: pd.DataFrame
    frame: Any
    diagnostics: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def session_name(orchard: str, seed: int, config: ExperimentConfig) -> str:
    return f"{orchard}_{config.rows}x{config.trees_per_row}_s{seed}"


def session_config(orchard: str, seed: int, config: ExperimentConfig) -> Any:
    """The simulator config of one session of the experiment."""
    from canopy_kit.config import merge
    from canopy_kit.sim import load_sim_config

    base: dict[str, Any] = {
        "seed": seed,
        "orchard": {"rows": config.rows, "trees_per_row": config.trees_per_row},
    }
    if config.drone:
        base["drone"] = {"enabled": True}
    return load_sim_config(orchard, merge(base, config.sim_overrides), sensor=config.sensor)


def simulate(
    orchard: str, seed: int, config: ExperimentConfig, root: Path, progress: Progress | None = None
) -> Path:
    """Simulate one session into ``root``, or reuse the complete one with the same config there.

    Returns the bag path. A ``.complete`` file marks a finished simulation.
    """
    from canopy_kit.config import to_dict
    from canopy_kit.io.session_layout import find_bag
    from canopy_kit.sim import simulate_session
    from canopy_kit.sim.session import load_sim_config_of

    sim_cfg = session_config(orchard, seed, config)
    marker = root / ".complete"
    if marker.is_file():
        try:
            if to_dict(load_sim_config_of(root)) == to_dict(sim_cfg):
                return find_bag(root)
        except CanopyKitError:
            pass  # unreadable: simulate again
    session = simulate_session(root, sim_cfg, overwrite=True, progress=progress)
    marker.write_text("simulated\n")
    return session.bag


def compute_on_map(
    pipeline_config: Any,
    mapping: Any,
    sim_dir: Path,
    drone_images: Path | None,
    out: Path,
    progress: Progress,
) -> Any:
    """The pipeline's stages after mapping, on a given map, scored against the truth."""
    from canopy_kit.evaluate.validation import evaluate_against_truth
    from canopy_kit.pipeline import RunContext, aerial_stage, segment_stage, volume_stage
    from canopy_kit.results.tree_table import tree_table

    ctx = RunContext(pipeline_config, mapping=mapping)
    ctx.segmentation = segment_stage(ctx, progress)
    ctx.trees = volume_stage(ctx, progress, surfaces=False).table
    if drone_images is not None:
        ctx.aerial = aerial_stage(ctx, drone_images, out / "aerial", progress)
    ctx.table = tree_table(ctx)
    ctx.evaluation = evaluate_against_truth(ctx, ctx.table, sim_dir)
    ctx.table = ctx.evaluation.pop("trees")
    ctx.truth_matches = ctx.evaluation.pop("segmentation_trees")
    return ctx


def run_record(ctx: Any, mapping_scores: dict[str, Any]) -> dict[str, Any]:
    """The per-run numbers: segmentation score, mapping error, map density."""
    score = ctx.evaluation["segmentation"]
    rec = {
        k: score[k]
        for k in (
            "n_truth",
            "n_predicted",
            "n_correct",
            "success_rate",
            "n_merged",
            "n_split",
            "n_missed",
            "n_other",
            "n_false_segments",
            "label_accuracy",
            "mode",
        )
    }
    rec["ate_rmse_m"] = mapping_scores.get("ate_rmse_m", np.nan)
    rec["drift_percent"] = mapping_scores.get("drift_percent", np.nan)
    cloud = ctx.mapping.map
    if "tree_id" in cloud.fields:  # map points per true tree: what N_min and 45,000 count
        ids = np.asarray(cloud.fields["tree_id"]).astype(np.int64)
        counts = np.bincount(ids[ids >= 0])
        counts = counts[counts > 0]
        rec["map_points_per_tree_median"] = float(np.median(counts)) if len(counts) else np.nan
    return rec


def run_mapping(
    orchard: str,
    seed: int,
    mapping: str,
    config: ExperimentConfig,
    root: Path,
    bag: Path,
    progress: Progress,
    done: list[int],
) -> tuple[list[dict[str, Any]], list[pd.DataFrame]]:
    """Every method on one simulated session, on one kind of map.

    ``pipeline``: the first method runs :func:`canopy_kit.pipeline.compute` (mapping and its
    evaluation included); the others reuse that map. ``true_poses``: a map from the true
    poses (:func:`canopy_kit.evaluate.truth_map.truth_mapping`).
    """
    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.truth_map import truth_mapping
    from canopy_kit.pipeline import compute

    drone = root / "drone" if config.drone else None
    shared = truth_mapping(root, progress=progress) if mapping == "true_poses" else None
    mapping_scores: dict[str, Any] = {}
    records: list[dict[str, Any]] = []
    tables: list[pd.DataFrame] = []
    for method in config.methods:
        preset = METHOD_PRESETS[method]
        rec: dict[str, Any] = {
            "orchard": orchard,
            "seed": seed,
            "session": root.name,
            "mapping": mapping,
            "method": method,
            "preset": preset,
        }
        t0 = time.perf_counter()
        try:
            if shared is None:
                ctx, _ = compute(
                    load_preset(preset), bag, root / "run", drone, root, progress=progress
                )
                mapping_scores = ctx.evaluation.get("mapping", {})
                m = ctx.mapping
                shared = SharedMap(
                    m.map,
                    m.trajectory,
                    getattr(m, "frame", None),
                    dict(getattr(m, "diagnostics", {})),
                    list(getattr(m, "warnings", [])),
                )
            else:
                ctx = compute_on_map(
                    load_preset(preset),
                    shared,
                    root,
                    drone,
                    root / f"run_{mapping}_{method}",
                    progress,
                )
            rec.update(run_record(ctx, mapping_scores))
            columns = [c for c in TREE_COLUMNS if config.drone or not c.startswith("aerial_")]
            table = ctx.table.reindex(
                columns=columns
                + [c for c in ctx.table.columns if c.startswith("volume_") and c != "volume_flags"]
            )
            tables.append(table.assign(orchard=orchard, seed=seed, mapping=mapping, method=method))
            rec["error"] = ""
        except CanopyKitError as exc:  # one failed run must not lose the others
            rec["error"] = f"{type(exc).__name__}: {exc}"
        rec["seconds"] = round(time.perf_counter() - t0, 1)
        records.append(rec)
        done[0] += 1
        progress("experiment runs", done[0], config.n_runs())
    return records, tables


def run_experiments(
    config: ExperimentConfig,
    work_dir: str | Path,
    progress: Progress | None = None,
    keep_sessions: bool = False,
    table1: str | Path | None = None,
    saved_only: bool = False,
) -> ExperimentResults:
    """Simulate every session in ``work_dir``, run and score everything.

    Mappings come outermost, so the pipeline's results of every session are in before the
    true-pose variant starts. Each finished session x mapping leaves its results in
    ``work_dir``, and a session is deleted after its last mapping (unless
    ``keep_sessions``): running the same config there again resumes where it stopped.
    ``saved_only`` runs nothing: it collects the session x mappings already finished in
    ``work_dir`` (e.g. by several processes sharing it) and leaves the others out; the
    ``runs`` table and the comparison's ``sessions`` column say which are in.
    """
    config.validate()
    report = progress or (lambda *_: None)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    paper = paper_figures(table1)
    t0 = time.perf_counter()
    done = [0]
    report("experiment runs", 0, config.n_runs())
    records: list[dict[str, Any]] = []
    tables: list[pd.DataFrame] = []
    for mapping in config.mappings:
        last = mapping == config.mappings[-1]
        for orchard in config.orchards:
            for seed in config.seeds:
                root = work / session_name(orchard, seed, config)
                saved = load_checkpoint(work, orchard, seed, mapping, config)
                if saved is None and saved_only:
                    continue
                if saved is None:
                    bag = simulate(orchard, seed, config, root, report)
                    recs, tabs = run_mapping(
                        orchard, seed, mapping, config, root, bag, report, done
                    )
                    save_checkpoint(work, orchard, seed, mapping, config, recs, tabs)
                else:
                    recs, tabs = saved
                    done[0] += len(recs)
                    report("experiment runs", done[0], config.n_runs())
                if last and not keep_sessions:
                    shutil.rmtree(root, ignore_errors=True)
                records += recs
                tables += tabs
    if saved_only and not records:
        raise InputError(
            f"{work}: no finished sessions of this configuration "
            f"({config.rows} rows x {config.trees_per_row} trees, same settings)"
        )
    runs = pd.DataFrame(records)
    trees = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    if len(trees):
        first = ["orchard", "seed", "mapping", "method"]
        trees = trees[first + [c for c in trees.columns if c not in first]]
    comparison = compare(runs, trees, paper, config)
    return ExperimentResults(
        config, runs, trees, comparison, paper, round(time.perf_counter() - t0, 1)
    )


def _checkpoint_paths(
    work: Path, orchard: str, seed: int, mapping: str, config: ExperimentConfig
) -> tuple[Path, Path]:
    """Files of one finished session x mapping, named by every setting that matters."""
    settings = {
        k: v for k, v in asdict(config).items() if k not in ("seeds", "orchards", "mappings")
    }
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    stem = f"{session_name(orchard, seed, config)}_{mapping}_{digest.hexdigest()[:10]}"
    return work / f"{stem}.runs.json", work / f"{stem}.trees.csv"


def save_checkpoint(
    work: Path,
    orchard: str,
    seed: int,
    mapping: str,
    config: ExperimentConfig,
    records: list[dict[str, Any]],
    tables: list[pd.DataFrame],
) -> None:
    """Keep a finished session x mapping's results in ``work`` for a rerun to resume after."""
    from canopy_kit.core.atomic import atomic_write_text, json_default

    runs_path, trees_path = _checkpoint_paths(work, orchard, seed, mapping, config)
    trees = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    atomic_write_text(trees_path, trees.to_csv(index=False))
    atomic_write_text(runs_path, json.dumps(records, default=json_default))


def load_checkpoint(
    work: Path, orchard: str, seed: int, mapping: str, config: ExperimentConfig
) -> tuple[list[dict[str, Any]], list[pd.DataFrame]] | None:
    """A finished session x mapping's results from ``work``, or None when not run there."""
    runs_path, trees_path = _checkpoint_paths(work, orchard, seed, mapping, config)
    if not (runs_path.is_file() and trees_path.is_file()):
        return None
    records = json.loads(runs_path.read_text())
    try:
        trees = pd.read_csv(trees_path)
    except pd.errors.EmptyDataError:
        trees = pd.DataFrame()
    if "volume_flags" in trees:
        trees["volume_flags"] = trees["volume_flags"].astype(object).fillna("")
    return records, ([trees] if len(trees) else [])


# -- files ---------------------------------------------------------------------------------
def write_results(
    results: ExperimentResults, out_dir: str | Path, overwrite: bool = False
) -> dict[str, Path]:
    """Runs, trees and comparison as CSV, everything as JSON, each written atomically.

    Refuses (:func:`check_results_dir`) committed data and earlier results unless
    ``overwrite``.
    """
    from canopy_kit.core.atomic import atomic_write_text, json_default

    out = check_results_dir(out_dir, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for key, frame in (
        ("runs", results.runs),
        ("trees", results.trees),
        ("comparison", results.comparison),
    ):
        files[key] = atomic_write_text(
            out / RESULT_FILES[key], frame.to_csv(index=False, float_format="%.4f")
        )
    files["summary"] = atomic_write_text(
        out / RESULT_FILES["summary"],
        json.dumps(results.to_dict(), indent=1, default=json_default) + "\n",
    )
    return files


def load_results(out_dir: str | Path | None = None) -> ExperimentResults:
    """Read back what :func:`write_results` wrote (for notebooks and docs)."""
    out = Path(out_dir) if out_dir is not None else default_results_dir()
    path = out / RESULT_FILES["summary"]
    if not path.is_file():
        raise InputError(f"{path}: no experiment results (run 'canopy-kit paper experiments')")
    data = json.loads(path.read_text())
    cfg = data["config"]
    config = ExperimentConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()})
    trees_csv = out / RESULT_FILES["trees"]
    trees = pd.read_csv(trees_csv) if trees_csv.is_file() else pd.DataFrame()
    return ExperimentResults(
        config,
        _frame(data["runs"]),
        trees,
        _frame(data["comparison"]),
        data["paper"],
        data.get("seconds", 0.0),
    )


def _frame(records: list[dict[str, Any]]) -> pd.DataFrame:
    """Records read from JSON: numeric columns (JSON null = NaN) back to numbers."""
    frame = pd.DataFrame(records)
    for col in frame.columns:
        values = frame[col]
        if values.map(lambda v: v is None or isinstance(v, (int, float))).all():
            frame[col] = pd.to_numeric(values)
    return frame


def _records(frame: pd.DataFrame) -> list[dict[str, Any]]:
    return json.loads(frame.to_json(orient="records")) if len(frame) else []
