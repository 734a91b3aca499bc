"""Trees out of a bag while it is read: the streaming counterpart of the batch pipeline.

Sweeps go into a sliding window of the map (odometry frame, voxel-thinned as the batch
map). Whenever the drive finishes a stretch of a row (see ``streaming.layout``), that
stretch is segmented and measured with the batch stages' own functions
(``segment.segment``, ``volume.verb.measure_trees``); trees clear of the unfinished part are
emitted and leave the window with the finished ground around them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.config import PipelineConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.streaming.layout import DriveLayout, RegionState
from canopy_kit.streaming.source import RunningGeoreference, SweepSource
from canopy_kit.streaming.window import ClosedArea, PointWindow

Progress = Callable[[str, float, float], None]


@dataclass
class StreamSettings:
    """When a stretch counts as finished and how often finished stretches are processed."""

    lag_m: float = 8.0  # finished this far behind the robot on the stretch's second side
    step_m: float = 10.0  # process a strip again once its finished part grew this much
    context_m: float = 4.0  # finished points kept before the frontier as context
    edge_m: float = 0.5  # a tree this close to the unfinished part waits
    min_pass_m: float = 6.0  # straight run along the rows that counts as a pass
    same_line_m: float = 1.5  # passes closer than this across the rows share an alley
    check_every: int = 5  # sweeps between looks at the layout

    def check(self) -> None:
        """Reject settings that cannot work, naming the setting."""
        for name in ("lag_m", "step_m", "min_pass_m", "same_line_m"):
            if not getattr(self, name) > 0:
                raise InputError(
                    f"stream setting {name} must be positive, got {getattr(self, name)}"
                )
        if self.context_m < 0 or self.edge_m < 0 or self.check_every < 1:
            raise InputError("stream settings context_m and edge_m must be >= 0, check_every >= 1")


@dataclass
class StreamedTree:
    """One tree, emitted once the robot has passed it."""

    index: int  # emission order
    values: dict[str, Any]  # measure_trees' row: odometry-frame x, y, metrics, volumes
    emitted_at: float  # bag time (s)
    passed_at: float  # bag time the robot was last abreast of the tree
    x: float = np.nan  # local UTM frame at emission (NaN before the GNSS heading is known)
    y: float = np.nan
    lat: float = np.nan
    lon: float = np.nan
    row: int = -1  # provisional: rows seen so far, numbered as the batch does
    label: str = ""
    hull: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)


class TreeStream:
    """Iterate to get :class:`StreamedTree` objects; diagnostics are filled on the way."""

    def __init__(
        self,
        config: PipelineConfig,
        bag: str | Path,
        settings: StreamSettings | None = None,
        progress: Progress | None = None,
    ) -> None:
        self.config = config
        self.settings = settings or StreamSettings()
        self.settings.check()
        self.progress = progress
        self.source = SweepSource(Path(bag), config.mapping, progress)
        self.layout = DriveLayout(
            min_pass_m=self.settings.min_pass_m, same_line_m=self.settings.same_line_m
        )
        self.window = PointWindow(config.mapping.map_voxel_size)
        self.georef = RunningGeoreference(config.mapping.gnss_epoch)
        self.trees: list[StreamedTree] = []
        self.closed: dict[tuple[float, float, int], float] = {}
        self.done_strips: dict[tuple, float] = {}  # partial strips: last processed frontier
        self.warnings: list[str] = []
        self.stats = {
            "regions_processed": 0,
            "duplicates_dropped": 0,
            "points_rejected": 0,
            "peak_window_points": 0,
            "peak_window_mb": 0.0,
            "segment_calls": 0,
        }
        self._hulls: dict[tuple, list[np.ndarray]] = {}
        self._finished: set[tuple] = set()
        self.now = np.nan
        self._estimators: dict[str, Any] | None = None  # the volume estimators, built once

    def __iter__(self) -> Iterator[StreamedTree]:
        s = self.settings
        for k, sweep in enumerate(self.source):
            self.now = sweep.time
            lever = getattr(
                self.source, "gnss_lever_arm", np.zeros(3)
            )  # the fixes are the antenna's
            self.georef.add_pose(sweep.time, sweep.pose[:3, 3] + sweep.pose[:3, :3] @ lever)
            changed = self.layout.update(sweep.pose[:2, 3])
            self._add(sweep.points)
            if changed or k % s.check_every == 0:
                yield from self._process_ready()
        self.layout.finish()
        yield from self._process_ready()
        self.warnings.extend(self.source.warnings)

    # -- window --------------------------------------------------------------------------
    def _add(self, points: PointCloud) -> None:
        if self.layout.axis is not None and (self.closed or self._hulls) and len(points):
            along, across = self.layout.to_row_frame(points.xyz[:, :2])
            finished = np.zeros(len(points), bool)
            for (lo, hi, sigma), before in self.closed.items():
                finished |= ClosedArea(lo, hi, sigma, before).contains(along, across)
            for hulls in self._hulls.values():
                for hull in hulls:
                    finished |= _inside_hull(points.xyz[:, :2], hull, 0.2)
            self.stats["points_rejected"] += int(finished.sum())
            points = points.select(np.flatnonzero(~finished))
        self.window.add(points)
        self.stats["peak_window_points"] = max(
            self.stats["peak_window_points"], self.window.n_points
        )
        self.stats["peak_window_mb"] = max(self.stats["peak_window_mb"], self.window.nbytes / 2**20)

    # -- regions -------------------------------------------------------------------------
    def _process_ready(self) -> Iterator[StreamedTree]:
        for state in self.layout.regions(self.settings.lag_m):
            if state.complete and state.key in self._finished and self.layout.axis is not None:
                continue  # closed: its points leave the window and new ones are rejected
            if state.complete:
                yield from self._process(state)
            elif state.partial:
                last = self.done_strips.get(state.key, -np.inf)
                if state.frontier - last >= self.settings.step_m:
                    yield from self._process(state)

    def _process(self, state: RegionState) -> Iterator[StreamedTree]:
        cloud = self.window.cloud()
        if len(cloud) == 0:
            self._close(state, np.inf)
            return
        if self.layout.axis is None:  # never drove a pass: the whole window is one region
            along, across = np.zeros(len(cloud)), np.zeros(len(cloud))
        else:
            along, across = self.layout.to_row_frame(cloud.xyz[:, :2])
        sel = (across > state.lo) & (across <= state.hi)
        progress = state.sigma * along
        if state.partial:
            sel &= progress < state.frontier
        idx = np.flatnonzero(sel)
        if len(idx) == 0:
            self._finish_region(state, np.zeros(len(cloud), bool), np.inf)
            return
        sub = cloud.select(idx)
        emitted, keep_from = self._trees_in(sub, state, progress[idx])
        drop = np.zeros(len(cloud), bool)
        for tree, members in emitted:
            drop[idx[members]] = True
            drop |= sel & _inside_hull(cloud.xyz[:, :2], tree.hull, 0.2)
            self._hulls.setdefault(state.key, []).append(tree.hull)
        if state.partial:
            boundary = min(state.frontier - self.settings.context_m, keep_from)
            drop |= sel & (progress < boundary)
        else:
            boundary = np.inf
            drop |= sel
        self._finish_region(state, drop, boundary)
        for tree, _ in emitted:
            yield tree

    def _finish_region(self, state: RegionState, drop: np.ndarray, boundary: float) -> None:
        self.window.drop(drop)
        self._close(state, boundary)
        self.stats["regions_processed"] += 1

    def _close(self, state: RegionState, boundary: float) -> None:
        if self.layout.axis is None:
            return
        if state.partial:
            key = (state.lo, state.hi, state.sigma)
            self.closed[key] = max(self.closed.get(key, -np.inf), boundary)
            self.done_strips[state.key] = state.frontier
        else:
            self.closed[(state.lo, state.hi, 1)] = np.inf
            self._hulls.pop(state.key, None)
            self._finished.add(state.key)

    # -- trees ---------------------------------------------------------------------------
    def _trees_in(
        self, sub: PointCloud, state: RegionState, progress: np.ndarray
    ) -> tuple[list[tuple[StreamedTree, np.ndarray]], float]:
        """Segment a finished stretch; the trees to emit and where the waiting ones begin."""
        from canopy_kit.results.tree_table import with_crown_contact, with_trunk_flags
        from canopy_kit.segment.verb import make_segmenter, segment
        from canopy_kit.volume.verb import build_estimators, measure_trees

        cfg = self.config
        direction = self._driving_direction()
        self.stats["segment_calls"] += 1
        try:
            seg = segment(
                sub,
                make_segmenter(cfg.segment.method, cfg.segment.params),
                cfg.preprocess,
                cfg.rows,
                driving_direction=direction,
                direction_source="trajectory" if direction is not None else None,
                seed=cfg.seed,
            )
        except InputError as exc:  # e.g. a region of bare ground: no canopy at all
            if "no points" not in str(exc):
                self.warnings.append(f"region {state.key}: {exc}")
            return [], np.inf
        labels = seg.labels
        keep_from = np.inf
        chosen: list[int] = []
        for sid in np.unique(labels[labels >= 0]):
            members = labels == sid
            if state.partial and progress[members].max() > state.frontier - self.settings.edge_m:
                keep_from = min(keep_from, float(progress[members].min()) - 0.1)
                continue
            centre = np.median(sub.xyz[members, :2], axis=0)
            if any(_inside_hull(centre[None], h, 0.3)[0] for h in self._hulls.get(state.key, [])):
                self.stats["duplicates_dropped"] += 1
                continue
            chosen.append(int(sid))
        if not chosen:
            return [], keep_from
        only = np.where(np.isin(labels, chosen), labels, -1)
        if self._estimators is None:
            self._estimators = build_estimators(cfg.volume)
        table = measure_trees(
            sub, only, cfg.volume, ground_height=seg.ground.height, estimators=self._estimators
        )
        # against every tree of the stretch, the waiting ones and those already emitted too
        table = with_crown_contact(table, sub.xyz, labels, cfg.volume)
        if seg.trunk_feet:  # a wall cut at its trunks: rows whose trunks were probably missed
            ids = table["segment"].map({t.segment_id: t.tree_id for t in seg.trees})
            table = with_trunk_flags(table, seg.trunk_feet, ids)
            warning = seg.trunk_feet.get("warning", "")
            if warning and table["trunk_flags"].astype(bool).any():
                self.warnings.append(f"region {state.key}: {warning}")
        out = []
        for rec in table.to_dict("records"):
            sid = int(rec["segment"])
            tree = StreamedTree(
                len(self.trees),
                rec,
                self.now,
                self._passed_at(rec),
                hull=np.asarray(seg.footprints.get(sid, np.zeros((0, 2)))),
            )
            self.trees.append(tree)
            out.append((tree, np.flatnonzero(labels == sid)))
        self._place([t for t, _ in out])
        return out, keep_from

    def _driving_direction(self) -> np.ndarray | None:
        from canopy_kit.segment.rows import driving_direction_from_trajectory

        _, xyz = self.georef.trajectory()
        try:
            return driving_direction_from_trajectory(xyz[:, :2]) if len(xyz) > 1 else None
        except InputError:
            return None

    def _passed_at(self, rec: dict[str, Any]) -> float:
        """When the robot was last abreast of the tree (the end of its closest visit)."""
        t, xyz = self.georef.trajectory()
        d = np.hypot(xyz[:, 0] - rec["x"], xyz[:, 1] - rec["y"])
        near = np.flatnonzero(d <= d.min() + 1.0)
        return float(t[near[-1]])

    def _place(self, new: list[StreamedTree]) -> None:
        """Georeference the new trees with the fit so far; provisional rows for all trees."""
        from canopy_kit.segment.rows import assign_rows

        fit = self.georef.fit(self.source.gnss, now=self.now)
        for tree in new:
            if fit is not None:
                xy = fit[:2, :2] @ [tree.values["x"], tree.values["y"]] + fit[:2, 3]
                tree.x, tree.y = float(xy[0]), float(xy[1])
                lat, lon, _ = self.georef.frame.to_wgs84(np.array([[tree.x, tree.y, 0.0]]))
                tree.lat, tree.lon = float(lat[0]), float(lon[0])
        xy = np.array([[t.values["x"], t.values["y"]] for t in self.trees])
        rows = assign_rows(xy, self.config.rows, self._driving_direction(), "trajectory")
        for tree in new:
            tree.row, tree.label = int(rows.row[tree.index]), rows.labels[tree.index]


def _inside_hull(xy: np.ndarray, hull: np.ndarray, buffer: float) -> np.ndarray:
    """Points ``xy`` (N, 2) inside a counter-clockwise convex ``hull`` grown by ``buffer``."""
    xy = np.atleast_2d(xy)
    if len(hull) < 3 or len(xy) == 0:
        return np.zeros(len(xy), bool)
    lo, hi = hull.min(axis=0) - buffer, hull.max(axis=0) + buffer
    box = np.all((xy >= lo) & (xy <= hi), axis=1)
    out = np.zeros(len(xy), bool)
    if not box.any():
        return out
    edges = np.roll(hull, -1, axis=0) - hull
    normals = np.column_stack([edges[:, 1], -edges[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    dist = np.einsum("nmk,mk->nm", xy[box, None, :] - hull[None], normals)
    out[box] = np.all(dist <= buffer, axis=1)
    return out
