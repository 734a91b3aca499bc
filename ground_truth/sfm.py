"""Structure from motion with pycolmap on the CPU, georeferenced to the photos' GPS positions.

Features: SIFT on images downscaled to ``max_image_size``. Pairs: every pair for small
flights, the GPS neighbours for larger ones (sequential pairs when the GPS positions are
too close together to tell neighbours apart). Mapping: incremental, with the GPS
positions as position priors in the local frame, then a robust similarity alignment of
the model onto those positions (``align_reconstruction_to_locations``), so the model is
in the same local metric frame / CRS as the LiDAR map.

Trap (measured): after ``import pycolmap`` (4.2 wheel) zlib use could crash the process
unless zlib was imported first; ``import zlib`` comes before every pycolmap import.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.errors import ProcessingError
from canopy_kit.geo import LocalFrame
from ground_truth.camera import PosedCamera
from ground_truth.exif import Flight

Progress = Callable[[str, float, float], None]


@dataclass
class SfmOptions:
    """Structure-from-motion settings (pycolmap names where they map one to one)."""

    max_image_size: int = 1600
    max_num_features: int = 8192
    first_octave: int = 0
    matching: str = "auto"  # auto | exhaustive | spatial | sequential
    exhaustive_max_images: int = 30
    spatial_neighbors: int = 30
    sequential_overlap: int = 10
    camera_model: str = "SIMPLE_RADIAL"
    refine_focal_length: bool | None = None  # None: only when EXIF states no focal length
    gps_sigma_horizontal: float = 1.0
    gps_sigma_vertical: float = 2.0
    gps_sigma_floor: float = 0.01
    min_registered_fraction: float = 0.5
    num_threads: int = -1
    seed: int = 0


@dataclass
class SparseModel:
    """A georeferenced sparse reconstruction as plain arrays, with its quality report."""

    frame: LocalFrame
    cameras: dict[str, PosedCamera]
    points: np.ndarray  # (N, 3) local frame
    colors: np.ndarray  # (N, 3) uint8
    point_errors: np.ndarray  # (N,) mean reprojection error, px
    track_lengths: np.ndarray  # (N,)
    unregistered: list[str]
    gps_residuals: pd.DataFrame  # image, dx, dy, dz (camera centre minus GPS), metres
    mean_reprojection_error_px: float
    matching: str
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def n_registered(self) -> int:
        return len(self.cameras)

    def report(self) -> dict:
        """The numbers a user checks first: registration, reprojection error, GPS residuals."""
        r = self.gps_residuals
        horiz = np.hypot(r["dx"], r["dy"]) if len(r) else np.array([np.nan])
        return {
            "registered_images": self.n_registered,
            "total_images": self.n_registered + len(self.unregistered),
            "unregistered": list(self.unregistered),
            "points": int(len(self.points)),
            "mean_reprojection_error_px": self.mean_reprojection_error_px,
            "gps_residual_rms_horizontal_m": float(np.sqrt(np.mean(horiz**2))),
            "gps_residual_rms_vertical_m": float(np.sqrt(np.mean(r["dz"] ** 2))) if len(r) else np.nan,
            "gps_residual_max_m": float(np.sqrt(r["dx"]**2 + r["dy"]**2 + r["dz"]**2).max())
            if len(r) else np.nan,
            "matching": self.matching,
            "timings_s": dict(self.timings),
        }


def choose_matching(positions: np.ndarray, options: SfmOptions) -> str:
    """Exhaustive for small flights; else GPS neighbours, or capture order if GPS is degenerate."""
    if options.matching != "auto":
        return options.matching
    n = len(positions)
    if n <= options.exhaustive_max_images:
        return "exhaustive"
    d = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    return "spatial" if spacing > 3.0 * options.gps_sigma_horizontal else "sequential"


def _neighbour_distance(positions: np.ndarray) -> float:
    """A search radius covering the overlapping photos of a survey (several photo spacings)."""
    d = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(8.0 * np.median(d.min(axis=1)))


def _quiet_colmap():  # noqa: ANN202
    import zlib  # noqa: F401  (before pycolmap: see module docstring)

    import pycolmap

    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: the library does not print
    return pycolmap, previous


def run_sfm(flight: Flight, work_dir: str | Path, frame: LocalFrame | None = None,
            options: SfmOptions | None = None, progress: Progress | None = None) -> SparseModel:
    """Reconstruct the flight with pycolmap and georeference it into ``frame``."""
    opts = options or SfmOptions()
    report = progress or (lambda *_: None)
    frame = frame or flight.default_frame()
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    if database.exists():
        database.unlink()
    pycolmap, previous_level = _quiet_colmap()
    try:
        pycolmap.set_random_seed(opts.seed)
        gps = flight.local_positions(frame)
        timings: dict[str, float] = {}

        t0 = time.perf_counter()
        report("SfM features", 0, len(flight.images))
        _extract(pycolmap, flight, database, opts)
        _write_position_priors(pycolmap, database, flight, gps, opts)
        timings["features"] = time.perf_counter() - t0
        report("SfM features", len(flight.images), len(flight.images))

        t0 = time.perf_counter()
        matching = choose_matching(gps, opts)
        _match(pycolmap, database, matching, gps, opts)
        timings["matching"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        rec = _map(pycolmap, database, flight, work, opts, report)
        timings["mapping"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        _align(pycolmap, rec, flight, gps, opts)
        _refine_with_gps(pycolmap, rec, flight, gps, opts)
        _align(pycolmap, rec, flight, gps, opts)
        timings["georeferencing"] = time.perf_counter() - t0
        rec.write(str(work))
        return _to_model(rec, flight, gps, frame, matching, timings)
    finally:
        pycolmap.logging.minloglevel = previous_level


def _extract(pycolmap, flight: Flight, database: Path, opts: SfmOptions) -> None:  # noqa: ANN001
    width, height = flight.size
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    focal = flight.focal_px or 1.2 * max(width, height)  # COLMAP's own default guess
    extra = {"SIMPLE_PINHOLE": [], "PINHOLE": None, "SIMPLE_RADIAL": [0.0], "RADIAL": [0.0, 0.0]}
    if opts.camera_model not in extra or opts.camera_model == "PINHOLE":
        raise ProcessingError(f"SfM camera model {opts.camera_model} is not supported "
                              "(SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL)")
    params = [focal, width / 2.0, height / 2.0, *extra[opts.camera_model]]
    reader.camera_params = ",".join(f"{v:.6f}" for v in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = opts.num_threads
    extraction.max_image_size = opts.max_image_size
    extraction.sift.max_num_features = opts.max_num_features
    extraction.sift.first_octave = opts.first_octave
    pycolmap.extract_features(str(database), str(flight.folder), flight.names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)


def _write_position_priors(pycolmap, database: Path, flight: Flight, gps: np.ndarray,  # noqa: ANN001
                           opts: SfmOptions) -> None:
    """Replace the WGS84 priors COLMAP read from EXIF by local-frame (Cartesian) ones."""
    by_name = dict(zip(flight.names, gps))
    cov = np.diag([opts.gps_sigma_horizontal**2, opts.gps_sigma_horizontal**2,
                   opts.gps_sigma_vertical**2])
    db = pycolmap.Database.open(str(database))
    try:
        existing = {p.corr_data_id.id: p for p in db.read_all_pose_priors()}
        for image in db.read_all_images():
            prior = existing.get(image.image_id)
            if prior is None:
                prior = pycolmap.PosePrior()
                prior.corr_data_id = image.data_id
            prior.position = np.asarray(by_name[image.name], float)
            prior.position_covariance = cov
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            if image.image_id in existing:
                db.update_pose_prior(prior)
            else:
                db.write_pose_prior(prior)
    finally:
        db.close()


def _match(pycolmap, database: Path, matching: str, gps: np.ndarray, opts: SfmOptions) -> None:  # noqa: ANN001
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = opts.num_threads
    kw = {"matching_options": options, "device": pycolmap.Device.cpu}
    if matching == "exhaustive":
        pycolmap.match_exhaustive(str(database), **kw)
    elif matching == "spatial":
        pairing = pycolmap.SpatialPairingOptions()
        pairing.ignore_z = True
        pairing.max_num_neighbors = opts.spatial_neighbors
        pairing.max_distance = _neighbour_distance(gps)
        pycolmap.match_spatial(str(database), pairing_options=pairing, **kw)
    elif matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = opts.sequential_overlap
        pycolmap.match_sequential(str(database), pairing_options=pairing, **kw)
    else:
        raise ProcessingError(f"SfM matching {matching!r} is not one of auto, exhaustive, "
                              "spatial, sequential")


def _map(pycolmap, database: Path, flight: Flight, work: Path, opts: SfmOptions,  # noqa: ANN001
         report: Progress):  # noqa: ANN202
    n = len(flight.images)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = opts.num_threads
    options.random_seed = opts.seed
    options.use_prior_position = True
    options.use_robust_loss_on_prior_position = True
    options.multiple_models = True
    # Nadir photos from one altitude cannot separate focal length from flying height
    # (measured: refined focal +2.8 %, ground 0.98 m too low); trust the EXIF focal.
    refine = opts.refine_focal_length
    options.ba_refine_focal_length = flight.focal_px is None if refine is None else refine
    options.mapper.abs_pose_refine_focal_length = options.ba_refine_focal_length
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        report("SfM registration", min(registered[0] + 1, n), n)

    report("SfM registration", 0, n)
    models = pycolmap.incremental_mapping(str(database), str(flight.folder), str(work / "models"),
                                          options=options, next_image_callback=next_image)
    if not models:
        raise ProcessingError(f"{flight.folder}: structure from motion registered no images "
                              "(too little overlap or texture between the photos?)")
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    if best.num_reg_images() < max(3, opts.min_registered_fraction * n):
        raise ProcessingError(
            f"{flight.folder}: only {best.num_reg_images()} of {n} photos registered in one model "
            f"(need {opts.min_registered_fraction:.0%}); check overlap, blur and exposure")
    report("SfM registration", n, n)
    return best


def _align(pycolmap, rec, flight: Flight, gps: np.ndarray, opts: SfmOptions) -> None:  # noqa: ANN001
    """Similarity transform of the model onto the GPS positions.

    A least-squares fit over all photos first tells how good the GPS is; a robust fit
    with an inlier threshold of three times that residual then drops gross fixes. A
    threshold from a nominal GPS accuracy would be wrong both ways: consumer-camera GPS
    lagging by a photo (measured: 15 m RMS) or RTK at a few centimetres.
    """
    by_name = dict(zip(flight.names, gps))
    names = [im.name for im in rec.images.values()]
    targets = np.array([by_name[n] for n in names])
    centres = np.array([im.projection_center() for im in rec.images.values()])
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 1e6  # every photo an inlier: plain least squares
    sim3 = pycolmap.align_reconstruction_to_locations(rec, names, targets, 3, ransac)
    if sim3 is None:
        raise ProcessingError(f"{flight.folder}: the model could not be aligned to the photos' GPS "
                              "positions (fewer than 3 registered photos, or all in one spot)")
    moved = np.array([sim3 * c for c in centres])
    rms = float(np.sqrt(np.mean(np.sum((moved - targets) ** 2, axis=1))))
    ransac.max_error = max(3.0 * rms, 3.0 * opts.gps_sigma_floor)
    robust = pycolmap.align_reconstruction_to_locations(rec, names, targets, 3, ransac)
    rec.transform(robust if robust is not None else sim3)


def _refine_with_gps(pycolmap, rec, flight: Flight, gps: np.ndarray, opts: SfmOptions) -> None:  # noqa: ANN001
    """Bundle adjustment with GPS position priors as tight as the GPS turns out to be.

    A nadir block from one altitude bends into a dome (radial distortion trades against
    curvature): measured 0.2 m ground shifts between photos with loose priors, 0.07 m
    after this step. The prior sigma is the RMS residual of the aligned model, floored.
    """
    by_name = dict(zip(flight.names, gps))
    images = list(rec.images.values())
    res = np.array([im.projection_center() - by_name[im.name] for im in images])
    sigma_h = max(float(np.sqrt(np.mean(res[:, 0] ** 2 + res[:, 1] ** 2) / 2)), opts.gps_sigma_floor)
    sigma_v = max(float(np.sqrt(np.mean(res[:, 2] ** 2))), 2 * opts.gps_sigma_floor)
    priors = []
    for im in images:
        prior = pycolmap.PosePrior()
        prior.corr_data_id = im.data_id
        prior.position = np.asarray(by_name[im.name], float)
        prior.position_covariance = np.diag([sigma_h**2, sigma_h**2, sigma_v**2])
        prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        priors.append(prior)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = opts.refine_focal_length if opts.refine_focal_length is not None \
        else flight.focal_px is None
    ba.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    prior_options = pycolmap.PosePriorBundleAdjustmentOptions()
    prior_options.ceres.prior_position_loss_function_type = pycolmap.LossFunctionType.CAUCHY
    adjuster = pycolmap.create_pose_prior_bundle_adjuster(ba, prior_options, config, priors, rec)
    adjuster.solve()


def _to_model(rec, flight: Flight, gps: np.ndarray, frame: LocalFrame, matching: str,  # noqa: ANN001
              timings: dict[str, float]) -> SparseModel:
    cameras: dict[str, PosedCamera] = {}
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        m = pose.matrix()
        cameras[image.name] = PosedCamera(image.name, cam.model.name, tuple(float(v) for v in cam.params),
                                          int(cam.width), int(cam.height), np.array(m[:, :3]),
                                          np.array(m[:, 3]))
    ids = list(rec.points3D.keys())
    pts = rec.points3D
    points = np.array([pts[i].xyz for i in ids]).reshape(-1, 3)
    colors = np.array([pts[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    errors = np.array([pts[i].error for i in ids], dtype=float)
    tracks = np.array([pts[i].track.length() for i in ids], dtype=int)
    by_name = dict(zip(flight.names, gps))
    names = sorted(cameras)
    res = np.array([cameras[n].center - by_name[n] for n in names]).reshape(-1, 3)
    residuals = pd.DataFrame({"image": names, "dx": res[:, 0], "dy": res[:, 1], "dz": res[:, 2]})
    unregistered = [n for n in flight.names if n not in cameras]
    return SparseModel(frame, cameras, points, colors, errors, tracks, unregistered, residuals,
                       float(rec.compute_mean_reprojection_error()), matching, timings)
