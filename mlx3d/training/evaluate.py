"""Evaluation on held-out views: PSNR and SSIM per view, side-by-side images, a JSON report."""

from __future__ import annotations

import json
import os
import time

import mlx.core as mx
import numpy as np

from .metrics import psnr, ssim

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def evaluate(model, dataset, split: str = "test", background=(0.0, 0.0, 0.0), out_dir=None, progress=None) -> dict:
    """Render every view of ``split`` and compare it with its image.

    background: the colour images with alpha are composited on (and the render
    uses). With ``out_dir``, writes ``renders/<name>.png`` (ground truth | render)
    and ``metrics.json``. Returns {'views': [...], 'psnr', 'ssim', 'seconds_per_view'}.
    """
    from PIL import Image

    from ..io.atomic import atomic_write

    indices = list(dataset.split(split))
    if not indices:
        raise ValueError(f"the dataset has no {split!r} views to evaluate")
    views = []
    t0 = time.perf_counter()
    for done, i in enumerate(indices, start=1):
        frame = dataset.frames[i]
        target, weight = dataset.load_image(i, background=background)
        image = mx.clip(model.render(frame.camera, background=background)["image"], 0.0, 1.0)
        ref = mx.array(target)
        views.append({"name": frame.name, "psnr": float(psnr(image, ref)), "ssim": float(ssim(image, ref))})
        if out_dir is not None:
            os.makedirs(os.path.join(out_dir, "renders"), exist_ok=True)
            pair = np.concatenate([np.asarray(target), np.array(image)], axis=1)
            name = os.path.splitext(os.path.basename(frame.name))[0] + ".png"
            with atomic_write(os.path.join(out_dir, "renders", name)) as f:
                Image.fromarray((np.clip(pair, 0, 1) * 255).round().astype(np.uint8)).save(f, format="PNG")
        if progress is not None:
            progress(done, len(indices))
    report = {
        "split": split,
        "views": views,
        "psnr": float(np.mean([v["psnr"] for v in views])),
        "ssim": float(np.mean([v["ssim"] for v in views])),
        "seconds_per_view": (time.perf_counter() - t0) / len(indices),
        "num_gaussians": len(model),
    }
    if out_dir is not None:
        with atomic_write(os.path.join(out_dir, "metrics.json"), mode="w") as f:
            json.dump(report, f, indent=2)
    return report
