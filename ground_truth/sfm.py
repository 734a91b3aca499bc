"""Structure from motion with pycolmap on the CPU, georeferenced to the photos' GPS positions.

Features: SIFT on images downscaled to ``max_image_size``. Pairs: every pair for small
flights, the GPS neighbours for larger ones (sequential pairs when the GPS positions are
too close together to tell neighbours apart). Mapping: incremental, with the GPS
positions as position priors in the local frame, then a robust similarity alignment of
the model onto those positions (``georeference``: levelled by the GPS or by the photos'
optical axes, whichever is more precise), so the model is in the same local metric
frame / CRS as the LiDAR map.

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

from canopy_kit.config import GroundTruthConfig
from canopy_kit.core.extras import needs_extra
from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import ProcessingError
from ground_truth.camera import PosedCamera
from ground_truth.exif import Flight

Progress = Callable[[str, float, float], None]


@dataclass
class SfmOptions:
    """Structure-from-motion settings (pycolmap names where they map one to one)."""

    max_image_size: int = GroundTruthConfig.max_image_size  # the default is the config's
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
    nadir_tilt_sigma_deg: float = 1.0  # how far a flight's mean optical axis may be off vertical
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
    alignment: dict = field(default_factory=dict)  # how the model was levelled and scaled

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
            "gps_residual_rms_vertical_m": float(np.sqrt(np.mean(r["dz"] ** 2)))
            if len(r)
            else np.nan,
            "gps_residual_max_m": float(np.sqrt(r["dx"] ** 2 + r["dy"] ** 2 + r["dz"] ** 2).max())
            if len(r)
            else np.nan,
            "matching": self.matching,
            "alignment": dict(self.alignment),
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


def _quiet_colmap():
    import zlib  # noqa: F401  (before pycolmap: see module docstring)

    with needs_extra("aerial"):
        import pycolmap

    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: the library does not print
    return pycolmap, previous


def run_sfm(
    flight: Flight,
    work_dir: str | Path,
    frame: LocalFrame | None = None,
    options: SfmOptions | None = None,
    progress: Progress | None = None,
) -> SparseModel:
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
        alignment = _align(pycolmap, rec, flight, gps, opts)
        if alignment["vertical_from"] == "gps":  # GPS good enough to fight doming with
            _refine_with_gps(pycolmap, rec, flight, gps, opts)
            alignment = _align(pycolmap, rec, flight, gps, opts)
        timings["georeferencing"] = time.perf_counter() - t0
        rec.write(str(work))
        return _to_model(rec, flight, gps, frame, matching, timings, alignment)
    finally:
        pycolmap.logging.minloglevel = previous_level


def _extract(pycolmap, flight: Flight, database: Path, opts: SfmOptions) -> None:
    width, height = flight.size
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    focal = flight.focal_px or 1.2 * max(width, height)  # COLMAP's own default guess
    extra = {"SIMPLE_PINHOLE": [], "PINHOLE": None, "SIMPLE_RADIAL": [0.0], "RADIAL": [0.0, 0.0]}
    if opts.camera_model not in extra or opts.camera_model == "PINHOLE":
        raise ProcessingError(
            f"SfM camera model {opts.camera_model} is not supported "
            "(SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL)"
        )
    params = [focal, width / 2.0, height / 2.0, *extra[opts.camera_model]]
    reader.camera_params = ",".join(f"{v:.6f}" for v in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = opts.num_threads
    extraction.max_image_size = opts.max_image_size
    extraction.sift.max_num_features = opts.max_num_features
    extraction.sift.first_octave = opts.first_octave
    pycolmap.extract_features(
        str(database),
        str(flight.folder),
        flight.names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def _write_position_priors(
    pycolmap,
    database: Path,
    flight: Flight,
    gps: np.ndarray,
    opts: SfmOptions,
) -> None:
    """Replace the WGS84 priors COLMAP read from EXIF by local-frame (Cartesian) ones."""
    by_name = dict(zip(flight.names, gps))
    cov = np.diag(
        [opts.gps_sigma_horizontal**2, opts.gps_sigma_horizontal**2, opts.gps_sigma_vertical**2]
    )
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


def _match(pycolmap, database: Path, matching: str, gps: np.ndarray, opts: SfmOptions) -> None:
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
        raise ProcessingError(
            f"SfM matching {matching!r} is not one of auto, exhaustive, spatial, sequential"
        )


def _map(
    pycolmap,
    database: Path,
    flight: Flight,
    work: Path,
    opts: SfmOptions,
    report: Progress,
):
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
    models = pycolmap.incremental_mapping(
        str(database),
        str(flight.folder),
        str(work / "models"),
        options=options,
        next_image_callback=next_image,
    )
    if not models:
        raise ProcessingError(
            f"{flight.folder}: structure from motion registered no images "
            "(too little overlap or texture between the photos?)"
        )
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    if best.num_reg_images() < max(3, opts.min_registered_fraction * n):
        raise ProcessingError(
            f"{flight.folder}: only {best.num_reg_images()} of {n} photos registered in one model "
            f"(need {opts.min_registered_fraction:.0%}); check overlap, blur and exposure"
        )
    report("SfM registration", n, n)
    return best


def _rotation_to_up(up: np.ndarray) -> np.ndarray:
    """The rotation that turns the unit vector ``up`` onto +z (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - c) / s**2)


def _levelled_fit(
    centres: np.ndarray, targets: np.ndarray, up: np.ndarray, inliers: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation, translation) mapping model ``up`` to +z: a horizontal similarity
    (Umeyama in 2-D) plus a height offset, fitted on the ``inliers``."""
    r0 = _rotation_to_up(up)
    level = centres @ r0.T
    a, b = level[inliers, :2], targets[inliers, :2]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    r2 = u @ d @ vt
    scale = float(np.trace(np.diag(sv) @ d) / max(np.sum((a - ma) ** 2), 1e-12))
    rz = np.eye(3)
    rz[:2, :2] = r2
    rotation = rz @ r0
    t = np.zeros(3)
    t[:2] = mb - scale * r2 @ ma
    t[2] = float(np.mean(targets[inliers, 2] - scale * level[inliers, 2]))
    return scale, rotation, t


def _umeyama(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (scale, rotation, translation) with b ≈ s R a + t."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.eye(a.shape[1])
    d[-1, -1] = np.sign(np.linalg.det(u @ vt))
    r = u @ d @ vt
    s = float(np.trace(np.diag(sv) @ d) / max(np.sum((a - ma) ** 2), 1e-12))
    return s, r, mb - s * r @ ma


def georeference(
    centres: np.ndarray,
    optical_axes: np.ndarray,
    targets: np.ndarray,
    options: SfmOptions | None = None,
) -> tuple[float, np.ndarray, np.ndarray, dict]:
    """Similarity (scale, rotation, translation) taking model camera centres onto GPS positions.

    Which way is up comes from two estimates, weighted by their precision: the tilt of a full
    least-squares similarity to the GPS (uncertainty: the per-axis GPS residual over the
    camera spread across the flight's narrowest direction), and minus the mean optical axis
    (``optical_axes``: world direction of each camera's +z; nadir photos look straight down;
    uncertainty: their scatter over √n, at least ``nadir_tilt_sigma_deg``). When the two
    differ by more than three combined sigmas, the GPS heights are taken as systematically
    wrong and only the photos level the model (nadir flights assumed, as the orthomosaic
    does). Measured on real consumer-camera photos: GPS altitude climbing 26 m in 30 s of
    level flight made the GPS-only fit tilt the model by 47°. Scale, heading and position then come from a
    horizontal similarity plus a height offset: a least-squares fit first tells how good the
    GPS is, a second drops fixes beyond three times that residual (a nominal accuracy would
    be wrong both ways: metre-level camera GPS, centimetre-level RTK). Returns also a dict
    saying what was decided.
    """
    opts = options or SfmOptions()
    centres, targets = np.asarray(centres, float), np.asarray(targets, float)
    n = len(centres)
    if (
        n < 3
        or np.ptp(targets[:, :2], axis=0).max() < 1e-6
        or np.ptp(centres, axis=0).max() < 1e-12
    ):
        raise ProcessingError(
            "the model could not be aligned to the photos' GPS positions "
            "(fewer than 3 registered photos, or all in one spot)"
        )
    axes = np.asarray(optical_axes, float)
    down = axes.mean(axis=0)
    down /= np.linalg.norm(down)
    scatter = np.arccos(np.clip(axes @ down, -1.0, 1.0))
    sigma_nadir = float(
        np.hypot(np.sqrt(np.mean(scatter**2) / n), np.radians(opts.nadir_tilt_sigma_deg))
    )
    s_full, r_full, t_full = _umeyama(centres, targets)
    res_full = s_full * centres @ r_full.T + t_full - targets
    sigma_axis = float(np.sqrt(np.sum(res_full**2) / max(3 * n - 7, 1)))
    xy = targets[:, :2] - targets[:, :2].mean(axis=0)
    narrow = np.linalg.eigh(xy.T @ xy)[1][:, 0]
    sigma_gps = sigma_axis / max(float(np.sqrt(np.sum((xy @ narrow) ** 2))), 1e-9)
    up_gps, up_nadir = r_full[2], -down  # r_full.T @ ẑ: the model direction the fit makes vertical
    tilt = float(np.arccos(np.clip(up_gps @ up_nadir, -1.0, 1.0)))
    # Far apart beyond both uncertainties: the GPS heights carry a systematic error (a drift
    # the tilted fit half absorbs, so its residual understates it); drop their vertical.
    consistent = tilt <= 3.0 * float(np.hypot(sigma_gps, sigma_nadir))
    w_gps, w_nadir = (1.0 / max(sigma_gps, 1e-9) ** 2 if consistent else 0.0), 1.0 / sigma_nadir**2
    up = w_gps * up_gps + w_nadir * up_nadir
    up /= np.linalg.norm(up)
    inliers = np.ones(n, bool)
    scale, rotation, t = _levelled_fit(centres, targets, up, inliers)
    res = np.linalg.norm(scale * centres @ rotation.T + t - targets, axis=1)
    rms = float(np.sqrt(np.mean(res**2)))
    inliers = res <= max(3.0 * rms, 3.0 * opts.gps_sigma_floor)
    if inliers.sum() >= 3 and not inliers.all():
        scale, rotation, t = _levelled_fit(centres, targets, up, inliers)
    info = {
        "vertical_from": "gps" if w_gps >= w_nadir else "camera_axes",
        "gps_weight": float(w_gps / (w_gps + w_nadir)),
        "gps_tilt_vs_camera_axes_deg": float(np.degrees(tilt)),
        "gps_tilt_consistent": bool(consistent),
        "gps_tilt_sigma_deg": float(np.degrees(sigma_gps)),
        "camera_axes_tilt_sigma_deg": float(np.degrees(sigma_nadir)),
        "gps_inliers": int(inliers.sum()),
        "scale": float(scale),
    }
    return scale, rotation, t, info


def _align(pycolmap, rec, flight: Flight, gps: np.ndarray, opts: SfmOptions) -> dict:
    """Move the model onto the GPS positions (``georeference``); returns what was decided."""
    by_name = dict(zip(flight.names, gps))
    images = list(rec.images.values())
    targets = np.array([by_name[im.name] for im in images]).reshape(-1, 3)
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    axes = np.array([im.cam_from_world().rotation.matrix()[2] for im in images]).reshape(-1, 3)
    try:
        scale, rotation, t, info = georeference(centres, axes, targets, opts)
    except ProcessingError as exc:
        raise ProcessingError(f"{flight.folder}: {exc}") from None
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), t))
    return info


def _refine_with_gps(pycolmap, rec, flight: Flight, gps: np.ndarray, opts: SfmOptions) -> None:
    """Bundle adjustment with GPS position priors as tight as the GPS turns out to be.

    A nadir block from one altitude bends into a dome (radial distortion trades against
    curvature): measured 0.2 m ground shifts between photos with loose priors, 0.07 m
    after this step. The prior sigma is the RMS residual of the aligned model, floored.
    """
    by_name = dict(zip(flight.names, gps))
    images = list(rec.images.values())
    res = np.array([im.projection_center() - by_name[im.name] for im in images])
    sigma_h = max(
        float(np.sqrt(np.mean(res[:, 0] ** 2 + res[:, 1] ** 2) / 2)), opts.gps_sigma_floor
    )
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
    ba.refine_focal_length = (
        opts.refine_focal_length
        if opts.refine_focal_length is not None
        else flight.focal_px is None
    )
    ba.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    prior_options = pycolmap.PosePriorBundleAdjustmentOptions()
    prior_options.ceres.prior_position_loss_function_type = pycolmap.LossFunctionType.CAUCHY
    adjuster = pycolmap.create_pose_prior_bundle_adjuster(ba, prior_options, config, priors, rec)
    adjuster.solve()


def _to_model(
    rec,
    flight: Flight,
    gps: np.ndarray,
    frame: LocalFrame,
    matching: str,
    timings: dict[str, float],
    alignment: dict,
) -> SparseModel:
    cameras: dict[str, PosedCamera] = {}
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        m = pose.matrix()
        cameras[image.name] = PosedCamera(
            image.name,
            cam.model.name,
            tuple(float(v) for v in cam.params),
            int(cam.width),
            int(cam.height),
            np.array(m[:, :3]),
            np.array(m[:, 3]),
        )
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
    return SparseModel(
        frame,
        cameras,
        points,
        colors,
        errors,
        tracks,
        unregistered,
        residuals,
        float(rec.compute_mean_reprojection_error()),
        matching,
        timings,
        alignment,
    )
