"""Photos from a video: the sharpest frame of every ``1 / fps`` seconds, written as JPEGs.

A walk or an orbit filmed with a phone has many frames blurred by motion.
:func:`extract_frames` decodes the video (PyAV, which bundles FFmpeg: an
optional dependency, ``pip install "mlx3d-splat[poses]"``), splits it into
windows of ``1 / fps`` seconds, keeps the sharpest frame of each (sharpness:
the variance of the Laplacian of the frame's grey levels, measured at most
:data:`SHARPNESS_SIZE` pixels wide) and drops the kept frames whose sharpness
is below ``blur_ratio`` times their median, the blurriest left. Frames are
written full size as ``frame_00000.jpg`` ... in time order, so name order is
time order (what sequential matching needs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import PosesError

#: Video file suffixes :func:`is_video` recognises (case-insensitive).
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts")
#: Sharpness is measured on frames scaled to at most this many pixels wide.
SHARPNESS_SIZE = 480
DEFAULT_FPS = 2.0
DEFAULT_BLUR_RATIO = 0.4
PYAV_PIN = "18.1.0"


def is_video(path) -> bool:
    """True for a file whose suffix is one of :data:`VIDEO_SUFFIXES`."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of a (H, W) grey image (larger: sharper)."""
    g = np.asarray(grey, np.float32)
    if g.shape[0] < 3 or g.shape[1] < 3:
        return 0.0
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def _require_av():
    try:
        import av
    except ImportError as exc:
        raise PosesError(
            f"reading a video needs PyAV, which is not installed here ({exc}). Install it with "
            f"`pip install \"mlx3d-splat[poses]\"` (or `pip install av=={PYAV_PIN}`), or extract the frames "
            "yourself into a folder of photos.") from None
    return av


def extract_frames(video, folder, *, fps: float = DEFAULT_FPS, blur_ratio: float = DEFAULT_BLUR_RATIO,
                   progress=None, should_stop=None) -> list[str]:
    """Write the sharp frames of ``video`` into ``folder`` (module doc); returns their names in time order.

    fps: frames kept per second of video (at most one per window of ``1 / fps`` s); blur_ratio: kept frames
    less sharp than this fraction of the median are dropped (0 keeps all). progress: ``(done, total)``
    over the video's frames; should_stop: polled per frame, True raises KeyboardInterrupt."""
    av = _require_av()
    if not fps > 0:
        raise PosesError(f"fps must be positive, got {fps!r}")
    if not 0 <= blur_ratio < 1:
        raise PosesError(f"blur_ratio must be in [0, 1), got {blur_ratio!r}")
    path = Path(video)
    try:
        container = av.open(str(path))
    except (OSError, av.error.FFmpegError) as exc:
        raise PosesError(f"{path}: cannot open this video: {exc}") from None
    kept = []  # (sharpness, time, frame as RGB array)
    with container:
        if not container.streams.video:
            raise PosesError(f"{path}: has no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = float(stream.average_rate or 30)
        total = stream.frames or max(int(float(container.duration or 0) / 1e6 * rate), 1)
        window, best = None, None
        try:
            for i, frame in enumerate(container.decode(stream)):
                if should_stop is not None and should_stop():
                    raise KeyboardInterrupt
                t = float(frame.time if frame.time is not None else i / rate)
                w = int(t * fps)
                scale = min(1.0, SHARPNESS_SIZE / max(frame.width, 1))
                grey = frame.to_ndarray(format="gray", width=max(int(frame.width * scale), 3),
                                        height=max(int(frame.height * scale), 3))
                score = sharpness(grey)
                if w != window:
                    if best is not None:
                        kept.append(best)
                    window, best = w, None
                if best is None or score > best[0]:
                    best = (score, t, frame.to_ndarray(format="rgb24"))
                if progress is not None:
                    progress(min(i + 1, total), total)
        except av.error.FFmpegError as exc:
            raise PosesError(f"{path}: cannot decode frame {len(kept)}: {exc}") from None
        if best is not None:
            kept.append(best)
    if not kept:
        raise PosesError(f"{path}: no frames could be decoded")
    median = float(np.median([k[0] for k in kept]))
    sharp = [k for k in kept if k[0] >= blur_ratio * median]
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for n, (_, _, rgb) in enumerate(sharp):
        name = f"frame_{n:05d}.jpg"
        Image.fromarray(rgb).save(folder / name, quality=95)
        names.append(name)
    return names
