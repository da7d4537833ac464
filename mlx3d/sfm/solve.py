"""Cameras from photos: pycolmap's SIFT features, matching and incremental mapping, written as a dataset.

:func:`solve_poses` turns a folder of photos (or frames taken from a video,
:mod:`.video`) into a COLMAP workspace that :func:`mlx3d.datasets.load_dataset`
reads::

    OUT/images/         the photos solved (copies; EXIF rotation applied; WebP as PNG; spaces as _)
    OUT/sparse/0/       cameras.bin, images.bin, points3D.bin (COLMAP's binary model)
    OUT/poses.json      what was solved: photos registered, reprojection error, timings

Stages, each reported through ``progress(stage, done, total)`` and each
cancellable: ``photos`` (copying), ``features`` (SIFT on images scaled to at
most ``max_image_size`` pixels), ``matching`` (every pair for small sets,
neighbours in name order for videos and long walks, see :func:`choose_matching`),
``mapping`` (COLMAP's incremental mapper from three first pairs; the best
result is kept, see below).

Choices that differ from COLMAP's defaults, each for a kind of capture that
failed without it:

- one camera for all photos when they share a size (a phone or a video), with
  COLMAP's focal-length prior from EXIF when the photos carry one;
- SIFT keeps features of half COLMAP's contrast (:data:`SIFT_PEAK_THRESHOLD`):
  on a full orbit of a small object the views from above, each matching few
  others, were placed up to 3.2 degrees off with COLMAP's threshold, 1.0 with
  this one; four other rendered captures placed as well or better;
- the first image pair may be one camera walking straight towards the other
  (``init_max_forward_motion`` 1.0, COLMAP 0.95): a handheld walk down a
  street has no other kind of pair, and only 2 of ``lund``'s 29 photos
  registered without it;
- the mapper runs from first image pairs seen 16, 8 and (while no run placed
  every photo) 4 degrees apart (:data:`INITIAL_PAIR_ANGLES`), and keeps the scene with the
  most photos placed, then the smallest reprojection error: on ``lund`` the
  default 16 degrees gives a two-photo scene whose focal length runs away
  while 8 degrees places 27-28 of 29; on a rendered walk 16 degrees places
  every photo on a bent path (37 degrees and 57% of its length off the
  truth, 0.90 px) and 8 degrees on the true one (1.2 degrees, 0.7%, 0.62 px);
- a photo joins the scene with 15 inlier matches (COLMAP 30) and an inlier
  ratio of 0.1 (COLMAP 0.25): on a full orbit of a small object the photos
  looking down at its roof each match few others, and 41 of 60 joined with
  COLMAP's thresholds, all 60 with these;
- a pair's geometric check gives up after 2,000 RANSAC trials
  (:data:`VERIFICATION_MAX_TRIALS`, COLMAP 10,000): most of matching's time
  went to pairs that do not overlap, which run every trial; on a 50-photo
  orbit this took matching from 37 s to 26 s with the same 454 pairs and
  the same inliers kept;
- fixed random seeds (matching's RANSAC and the mapper) and the project's
  thread count (:func:`mlx3d.render.raster_cpu.get_num_threads`: the cores
  this process may use, or ``MLX3D_NUM_THREADS``), not every core of the
  machine: solves of the same photos agree closely, though not bit for bit
  (threads finish in any order; a 24-photo orbit's reprojection error
  varied in its sixth digit at 8 threads, in its fifteenth at 2).

Lens distortion is kept as COLMAP estimates it (``SIMPLE_RADIAL``; the
renderer draws the same model, :mod:`mlx3d.cameras`' ``'opencv'``) unless it
moves no pixel by more than :data:`PINHOLE_TOLERANCE`, when the cameras are
written as ``PINHOLE``. The photos are never resampled, so alpha channels
and full resolution survive.

The solved scene is then set upright (:func:`.orient.upright`: gravity from
the cameras' up vectors to ``+Z``, the middle of what they look at at the
origin, their median distance from it 4 units).

The work happens in a scratch folder beside ``OUT``, renamed to ``OUT`` only
when everything succeeded: a failed or cancelled solve leaves nothing.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import PosesError
from .orient import upright

#: Image file suffixes read as photos (case-insensitive).
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
#: Of those, the ones pycolmap's image reader cannot decode: copied as ``NAME.png`` (lossless).
CONVERTED = (".webp",)
MATCHING = ("auto", "exhaustive", "sequential")
#: ``auto`` matches every pair up to this many photos, neighbours in name order above it.
EXHAUSTIVE_MAX = 100
#: SIFT's contrast threshold, half COLMAP's 0.02 / 3: more features on small photos and faint textures.
SIFT_PEAK_THRESHOLD = 0.01 / 3
#: Features and matching run in this many parts, each a progress report (pycolmap reports none itself).
PROGRESS_STEPS = 10
#: RANSAC trials before a pair's geometric check gives up (COLMAP: 10,000).
VERIFICATION_MAX_TRIALS = 2000
#: Sequential matching: each photo is matched with this many next ones (and, quadratically, farther ones).
SEQUENTIAL_OVERLAP = 15
#: Pixels: distortion that moves no pixel more than this is written as a pinhole camera.
PINHOLE_TOLERANCE = 0.5
#: The mapper runs once for each of these least angles (degrees) between the rays of its first image pair
#: (COLMAP's default 16 first; the last only while no run placed every photo); the scene with the most
#: photos placed, then the smallest reprojection error, is kept.
INITIAL_PAIR_ANGLES = (16.0, 8.0, 4.0)
#: Default for ``min_registered``: refuse a result that registers fewer than this fraction of the photos.
MIN_REGISTERED = 0.5
PYCOLMAP_PIN = "4.2.1"

StageProgress = Optional[Callable[[str, int, int], None]]


@dataclass
class PosesResult:
    """What :func:`solve_poses` solved (also written as ``OUT/poses.json``).

    registered / unregistered: photo names (relative to ``OUT/images``);
    reprojection_error: mean over every observation, pixels;
    points: sparse points written; focal: the solved focal length in pixels
    (the first camera's); focal_prior: whether EXIF gave one to start from;
    seconds: wall time per stage; transform: the 4x4 similarity that set the
    solved scene upright (applied already)."""

    out: str
    photos: int
    registered: list = field(default_factory=list)
    unregistered: list = field(default_factory=list)
    reprojection_error: float = float("nan")
    points: int = 0
    matching: str = ""
    camera_model: str = ""
    focal: float = float("nan")
    focal_prior: bool = False
    seconds: dict = field(default_factory=dict)
    transform: list = field(default_factory=list)

    def summary(self) -> str:
        """One line for a person: registered/total, error, points, matching."""
        return (f"{len(self.registered)} of {self.photos} photos registered, mean reprojection error "
                f"{self.reprojection_error:.2f} px, {self.points:,} points ({self.matching} matching, "
                f"{self.camera_model} focal {self.focal:.0f} px{' from an EXIF prior' if self.focal_prior else ''})")


def require_pycolmap():
    """The ``pycolmap`` module, or a :class:`PosesError` saying how to get it or what to do instead."""
    try:
        import pycolmap
    except ImportError as exc:
        raise PosesError(
            f"solving cameras from photos needs pycolmap, which is not installed here ({exc}). Install it with "
            f"`pip install \"mlx3d-splat[poses]\"` (or `pip install pycolmap=={PYCOLMAP_PIN}`); it has wheels for "
            "Linux x86-64, macOS arm64 and Windows x64. Elsewhere, solve the cameras with COLMAP and pass its "
            "workspace (images/ and sparse/0) to `mlx3d train`.") from None
    return pycolmap


def list_photos(folder) -> list[str]:
    """Photo file names in ``folder`` (not its subfolders), sorted; a PosesError when there are none."""
    root = Path(folder)
    if not root.is_dir():
        raise PosesError(f"{root}: not a folder of photos")
    names = sorted(p.name for p in root.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if not names:
        raise PosesError(f"{root}: no photos found (looked for {', '.join(PHOTO_SUFFIXES)})")
    return names


def needs_solve(path) -> bool:
    """True for a video or a folder that is not a dataset (photos without poses); False for a dataset.
    A missing path raises the dataset's error; a folder with neither a dataset nor photos says both."""
    from mlx3d.datasets import DatasetError, detect_format

    from .video import is_video

    if is_video(path):
        return True
    try:
        detect_format(path)
        return False
    except DatasetError as exc:
        if not os.path.isdir(path):
            raise
        try:
            list_photos(path)
        except PosesError:
            raise DatasetError(f"{exc}; and it holds no photos to solve cameras from") from None
        return True


def poses_folder(out, poses_out=None) -> str:
    """Where cameras solved for training go: ``poses_out``, else the output file's name + ``_poses`` beside it."""
    return os.fspath(poses_out) if poses_out else os.path.splitext(os.path.abspath(out))[0] + "_poses"


def choose_matching(matching: str, count: int, video: bool) -> str:
    """``exhaustive`` or ``sequential`` for ``matching`` (one of :data:`MATCHING`): ``auto`` matches
    every pair of up to :data:`EXHAUSTIVE_MAX` photos, and neighbours in order for videos and larger sets."""
    if matching not in MATCHING:
        raise PosesError(f"matching must be one of {', '.join(MATCHING)}, got {matching!r}")
    if matching != "auto":
        return matching
    return "sequential" if video or count > EXHAUSTIVE_MAX else "exhaustive"


def image_pairs(names: list[str], kind: str) -> list[tuple[str, str]]:
    """The photo pairs to match: every pair (``exhaustive``), or each photo with the next
    :data:`SEQUENTIAL_OVERLAP` in name order and, quadratically, with photos 2, 4, 8, ... ahead
    (``sequential``, as COLMAP's sequential matching with ``quadratic_overlap``)."""
    count = len(names)
    if kind == "exhaustive":
        return [(names[i], names[j]) for i in range(count) for j in range(i + 1, count)]
    pairs = set()
    for i in range(count):
        for k in range(SEQUENTIAL_OVERLAP):
            for j in (i + k + 1, i + 2 ** (k + 1)):
                if j < count:
                    pairs.add((i, j))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


def _chunks(items: list, count: int) -> list[list]:
    """``items`` in about ``count`` consecutive runs (fewer when there are fewer items)."""
    size = max(1, math.ceil(len(items) / count))
    return [items[i:i + size] for i in range(0, len(items), size)]


def _copy_photos(source: Path, names: list[str], images: Path, progress, should_stop) -> list[tuple[str, tuple[int, int]]]:
    """Copy the photos into ``images``, applying EXIF rotation (a rotated copy keeps the rest of its EXIF);
    a photo in a format COLMAP cannot read (:data:`CONVERTED`) is written as ``NAME.png``, and white space in
    a name becomes ``_`` (COLMAP's lists of image pairs separate names by white space).

    Returns each photo's (name as copied, (width, height) as copied)."""
    from PIL import Image, ImageOps

    images.mkdir(parents=True)
    copied = []
    for i, name in enumerate(names):
        if should_stop is not None and should_stop():
            raise KeyboardInterrupt
        src = source / name
        convert = src.suffix.lower() in CONVERTED
        dst = images / re.sub(r"\s", "_", name + ".png" if convert else name)
        if dst.exists():
            raise PosesError(f"{source}: two photos would be copied as {dst.name} ({name} and another); rename one")
        try:
            with Image.open(src) as im:
                orientation = im.getexif().get(0x0112, 1)
                if orientation in (2, 3, 4, 5, 6, 7, 8) or convert:
                    upright_im = ImageOps.exif_transpose(im)
                    exif = upright_im.getexif()
                    quality = {"quality": 95} if dst.suffix.lower() in (".jpg", ".jpeg") else {}
                    upright_im.save(dst, exif=exif.tobytes(), **quality)
                    size = upright_im.size
                else:
                    size = im.size
                    shutil.copyfile(src, dst)
        except OSError as exc:
            raise PosesError(f"{src}: cannot read this photo: {exc}") from None
        copied.append((dst.name, size))
        if progress is not None:
            progress("photos", i + 1, len(names))
    return copied


def _run_stage(pycolmap, stage: str, work: Callable, done, total: int, progress, should_stop):
    """Run ``work(token)`` in a thread; meanwhile report ``done`` (a number, or a callable polled) of
    ``total`` as progress and cancel on request.

    Ctrl+C (KeyboardInterrupt in this thread) or ``should_stop()`` cancels pycolmap's work, waits for it to
    stop and raises KeyboardInterrupt. pycolmap's database is never read meanwhile: it has its own SQLite,
    and a second copy of SQLite on the same file in one process breaks its locks."""
    token = pycolmap.CancellationToken()
    outcome: dict = {}

    def target():
        try:
            outcome["value"] = work(token)
        except BaseException as exc:  # noqa: BLE001 - handed to the calling thread
            outcome["error"] = exc

    thread = threading.Thread(target=target, name=f"mlx3d-poses-{stage}", daemon=True)
    thread.start()
    try:
        while thread.is_alive():
            if should_stop is not None and should_stop():
                token.cancel()
            if progress is not None:
                progress(stage, min(done() if callable(done) else done, total), total)
            thread.join(0.1)
    except BaseException:
        token.cancel()
        thread.join()
        raise
    if token.is_cancelled:
        raise KeyboardInterrupt
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


def _max_distortion(camera) -> float:
    """Pixels: the largest shift SIMPLE_RADIAL's ``k`` gives any pixel (at the farthest image corner)."""
    f, cx, cy, k = (float(v) for v in camera.params[:4])
    corner = max(math.hypot(x - cx, y - cy) for x in (0, camera.width) for y in (0, camera.height))
    r = corner / f
    return abs(k) * r * r * corner


def _write_model(pycolmap, rec, sparse: Path) -> tuple[str, np.ndarray]:
    """Write ``rec`` into ``sparse`` (COLMAP binary), as PINHOLE cameras where distortion is negligible."""
    models = set()
    for cam_id, cam in rec.cameras.items():
        if cam.model_name == "SIMPLE_RADIAL" and _max_distortion(cam) <= PINHOLE_TOLERANCE:
            f, cx, cy = (float(v) for v in cam.params[:3])
            rec.camera(cam_id).model = pycolmap.CameraModelId.PINHOLE
            rec.camera(cam_id).params = [f, f, cx, cy]
        models.add(rec.camera(cam_id).model_name)
    sparse.mkdir(parents=True)
    rec.write_binary(str(sparse))
    for extra in ("rigs.bin", "frames.bin"):  # COLMAP 4's rig records: one trivial rig per camera here
        (sparse / extra).unlink(missing_ok=True)
    return "/".join(sorted(models))


def _mapping_options(pycolmap, seed: int, init_angle: float):
    from mlx3d.render.raster_cpu import get_num_threads

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.mapper.random_seed = seed
    options.triangulation.random_seed = seed
    options.mapper.init_max_forward_motion = 1.0
    options.mapper.init_min_tri_angle = init_angle
    options.mapper.abs_pose_min_num_inliers = 15  # COLMAP 30 and 0.25: photos seen by few others still join
    options.mapper.abs_pose_min_inlier_ratio = 0.1
    options.num_threads = get_num_threads()
    return options


def _cameras_of(rec):
    """mlx3d Cameras (pinhole intrinsics; only the poses matter to :func:`upright`) of ``rec``'s registered images."""
    from mlx3d.cameras import Camera

    cameras = []
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        cam = image.camera
        view = np.eye(4)
        view[:3, :] = image.cam_from_world().matrix()
        cameras.append(Camera(cam.width, cam.height, float(cam.params[0]), float(cam.params[0]),
                              cam.width / 2, cam.height / 2, view))
    return cameras


def _quiet(pycolmap, verbose: bool):
    """COLMAP logs every step to stderr: errors only unless ``verbose``. Returns the previous level."""
    previous = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2  # glog's ERROR
    return previous


def solve_poses(photos, out, *, matching: str = "auto", max_image_size: int = 1600,
                min_registered: float = MIN_REGISTERED, seed: int = 0, video: bool = False,
                progress: StageProgress = None, should_stop: Optional[Callable[[], bool]] = None,
                verbose: bool = False) -> PosesResult:
    """Solve the cameras of the photos in folder ``photos`` and write the dataset ``out`` (module doc).

    matching: one of :data:`MATCHING` (:func:`choose_matching`); video: the photos are a video's frames in
    order (``auto`` then matches neighbours). max_image_size: features are found on photos scaled to at
    most this many pixels on their longer side (positions are in full-size pixels). min_registered:
    fraction of the photos that must register, else a PosesError names the unregistered ones. progress:
    ``(stage, done, total)``, called from this thread; should_stop: polled about every 0.1 s, True cancels.
    A cancel (or Ctrl+C) raises KeyboardInterrupt and leaves nothing behind. ``out`` must not exist or be an
    empty folder.
    """
    from mlx3d.render.raster_cpu import get_num_threads

    pycolmap = require_pycolmap()
    source, out = Path(photos), Path(out)
    names = list_photos(source)
    if len(names) < 3:
        raise PosesError(f"{source}: {len(names)} photo(s); solving cameras needs at least 3 (20 or more for a good capture)")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PosesError(f"{out}: already exists and is not an empty folder; choose a new output folder")
    if not 0.0 < min_registered <= 1.0:
        raise PosesError(f"min_registered must be a fraction in (0, 1], got {min_registered!r}")
    if int(max_image_size) < 64:
        raise PosesError(f"max_image_size must be at least 64 pixels, got {max_image_size!r}")
    kind = choose_matching(matching, len(names), video)

    out.parent.mkdir(parents=True, exist_ok=True)
    work = out.parent / f".{out.name}.partial-{secrets.token_hex(4)}"
    scratch = work / ".scratch"
    images, database = work / "images", work / ".scratch" / "database.db"
    seconds: dict = {}
    previous_level = _quiet(pycolmap, verbose)
    try:
        t0 = time.perf_counter()
        copied = _copy_photos(source, names, images, progress, should_stop)
        names, sizes = [name for name, _ in copied], [size for _, size in copied]
        scratch.mkdir()
        seconds["photos"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = int(max_image_size)
        extraction.sift.peak_threshold = SIFT_PEAK_THRESHOLD
        extraction.num_threads = get_num_threads()
        single = len(set(sizes)) == 1
        done = 0
        for chunk in _chunks(names, PROGRESS_STEPS):
            if single and done:  # the first run made the one camera (id 1); the others use it
                reader.existing_camera_id = 1
            mode = pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.AUTO
            _run_stage(pycolmap, "features", lambda token: pycolmap.extract_features(
                database, images, image_names=chunk, camera_mode=mode, reader_options=reader,
                extraction_options=extraction, device=pycolmap.Device.cpu, cancellation_token=token),
                done, len(names), progress, should_stop)
            done += len(chunk)
        if progress is not None:
            progress("features", len(names), len(names))
        seconds["features"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed  # the same photos give the same pairs, and so the same cameras
        verification.ransac.max_num_trials = VERIFICATION_MAX_TRIALS
        matcher = pycolmap.FeatureMatchingOptions()
        matcher.num_threads = get_num_threads()
        pairs = image_pairs(names, kind)
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(scratch / "pairs.txt")
        done = 0
        for chunk in _chunks(pairs, PROGRESS_STEPS):
            Path(pairing.match_list_path).write_text("".join(f"{a} {b}\n" for a, b in chunk), encoding="utf-8")
            _run_stage(pycolmap, "matching", lambda token: pycolmap.match_image_pairs(
                database, matching_options=matcher, pairing_options=pairing, verification_options=verification, device=pycolmap.Device.cpu,
                cancellation_token=token), done, len(pairs), progress, should_stop)
            done += len(chunk)
        if progress is not None:
            progress("matching", len(pairs), len(pairs))
        seconds["matching"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        rec, rec_error = None, math.inf
        for attempt, angle in enumerate(INITIAL_PAIR_ANGLES):
            if attempt == len(INITIAL_PAIR_ANGLES) - 1 and rec is not None and rec.num_reg_images() == len(names):
                break  # the last, smallest angle is for captures the others could not place whole
            registered = [0]
            attempt_dir = scratch / f"mapping-{attempt}"
            attempt_dir.mkdir()
            models = _run_stage(pycolmap, "mapping", lambda token: pycolmap.incremental_mapping(
                database, images, attempt_dir, _mapping_options(pycolmap, seed, angle),
                next_image_callback=lambda: registered.__setitem__(0, registered[0] + 1), cancellation_token=token),
                lambda: registered[0] + 1, len(names), progress, should_stop)
            for model in (models or {}).values():  # most photos placed, then the smallest reprojection error
                error = float(model.compute_mean_reprojection_error())
                if rec is None or (model.num_reg_images(), -error) > (rec.num_reg_images(), -rec_error):
                    rec, rec_error = model, error
        if progress is not None:
            progress("mapping", len(names), len(names))
        seconds["mapping"] = time.perf_counter() - t0

        done = set() if rec is None else {rec.image(i).name for i in rec.reg_image_ids()}
        missing = [n for n in names if n not in done]
        if len(done) < max(3, math.ceil(min_registered * len(names))):
            raise PosesError(
                f"{source}: only {len(done)} of {len(names)} photos could be placed in one scene "
                f"(at least {max(3, math.ceil(min_registered * len(names)))} needed). Photos that fail usually lack "
                "overlap with the others (each spot should be in 3 or more photos), are blurred, or show "
                "plain or shiny surfaces; try more photos with more overlap"
                + (", or --matching exhaustive" if kind == "sequential" else "")
                + (f". Not placed: {', '.join(missing[:20])}{' ...' if len(missing) > 20 else ''}" if missing else ""))

        matrix = upright(_cameras_of(rec))
        scale = float(np.cbrt(np.linalg.det(matrix[:3, :3])))
        rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(matrix[:3, :3] / scale), matrix[:3, 3]))
        for name in missing:  # a photo with no camera is not part of the dataset
            (images / name).unlink()
        first = rec.cameras[min(rec.cameras)]
        result = PosesResult(
            out=str(out), photos=len(names), registered=sorted(done), unregistered=missing,
            reprojection_error=float(rec.compute_mean_reprojection_error()), points=int(rec.num_points3D()),
            matching=kind, focal=float(first.params[0]), focal_prior=bool(first.has_prior_focal_length), seconds=seconds,
            transform=matrix.tolist())
        result.camera_model = _write_model(pycolmap, rec, work / "sparse" / "0")
        shutil.rmtree(scratch)
        (work / "poses.json").write_text(json.dumps(asdict(result), indent=2) + "\n", encoding="utf-8")
        if out.exists():
            out.rmdir()
        os.replace(work, out)
        return result
    finally:
        pycolmap.logging.minloglevel = previous_level
        shutil.rmtree(work, ignore_errors=True)


def solve_capture(source, out, *, fps: float | None = None, blur_ratio: float | None = None,
                  progress: StageProgress = None, should_stop: Optional[Callable[[], bool]] = None,
                  **solve_kw) -> PosesResult:
    """:func:`solve_poses` on a folder of photos, or on the sharp frames of a video file (:mod:`.video`).

    fps / blur_ratio: for a video (defaults :data:`.video.DEFAULT_FPS`, :data:`.video.DEFAULT_BLUR_RATIO`);
    its frames are taken into a scratch folder beside ``out`` (stage ``frames``) and matched in order."""
    from .video import DEFAULT_BLUR_RATIO, DEFAULT_FPS, extract_frames, is_video

    source = Path(source)
    if not is_video(source):
        if fps is not None or blur_ratio is not None:
            raise PosesError(f"{source}: fps and blur_ratio apply to a video file, and this is not one")
        return solve_poses(source, out, progress=progress, should_stop=should_stop, **solve_kw)
    require_pycolmap()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames = out.parent / f".{out.name}.frames-{secrets.token_hex(4)}"
    stage = None if progress is None else (lambda done, total: progress("frames", done, total))
    try:
        extract_frames(source, frames, fps=DEFAULT_FPS if fps is None else fps,
                       blur_ratio=DEFAULT_BLUR_RATIO if blur_ratio is None else blur_ratio,
                       progress=stage, should_stop=should_stop)
        solve_kw.setdefault("video", True)
        return solve_poses(frames, out, progress=progress, should_stop=should_stop, **solve_kw)
    finally:
        shutil.rmtree(frames, ignore_errors=True)
