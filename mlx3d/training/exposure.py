"""Whether the training photos differ in exposure, measured from the sparse model before training.

The per-image bilateral grid (:mod:`.bilateral_grid`) lets a model keep one
colour per surface while each photo carries its own exposure and white
balance. Photos shot at one exposure give it nothing to absorb, and a grid
that is free to change every photo's colours then costs time for nothing,
so ``TrainerConfig(bilateral_grid='auto')`` turns it on only when this
module measures a difference.

The measure needs where each photo sees the sparse points (a
structure-from-motion model's tracks, ``Dataset.observations``). A sparse
point's colour is the mean over the photos that observe it (COLMAP's), so
in a photo whose gain is ``g`` relative to the others, the pixels at its
observations read about ``g`` times their points' colours, whatever the
scene's content. Per training photo and channel, the median over its
observations of ``log(pixel / point colour)`` estimates ``log g``; the
*exposure spread* is the largest, over the three channels, standard
deviation of those medians across the photos (so a white-balance change
counts as well as a gain). Medians ignore occluded or mismatched points and
view-dependent highlights; observations at dark (< 0.05) or clipped
(> 0.98) values, or outside a photo's alpha, are not used.

Measured on ``bench/real_captures.py``'s captures (``docs/benchmarks/real_captures.md``):
0.00-0.01 for the rendered captures shot at one exposure, about 0.1 for
gains of 0.55-1.6 with ±12 % white balance and for ``lund``'s street photos.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EXPOSURE_SPREAD", "MIN_OBSERVATIONS", "exposure_spread", "exposure_varies"]

#: Above this spread (about ±3 % gain between photos, one standard deviation) the exposure varies.
EXPOSURE_SPREAD = 0.03
#: A photo needs this many usable observations to count; the measure needs three such photos.
MIN_OBSERVATIONS = 20
DARK, CLIPPED = 0.05, 0.98


def photo_gains(dataset) -> dict[int, np.ndarray]:
    """Per training frame (index) with enough observations: the median ``log(pixel / point colour)`` per
    channel, (3,)."""
    if dataset.observations is None or dataset.point_colors is None:
        return {}
    colours = dataset.point_colors.astype(np.float32) / 255.0
    gains = {}
    for i in dataset.train:
        xy, index = dataset.observations[i]
        if len(index) < MIN_OBSERVATIONS:
            continue
        rgb, weight = dataset.load_image(i)
        h, w = rgb.shape[:2]
        px = np.clip(np.floor(xy).astype(np.int64), 0, [w - 1, h - 1])  # pixel (x, y) whose square holds xy
        seen = rgb[px[:, 1], px[:, 0]]
        ref = colours[index]
        usable = (ref > DARK) & (seen > DARK) & (seen < CLIPPED) & (ref < CLIPPED)
        if weight is not None:
            usable &= weight[px[:, 1], px[:, 0], None] >= 0.5
        ratio = np.log(np.where(usable, seen, 1.0) / np.where(usable, ref, 1.0))
        if usable.sum(axis=0).min() < MIN_OBSERVATIONS:
            continue
        gains[i] = np.array([np.median(ratio[usable[:, c], c]) for c in range(3)])
    return gains


def exposure_spread(dataset) -> float | None:
    """The training photos' exposure spread (see the module docstring), or None when the dataset
    cannot tell (no tracks, or fewer than three photos with enough observations)."""
    gains = photo_gains(dataset)
    if len(gains) < 3:
        return None
    return float(np.std(np.stack(list(gains.values())), axis=0).max())


def exposure_varies(dataset) -> tuple[bool, str]:
    """``(varies, why)``: whether the spread exceeds :data:`EXPOSURE_SPREAD`, and a sentence saying so."""
    spread = exposure_spread(dataset)
    if spread is None:
        return False, "the exposure spread is not measurable without the sparse model's tracks"
    relation = "above" if spread > EXPOSURE_SPREAD else "at most"
    return spread > EXPOSURE_SPREAD, f"exposure spread {spread:.3f} over the training photos, {relation} {EXPOSURE_SPREAD:g}"
