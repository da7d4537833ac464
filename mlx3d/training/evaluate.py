"""Evaluation on held-out views: plain and colour-corrected PSNR/SSIM per view, the worst view, side-by-side images, a JSON report."""

from __future__ import annotations

import json
import os
import time

import mlx.core as mx
import numpy as np

from .colour import colour_correct
from .metrics import psnr, ssim

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}

#: Per-view metrics in the report: plain, and after the best affine colour map (see :mod:`.colour`).
METRICS = ("psnr", "ssim", "cc_psnr", "cc_ssim")


def render_view(model, dataset, index: int, background=(0.0, 0.0, 0.0)):
    """(ground truth, render) of frame ``index``: (H, W, 3) float32 numpy arrays in [0, 1].

    The image is composited on ``background``, which the render uses too.
    """
    frame = dataset.frames[index]
    target, _ = dataset.load_image(index, background=background)
    image = mx.clip(model.render(frame.camera, background=background)["image"], 0.0, 1.0)
    return np.asarray(target, dtype=np.float32), np.array(image, dtype=np.float32)


def view_metrics(image, target) -> dict:
    """PSNR and SSIM of ``image`` against ``target``, plain and colour-corrected (the keys of :data:`METRICS`)."""
    image, ref = mx.array(image), mx.array(target)
    corrected = colour_correct(image, ref)
    return {
        "psnr": float(psnr(image, ref)), "ssim": float(ssim(image, ref)),
        "cc_psnr": float(psnr(corrected, ref)), "cc_ssim": float(ssim(corrected, ref)),
    }


def save_side_by_side(path, target, image) -> None:
    """Write ``target | image`` (ground truth left, render right) as an 8-bit PNG, atomically."""
    from PIL import Image

    from ..io.atomic import atomic_write

    pair = np.concatenate([np.asarray(target), np.asarray(image)], axis=1)
    with atomic_write(path) as f:
        Image.fromarray((np.clip(pair, 0, 1) * 255).round().astype(np.uint8)).save(f, format="PNG")


def worst_view(views: list, key: str = "psnr") -> dict:
    """The view with the lowest ``key`` (the first of equals); its whole row."""
    if not views:
        raise ValueError("no views to pick the worst from")
    return min(views, key=lambda v: v[key])


def evaluate(model, dataset, split: str = "test", background=(0.0, 0.0, 0.0), out_dir=None, progress=None) -> dict:
    """Render every view of ``split`` and compare it with its image.

    background: the colour images with alpha are composited on (and the render
    uses). With ``out_dir``, writes ``renders/<name>.png`` (ground truth | render)
    and ``metrics.json``.

    Returns {'split', 'views', 'psnr', 'ssim', 'cc_psnr', 'cc_ssim', 'worst',
    'cc_worst', 'seconds_per_view', 'num_gaussians'}: each view is {'name',
    'psnr', 'ssim', 'cc_psnr', 'cc_ssim'}, where ``cc_`` are the metrics of the
    render after the affine colour map that best fits it to the image
    (:func:`mlx3d.training.colour.colour_correct`); the four top-level metrics
    are means over the views; ``worst`` is the row of the view with the lowest
    PSNR and ``cc_worst`` the row of the one with the lowest CC-PSNR.
    """
    indices = list(dataset.split(split))
    if not indices:
        raise ValueError(f"the dataset has no {split!r} views to evaluate")
    views = []
    t0 = time.perf_counter()
    for done, i in enumerate(indices, start=1):
        frame = dataset.frames[i]
        target, image = render_view(model, dataset, i, background)
        views.append({"name": frame.name, **view_metrics(image, target)})
        if out_dir is not None:
            os.makedirs(os.path.join(out_dir, "renders"), exist_ok=True)
            name = os.path.splitext(os.path.basename(frame.name))[0] + ".png"
            save_side_by_side(os.path.join(out_dir, "renders", name), target, image)
        if progress is not None:
            progress(done, len(indices))
    report = {
        "split": split,
        "views": views,
        **{key: float(np.mean([v[key] for v in views])) for key in METRICS},
        "worst": dict(worst_view(views, "psnr")),
        "cc_worst": dict(worst_view(views, "cc_psnr")),
        "seconds_per_view": (time.perf_counter() - t0) / len(indices),
        "num_gaussians": len(model),
    }
    if out_dir is not None:
        from ..io.atomic import atomic_write

        with atomic_write(os.path.join(out_dir, "metrics.json"), mode="w") as f:
            json.dump(report, f, indent=2)
    return report
