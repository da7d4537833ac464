"""Training Gaussians from images: trainer, density control, optimizer, metrics.

``GaussianTrainer`` and ``TrainerConfig`` are the entry points; ``metrics``
holds PSNR/SSIM and the photometric loss; ``bilateral_grid`` the per-image
colour correction.
"""

from .adam import Adam
from .density import densify_and_prune, reset_opacities
from .trainer import GaussianTrainer, TrainerConfig, TrainingError, events_at

__all__ = ["Adam", "GaussianTrainer", "TrainerConfig", "TrainingError", "densify_and_prune", "events_at", "reset_opacities"]
