"""Training Gaussians against images: ``TrainerConfig`` and ``GaussianTrainer``.

One step renders a view, compares it with the target (L1 + λ·D-SSIM),
differentiates w.r.t. the raw parameters and the 2D means (through a zero
offset, see ``render_gaussians(means2d_offset=...)``) and takes an Adam step
with 3DGS's per-parameter learning rates. Schedules (SH degree increase,
densification, opacity reset) are pure functions of the step so they can be
tested and inspected (``events_at``).

``method='2dgs'`` trains surfels: vanilla density control, the third local
scale clamped to ``two_d_thickness`` times the scene extent after every step
(``GaussianModel.apply_2dgs_constraints``), and the geometry regularisers of
``mlx3d.training.geometry`` on by default. Those regularisers work with any
method; with their weights at 0 the depth and normal channels are not
rendered at all.

``batch_size`` > 1 makes a step a batch of views: the loss is their mean,
each view adds to the densification statistics, and the learning rates and
Adam's constants are scaled as gsplat does for a batch of ``B`` views (see
``batch_adam``); ``TrainerConfig.scale_steps`` scales the schedules. The
views of a batch can be shared by several processes
(``mlx3d.training.distributed``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, replace

import mlx.core as mx
import numpy as np

from ..errors import Mlx3dError
from ..render import activation, render_gaussians
from ..render.pipeline import PROJECTIONS
from ..splatting.model import PARAM_NAMES, GaussianModel
from .adam import Adam, all_finite
from .density import add_gaussians_mcmc, densify_and_prune, relocate_dead, reset_opacities, sgld_noise
from .geometry import DepthUnprojector, depth_variance_loss, normal_consistency_loss, sparse_depth_loss, sparse_points
from .metrics import photometric_loss, psnr
from .plan import step_plan
from .statistics import ScreenStatistics


class TrainingError(Mlx3dError, RuntimeError):
    """Training cannot go on (NaN/Inf loss or parameters); the message says where."""


METHODS = ("vanilla", "mcmc", "2dgs")


@dataclass
class TrainerConfig:
    """Settings of a training run; defaults follow 3DGS for 30k steps."""

    method: str = "vanilla"  # 'vanilla' (adaptive density control) | 'mcmc' (3DGS as MCMC) | '2dgs' (surfels)
    steps: int = 30_000
    lambda_dssim: float = 0.2
    background: object = None  # 'black' | 'white' | 'random' | (r, g, b); None: white_background's
    white_background: bool = False  # background 'white' when `background` is not given
    # behind training renders when the photos are opaque (no alpha): 'random' draws a colour per step, so no part
    # of the model can go transparent and let the background (or a per-image grid over it) stand in for the scene;
    # 'auto': 'random' when the run seeded a backdrop to cover the frame with (init_background_points), else
    # `background` (an object shot on a plain backdrop may leave it transparent); None: `background`
    opaque_background: object = "auto"
    antialias: bool = False
    projection: str = "auto"  # 'auto' | 'ewa' | 'ut'
    sh_increase_every: int = 1000  # raise the active SH degree every this many steps
    # learning rates (means: initial and final, scaled by the scene extent, log-linear decay over lr_means_max_steps)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_means_max_steps: int | None = None  # None: `steps`
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    # adaptive density control
    densify_from: int = 500
    densify_until: int | None = None  # None: 15,000 (vanilla, 2dgs, as 3DGS) or 25,000 (mcmc, as 3DGS-MCMC)
    densify_every: int = 100
    opacity_reset_every: int = 3000
    reset_recovery: int = 500  # no opacity reset in the last this many steps: the model needs them to recover
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_screen_size: float = 20.0  # pixels, applied after the first opacity reset
    max_gaussians: int | None = None  # vanilla: stops growth; mcmc: the cap it grows to (see training.initial.mcmc_budget)
    # the initial model (see mlx3d.training.initial); None: the method's default
    init_opacity: float | None = None  # 0.5 (mcmc) or 0.1
    init_scale: float | None = None  # factor on the mean 3-NN distance: 0.1 (mcmc) or 1
    init_random_points: int = 100_000  # a dataset without points starts from this many random ones
    init_random_extent: float | None = None  # half-side of their cube (None: from the cameras)
    init_background_points: int | None = None  # None: auto (vanilla and mcmc on opaque photos); 0: none
    init_background_radius: float = 10.0  # their sphere's radius, times the scene extent
    # Gaussians farther than this × the scene extent from the cameras' centre are the backdrop: the size
    # prunes (max_screen_size, 0.1 × extent) leave them alone; None: 3DGS's prunes for every Gaussian.
    backdrop_distance: float | None = 5.0
    # 3DGS as Markov Chain Monte Carlo (method='mcmc'); relocation/growth run on the densify schedule
    mcmc_min_opacity: float = 0.005  # "dead" below this opacity
    mcmc_relocate_frac: float = 1.0  # at most this fraction of N relocated per event
    mcmc_growth: float = 0.05  # growth per event (fraction of N) up to max_gaussians
    mcmc_jitter_scale: float = 0.0  # offset of relocated copies, in their standard deviations
    mcmc_noise_lr: float = 5e5  # SGLD noise N(0, Σ) gated by opacity, times the means learning rate (the paper's)
    mcmc_noise_scale: float = 0.0  # isotropic noise on every mean, std mcmc_noise_scale · extent · sqrt(means lr)
    mcmc_opacity_reg: float = 0.01
    mcmc_scale_reg: float = 0.01
    # per-image affine colour grid absorbing exposure/white-balance differences; 'auto': on when the
    # training photos' exposure varies (training.exposure, measured by initial_state; a Trainer made
    # without it reads 'auto' as off)
    bilateral_grid: bool | str = "auto"
    bilateral_grid_shape: tuple = (16, 16, 8)
    bilateral_grid_lr: float | None = None  # None: 2e-3 (vanilla, 2dgs, as gsplat) or 1e-3 (mcmc, measured on bench_data's exposure scene)
    bilateral_grid_warmup: int | None = None  # lr rises linearly from 1% over these steps, then decays to 1% at `steps`;
    # None: steps / 30, at most 1,000 (gsplat's 1,000 of 30,000)
    lambda_bilateral_tv: float = 10.0
    # surfels and geometry regularisers (see mlx3d.training.geometry); None: the method's default
    two_d_thickness: float = 1e-3  # '2dgs': largest third scale, as a fraction of the scene extent
    lambda_2d_depth_variance: float | None = None  # '2dgs': 3, else 0
    lambda_2d_normal_consistency: float | None = None  # '2dgs': 0.05, else 0
    geometry_min_alpha: float = 0.5  # the regularisers apply where the render's alpha reaches this
    geometry_from: int = 1000  # and from this step on
    # the solve's sparse points as depth (Dataset.observations): L1 of inverse depth at each point a view observes,
    # times the scene extent (mlx3d.training.geometry.sparse_depth_loss); 0: off
    lambda_sparse_depth: float = 0.0
    seed: int = 0
    # views per step, over all ranks of a distributed run; 1: one view per step (3DGS). B > 1 scales the
    # learning rates by sqrt(B) and Adam's betas and eps with it (see batch_adam); schedules: scale_steps
    batch_size: int = 1
    low_memory: bool = False  # clear MLX's buffer cache after densification
    cache_limit_gb: float | None = None
    checkpoint_every: int = 0  # 0: only on request
    checkpoint_dir: str | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method {self.method!r} is not available; use one of {METHODS}")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if not isinstance(self.batch_size, (int, np.integer)) or isinstance(self.batch_size, bool) or self.batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {self.batch_size!r}")
        if self.projection not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}, got {self.projection!r}")
        if self.background is None:
            self.background = "white" if self.white_background else "black"
        for name in ("background", "opaque_background"):
            value = getattr(self, name)
            if name == "opaque_background" and value in (None, "auto") or value in ("black", "white", "random"):
                continue
            if isinstance(value, str) or len(value) != 3:
                extra = ", 'auto', None" if name == "opaque_background" else ""
                raise ValueError(f"{name} must be 'black', 'white', 'random'{extra} or (r, g, b), got {value!r}")
        if self.lr_means_max_steps is not None and self.lr_means_max_steps < 1:
            raise ValueError(f"lr_means_max_steps must be >= 1 (or None: steps), got {self.lr_means_max_steps}")
        if self.mcmc_noise_lr < 0 or self.mcmc_noise_scale < 0:
            raise ValueError(f"mcmc_noise_lr and mcmc_noise_scale must be >= 0, got {self.mcmc_noise_lr}, {self.mcmc_noise_scale}")
        surfels = self.method == "2dgs"
        mcmc = self.method == "mcmc"
        if self.densify_until is None:
            self.densify_until = 25_000 if mcmc else 15_000
        if self.init_opacity is None:
            self.init_opacity = 0.5 if mcmc else 0.1
        if self.bilateral_grid not in (True, False, "auto"):
            raise ValueError(f"bilateral_grid must be True, False or 'auto', got {self.bilateral_grid!r}")
        if self.bilateral_grid != "auto":
            self.bilateral_grid = bool(self.bilateral_grid)  # a numpy bool too: the step plan tests `is True`
        if self.bilateral_grid_lr is None:
            self.bilateral_grid_lr = 1e-3 if mcmc else 2e-3
        if not self.bilateral_grid_lr > 0:
            raise ValueError(f"bilateral_grid_lr must be > 0, got {self.bilateral_grid_lr}")
        if self.init_scale is None:
            self.init_scale = 0.1 if mcmc else 1.0
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if not self.init_scale > 0:
            raise ValueError(f"init_scale must be > 0, got {self.init_scale}")
        if self.init_random_points < 2:
            raise ValueError(f"init_random_points must be >= 2, got {self.init_random_points}")
        if self.max_gaussians is not None and self.max_gaussians < 2:
            raise ValueError(f"max_gaussians must be >= 2 (or None), got {self.max_gaussians}")
        if self.lambda_2d_depth_variance is None:
            self.lambda_2d_depth_variance = 3.0 if surfels else 0.0
        if self.lambda_2d_normal_consistency is None:
            self.lambda_2d_normal_consistency = 0.05 if surfels else 0.0
        if self.lambda_2d_depth_variance < 0 or self.lambda_2d_normal_consistency < 0:
            raise ValueError("lambda_2d_depth_variance and lambda_2d_normal_consistency must be >= 0")
        if not self.lambda_sparse_depth >= 0:
            raise ValueError(f"lambda_sparse_depth must be >= 0, got {self.lambda_sparse_depth}")
        if not self.two_d_thickness > 0:
            raise ValueError(f"two_d_thickness must be > 0, got {self.two_d_thickness}")

    #: The step counts ``scale_steps`` scales: the run's length, the schedules and the checkpoint interval.
    STEP_FIELDS = ("steps", "lr_means_max_steps", "sh_increase_every", "densify_from", "densify_until", "densify_every",
                   "opacity_reset_every", "reset_recovery", "bilateral_grid_warmup", "geometry_from", "checkpoint_every")

    def scale_steps(self, factor: float) -> "TrainerConfig":
        """This config with every step count of ``STEP_FIELDS`` times ``factor`` (gsplat's ``steps_scaler``):
        e.g. ``factor = 1 / batch_size`` trains on as many views, in batches, as the unscaled run one at a time.
        Intervals stay at least 1; a count of 0 (off) stays 0."""
        if not factor > 0:
            raise ValueError(f"the steps scaler must be > 0, got {factor}")
        changes = {}
        for name in self.STEP_FIELDS:
            value = getattr(self, name)
            if value:
                changes[name] = max(int(value * factor), 1) if name not in ("densify_from", "geometry_from", "reset_recovery") else int(value * factor)
        return replace(self, **changes)


def batch_adam(batch_size: int) -> dict:
    """Adam's constants and the learning-rate factor for batches of ``batch_size`` views, as gsplat's trainer sets
    them (the square-root scaling rule): lr x sqrt(B), eps 1e-15 / sqrt(B), betas (1 - B (1 - 0.9), 1 - B (1 - 0.999)).
    From B = 10 on the first beta would be 0 or negative: it is held at 0 (no momentum)."""
    b = int(batch_size)
    if b == 1:
        return {"lr_factor": 1.0, "betas": (0.9, 0.999), "eps": 1e-15}
    root = math.sqrt(b)
    # 1 - B (1 - 0.9) as (10 - B) / 10: exactly 0 at B = 10 (the float expression leaves 2e-16)
    return {"lr_factor": root, "betas": (max((10 - b) / 10, 0.0), max((1000 - b) / 1000, 0.0)), "eps": 1e-15 / root}


@dataclass
class TrainingView:
    """One view of a training step: camera, target (H, W, 3) in [0, 1], weight (H, W) or None,
    background (r, g, b) or None (the config's), image_index (the bilateral grid's image) or None,
    points: the sparse points the view observes, ``(pixels (K, 2) float32, camera z (K,) float32)``, or None
    (``lambda_sparse_depth``; see ``sparse_points``)."""

    camera: object
    target: object
    weight: object = None
    background: object = None
    image_index: int | None = None
    points: tuple | None = None


def events_at(config: TrainerConfig, step: int) -> tuple:
    """Schedule events after step ``step`` (1-based): 'sh_up', and 'densify' and
    'reset_opacity' (vanilla) or 'relocate' and 'grow' (mcmc)."""
    events = []
    if config.sh_increase_every and step % config.sh_increase_every == 0:
        events.append("sh_up")
    if config.densify_from < step <= config.densify_until:
        if config.method == "mcmc":
            if step % config.densify_every == 0:
                events += ["relocate", "grow"]
            return tuple(events)
        if step % config.densify_every == 0:
            events.append("densify")
        # A reset needs density control after it (pruning what stays transparent) and steps to recover,
        # so none at the last densification step (as in the 3DGS reference) nor in the last reset_recovery steps.
        if (config.opacity_reset_every and step % config.opacity_reset_every == 0 and step < config.densify_until
                and step <= config.steps - config.reset_recovery):
            events.append("reset_opacity")
    return tuple(events)


class GaussianTrainer:
    """Optimises a ``GaussianModel`` in place.

    scene_extent: radius of the camera centres (the dataset's ``scene_extent()``);
    it scales the means learning rate and the densification thresholds. A
    non-positive extent (e.g. a single camera) is taken as 1. scene_centre:
    (3,) their mean (the dataset's ``scene_centre()``; ``fit`` takes it from
    its dataset when not given), where ``backdrop_distance`` is measured from.
    ranks: a ``training.distributed.Ranks`` of processes training this model
    together (each renders its share of every batch), or None.
    """

    def __init__(self, model: GaussianModel, config: TrainerConfig | None = None, scene_extent: float = 1.0, num_images: int | None = None,
                 scene_centre=None, ranks=None):
        self.model = model
        self.config = config or TrainerConfig()
        if self.config.bilateral_grid == "auto":  # initial_state decides it from the dataset
            self.config = replace(self.config, bilateral_grid=False)
        self.ranks = ranks if ranks is not None and ranks.size > 1 else None
        self.scene_extent = float(scene_extent) if scene_extent > 0 else 1.0
        self.scene_centre = None if scene_centre is None else np.asarray(scene_centre, np.float64).reshape(3)
        self.bilateral = None  # the BilateralGrid when enabled (needs num_images; fit() knows it)
        self.grid_optimizer = None
        if self.config.bilateral_grid and num_images:
            self._make_grid(num_images)
        self.step_count = 0
        self.active_sh_degree = 0
        self.rng = np.random.default_rng(self.config.seed)
        self._opaque_dataset, self._opaque = None, False  # training_background's cache
        batch = batch_adam(self.config.batch_size)
        self.optimizer = Adam(self.learning_rates(), betas=batch["betas"], eps=batch["eps"])
        self._reset_stats()
        self.opacity_resets = 0
        self.unprojector = DepthUnprojector()
        if self.config.method == "2dgs":
            self.model.apply_2dgs_constraints(self.max_thickness)
        if self.config.cache_limit_gb is not None:
            mx.set_cache_limit(int(self.config.cache_limit_gb * 2**30))

    def _make_grid(self, num_images: int) -> None:
        from .bilateral_grid import BilateralGrid, GridAdam, warmup_decay

        self.bilateral = BilateralGrid(num_images, self.config.bilateral_grid_shape)
        warmup = self.config.bilateral_grid_warmup
        schedule = warmup_decay(self.config.steps, min(self.config.steps // 30, 1000) if warmup is None else warmup)
        self.grid_optimizer = GridAdam(self.config.bilateral_grid_lr * batch_adam(self.config.batch_size)["lr_factor"], schedule=schedule)  # updates only the stepped image's grid

    @property
    def max_thickness(self) -> float:
        """'2dgs': the largest third scale, in scene units."""
        return self.config.two_d_thickness * self.scene_extent

    # ------------------------------------------------------------------ schedules
    def learning_rates(self) -> dict:
        """Per-parameter learning rates at the current step (times sqrt(batch_size), see ``batch_adam``)."""
        c = self.config
        t = min(self.step_count / (c.lr_means_max_steps or c.steps), 1.0)
        lr_means = math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final)) * self.scene_extent
        rates = {
            "means": lr_means,
            "scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacities": c.lr_opacities,
            "sh_dc": c.lr_sh_dc,
            "sh_rest": c.lr_sh_rest,
        }
        factor = batch_adam(c.batch_size)["lr_factor"]
        return rates if factor == 1.0 else {k: v * factor for k, v in rates.items()}

    def _reset_stats(self):
        self.statistics = ScreenStatistics(len(self.model))

    # the density statistics as float64 (N,) numpy arrays (see mlx3d.training.statistics)
    grad_accum = property(lambda self: self.statistics.arrays()[0], lambda self, v: self.statistics.set(0, v))
    grad_count = property(lambda self: self.statistics.arrays()[1], lambda self, v: self.statistics.set(1, v))
    max_radii = property(lambda self: self.statistics.arrays()[2], lambda self, v: self.statistics.set(2, v))

    def background_colour(self, spec=None) -> tuple:
        """The (r,g,b) background for the next step: ``spec`` or the config's ``background``
        ('black' | 'white' | 'random', which draws a new colour, | (r, g, b))."""
        bg = self.config.background if spec is None else spec
        if bg == "black":
            return (0.0, 0.0, 0.0)
        if bg == "white":
            return (1.0, 1.0, 1.0)
        if bg == "random":
            return tuple(self.rng.uniform(0, 1, 3))
        return tuple(bg)

    def _loss(self, p, offset, grid, camera, target, mask, bg, plan, degree, image_index=None, points=None):
        """(loss, render output) of one view: the photometric loss plus the terms in ``plan.losses``.

        p: the raw parameters; offset: None or (N, 2) added to the 2D means
        (dL/d offset is the screen-space gradient); grid: the bilateral grid
        when ``image_index`` is given; points: the view's sparse depth targets
        (``TrainingView.points``). ``out['ran']`` lists the stages run.
        """
        c = self.config
        use_grid = self.bilateral is not None and image_index is not None
        r, terms = plan.render, set(plan.losses)
        sh = (p["sh_dc"], p["sh_rest"])  # read in place by the CPU kernel, no concatenation
        out = render_gaussians(
            camera, p["means"], p["quats"], activation.exp(p["scales"], r.backend), activation.sigmoid(p["opacities"], r.backend),
            sh=sh, sh_degree=degree,
            background=bg, antialias=r.antialias, projection=r.projection, means2d_offset=offset, render_depth=r.depth,
            render_depth_variance=r.depth_variance, render_normals=r.normals, planar_depth=r.planar_depth, backend=r.backend,
        )
        ran = list(out["stages"])
        image = out["image"]
        if use_grid:
            image = self.bilateral.apply(image, image_index, grid)
            out = dict(out, image=image)
            ran.append("bilateral_grid")
        loss = photometric_loss(image, target, c.lambda_dssim, mask, backend=r.backend)  # skips SSIM when lambda_dssim is 0
        ran += ["loss_l1", "loss_dssim"] if c.lambda_dssim > 0 else ["loss_l1"]
        if "depth_variance" in terms:
            out["depth_variance_loss"] = depth_variance_loss(
                out["depth_variance"], out["alpha"], c.geometry_min_alpha, self.scene_extent, camera.model == "orthographic"
            )
            loss = loss + c.lambda_2d_depth_variance * out["depth_variance_loss"]
            ran.append("loss_depth_variance")
        if "normal_consistency" in terms:
            out["normal_loss"] = normal_consistency_loss(out["normals"], out["depth"], out["alpha"], camera, self.unprojector, c.geometry_min_alpha)
            loss = loss + c.lambda_2d_normal_consistency * out["normal_loss"]
            ran.append("loss_normal_consistency")
        if "sparse_depth" in terms:
            out["sparse_depth_loss"] = sparse_depth_loss(out["depth"], *points, self.scene_extent)
            loss = loss + c.lambda_sparse_depth * out["sparse_depth_loss"]
            ran.append("loss_sparse_depth")
        if "bilateral_tv" in terms:
            loss = loss + c.lambda_bilateral_tv * self.bilateral.tv_loss(grid)
            ran.append("loss_bilateral_tv")
        if "opacity_l1" in terms:
            loss = loss + c.mcmc_opacity_reg * mx.mean(activation.sigmoid(p["opacities"], r.backend))
            ran.append("loss_opacity_l1")
        if "scale_l1" in terms:
            loss = loss + c.mcmc_scale_reg * mx.mean(activation.exp(p["scales"], r.backend))
            ran.append("loss_scale_l1")
        out["ran"] = ran
        return loss, out

    # ------------------------------------------------------------------ one step
    def step(self, camera, target, weight=None, background=None, image_index: int | None = None) -> dict:
        """One optimisation step on one view. target (H,W,3) in [0,1]; weight (H,W) or None.

        background: colour composited behind the render (defaults to the config's,
        which must match how the target was composited); image_index: which
        training image this is (needed by the bilateral grid). Returns logging info.
        """
        return self.step_batch([TrainingView(camera, target, weight, background, image_index)])

    def step_batch(self, views, batch_images=None) -> dict:
        """One optimisation step on a batch of views (``TrainingView``): the mean of their losses.

        On one process ``views`` is the batch. With ``ranks`` it is this rank's share, the views at
        ``ranks.positions(B)`` of a batch of B; ``batch_images`` (B,) lists every view's image index
        (needed by the bilateral grid; default: ``views``' own), and every rank calls this with the
        same batch (``fit`` deals it). Returns logging info; ``loss`` and ``psnr`` are means over the batch.
        """
        c = self.config
        views = list(views)
        if not views:
            raise ValueError("a training step needs at least one view")
        use_grid = self.bilateral is not None
        if c.bilateral_grid and (not use_grid or any(v.image_index is None for v in views)):
            raise ValueError("bilateral_grid needs the trainer's num_images and each step's image_index")
        ranks = self.ranks
        batch_images = [v.image_index for v in views] if batch_images is None else list(batch_images)
        batch = len(batch_images)
        positions = ranks.positions(batch) if ranks is not None else list(range(batch))
        if len(positions) != len(views):
            raise ValueError(f"this rank renders {len(positions)} of the batch's {batch} views, got {len(views)}")
        if ranks is not None and c.background == "random" and any(v.background is None for v in views):
            raise ValueError("with ranks, give every view its background colour (a colour drawn here would differ between ranks)")
        n = len(self.model)
        degree = min(self.active_sh_degree, self.model.sh_degree)
        self.optimizer.lrs = self.learning_rates()

        loss_sum = psnr_sum = grads = None
        grid_grads, screens, ran, extra = [], [], None, {}
        for view in views:  # forward and backward of each view; gradients summed
            (loss, out, g, grad_grid, screen, quality) = self._view_gradients(view, degree, n, use_grid)
            loss_sum = loss if loss_sum is None else loss_sum + loss
            psnr_sum = quality if psnr_sum is None else psnr_sum + quality
            grads = g if grads is None else {k: grads[k] + g[k] for k in grads}
            if use_grid:
                grid_grads.append(grad_grid)
            screens.append((view.camera, screen))
            ran = out["ran"] if ran is None else ran
            if c.lambda_sparse_depth > 0:  # the same keys on every rank: 0 for a view that observes no point
                out.setdefault("sparse_depth_loss", mx.array(0.0))
            for key in ("depth_variance_loss", "normal_loss", "sparse_depth_loss"):
                if key in out:
                    extra[key] = out[key] if key not in extra else extra[key] + out[key]
            mx.eval(loss_sum, psnr_sum, grads, *grid_grads[-1:], *screen, *extra.values())
            del out
        plan = step_plan(c, views[0].camera, degree, self.step_count)
        r = plan.render
        if use_grid:
            # one slot per batch position: with ranks, the other ranks' slots arrive by the sum
            slots = dict(zip(positions, grid_grads))
            grid_grads = [slots.get(p, mx.zeros_like(grid_grads[0])) for p in range(batch)]
        if ranks is not None:
            loss_sum, psnr_sum, grads, grid_grads, extra = self._sum_over_ranks(loss_sum, psnr_sum, grads, grid_grads, extra)
        if batch > 1:
            grads = {k: v / batch for k, v in grads.items()}
            grid_grads = [g / batch for g in grid_grads]
        loss = loss_sum / batch if batch > 1 else loss_sum
        finite = all_finite([loss, *grads.values()] + grid_grads, r.backend)
        mx.eval(loss, grads, finite, *grid_grads)
        loss_value = float(loss)
        if not bool(finite):
            raise TrainingError(f"step {self.step_count + 1}: the loss or a gradient is not finite (loss {loss_value}); parameters left at the last good step")
        # Evaluated apart from the gradients, whose graph holds the old parameters, and with nothing here
        # holding them: Adam then writes the new parameters and moments over the old ones' memory.
        params = self.model.params
        self.model.params = self.optimizer.update(params, grads)
        del params, grads
        mx.eval(self.model.params, self.optimizer.m, self.optimizer.v)

        ran = ran + ["adam"]
        if use_grid:
            self._update_grids(batch_images, grid_grads)
        if "thickness_clamp" in plan.after_step:
            self.model.apply_2dgs_constraints(self.max_thickness)
            ran.append("thickness_clamp")
        if "sgld_noise" in plan.after_step:
            lr = self.optimizer.lrs["means"]
            isotropic = c.mcmc_noise_scale * self.scene_extent * math.sqrt(max(lr, 0.0))
            self.model.params["means"] = sgld_noise(self.model.params, lr, c.mcmc_noise_lr, self.rng, isotropic)
            ran.append("sgld_noise")
        self.step_count += 1

        if "screen_statistics" in plan.after_step:
            for camera, (grad2d, visible, radii) in screens:
                self.add_screen_statistics(camera, visible, grad2d, radii, r.backend)
            ran.append("screen_statistics")
        del screens

        info = {"step": self.step_count, "loss": loss_value, "psnr": float(psnr_sum) / batch}
        info.update({key: float(value) / batch for key, value in extra.items()})
        if batch > 1:
            info["batch_size"] = batch
        if plan.events and ranks is not None:
            ranks.check_same(f"model state before the events of step {self.step_count}", self.state_digest())
        for event in plan.events:
            info[event] = self._apply_event(event)
            ran.append(event)
        info["num_gaussians"] = len(self.model)  # after this step's density control
        info["stages"] = tuple(ran)
        # the original mlx3D's keys
        info.update({
            "method": c.method, "active_sh_degree": self.active_sh_degree, "lr_means": self.optimizer.lrs["means"],
            "densify": info["densify"] if "densify" in info else (
                {"relocated": info["relocate"], "added": info.get("grow", 0)} if "relocate" in info else None),
            "opacity_reset": "reset_opacity" in plan.events, "sh_degree_changed": "sh_up" in plan.events,
            "geometry": {"depth_variance": info.get("depth_variance_loss", 0.0), "normal_consistency": info.get("normal_loss", 0.0)},
        })
        return info

    def _view_gradients(self, view: TrainingView, degree: int, n: int, use_grid: bool) -> tuple:
        """Forward and backward of one view: (loss, render output, parameter gradients, grid gradient
        or None, screen statistics inputs [grad2d, visible, radii] or [], PSNR), all lazy."""
        c = self.config
        camera, image_index = view.camera, view.image_index
        bg = self.background_colour() if view.background is None else tuple(view.background)
        target = mx.array(view.target, dtype=mx.float32)
        mask = None if view.weight is None else mx.array(view.weight, dtype=mx.float32)
        plan = step_plan(c, camera, degree, self.step_count, sparse_points=view.points is not None)

        def loss_fn(p, offset, grid):
            return self._loss(p, offset, grid, camera, target, mask, bg, plan, degree, image_index if use_grid else None, view.points)

        grid_in = self.grid_optimizer.current(self.bilateral, image_index) if use_grid else mx.zeros((1,))
        # dL/d(means2d) through a zero offset, only for the densification statistics
        if "screen_statistics" in plan.after_step:
            (loss, out), (grads, grad2d, grad_grid) = mx.value_and_grad(loss_fn, argnums=(0, 1, 2))(self.model.params, mx.zeros((n, 2)), grid_in)
            screen = [grad2d, out["visible"], out["radii"]]
        else:
            (loss, out), (grads, grad_grid) = mx.value_and_grad(loss_fn, argnums=(0, 2))(self.model.params, None, grid_in)
            screen = []
        quality = psnr(out["image"], target, mask, clip=True, backend=plan.render.backend)
        return loss, out, grads, grad_grid if use_grid else None, screen, quality

    def _sum_over_ranks(self, loss, quality, grads: dict, grid_grads: list, extra: dict) -> tuple:
        """Every rank's sums of one step (losses, PSNRs, gradients, grid gradients per batch position) added
        over the ranks in one all_sum of a flat float32 buffer."""
        names = sorted(grads)
        parts = [mx.stack([loss, quality, *extra.values()]).astype(mx.float32)] + [grads[k].reshape(-1) for k in names]
        parts += [g.reshape(-1) for g in grid_grads]
        total = self.ranks.sum(mx.concatenate(parts), f"the gradient sum of step {self.step_count + 1}")
        head = 2 + len(extra)
        sizes = [head] + [grads[k].size for k in names] + [g.size for g in grid_grads]
        pieces = mx.split(total, np.cumsum(sizes)[:-1].tolist())
        grads = {k: p.reshape(grads[k].shape) for k, p in zip(names, pieces[1:])}
        grid_grads = [p.reshape(g.shape) for p, g in zip(pieces[1 + len(names):], grid_grads)]
        sums = pieces[0]
        return sums[0], sums[1], grads, grid_grads, dict(zip(extra, [sums[2 + i] for i in range(len(extra))]))

    def _update_grids(self, batch_images: list, grid_grads: list) -> None:
        """One grid Adam step from a batch's grid gradients (views of the same image add up)."""
        if len(batch_images) == 1:
            self.grid_optimizer.update(self.bilateral, batch_images[0], grid_grads[0])
            return
        by_image = {}
        for index, g in zip(batch_images, grid_grads):
            i = int(index) % self.bilateral.num_images
            by_image[i] = g if i not in by_image else by_image[i] + g
        self.grid_optimizer.update(self.bilateral, list(by_image), mx.stack(list(by_image.values())))

    def state_digest(self) -> bytes:
        """Bytes identifying the training state (step, SH degree, parameters, Adam's step), for comparing ranks."""
        from .distributed import digest

        return digest(self.step_count, self.active_sh_degree, self.optimizer.step_count,
                      *(self.model.params[k] for k in sorted(self.model.params)))

    def add_screen_statistics(self, camera, visible, grad2d, radii, backend: str = "auto") -> None:
        """Adds one view to the density statistics: visible (N,) bool, grad2d (N,2) dL/d(means2d) in
        pixels, radii (N,). The screen-space gradient is taken in NDC units (as 3DGS's threshold expects)."""
        from ..render.rasterize import resolve_backend

        self.statistics.add(camera, visible, grad2d, radii, resolve_backend(backend))

    def _apply_event(self, event: str):
        c = self.config
        if event == "sh_up":
            self.active_sh_degree = min(self.active_sh_degree + 1, self.model.sh_degree)
            self.model.active_sh_degree = self.active_sh_degree  # where the original mlx3D keeps it
            return self.active_sh_degree
        if event == "densify":
            accum, count, radii = self.statistics.arrays() if self.ranks is None else self.statistics.reduce(self.ranks)
            params, counts = densify_and_prune(
                self.model.params, accum, count, c.densify_grad_threshold, self.scene_extent, c.percent_dense,
                c.prune_opacity, self.optimizer, c.max_screen_size if self.opacity_resets else None, radii,
                c.max_gaussians, self.rng, self.scene_centre,
                None if c.backdrop_distance is None else c.backdrop_distance * self.scene_extent,
            )
            self._set_params(params)
            return counts
        if event == "relocate":
            params, moved = relocate_dead(self.model.params, self.optimizer, c.mcmc_min_opacity, self.rng, c.mcmc_relocate_frac, c.mcmc_jitter_scale)
            self.model.params = params
            return moved
        if event == "grow":
            params, added = add_gaussians_mcmc(self.model.params, self.optimizer, c.max_gaussians, c.mcmc_growth, self.rng, c.mcmc_min_opacity) if c.max_gaussians else (self.model.params, 0)
            if added:
                self._set_params(params)
            return added
        if event == "reset_opacity":
            self.model.params = reset_opacities(self.model.params, self.optimizer)
            self.opacity_resets += 1
            return True
        raise ValueError(event)

    def _set_params(self, params: dict):
        """Replace the model's parameters after a change of count."""
        self.model.params = params
        self.model._drop_extra("densification")
        self._reset_stats()
        if self.config.low_memory:
            mx.clear_cache()

    # ------------------------------------------------------------------ loop
    def fit(self, dataset, steps: int | None = None, progress=None, should_stop=None) -> list:
        """Train on ``dataset.train`` views in random order; returns per-step info.

        Each step draws ``batch_size`` views (with their background colours); with
        ``ranks``, every rank draws the same ones and renders its share. progress(done,
        total, info) is called after every step; should_stop() is polled to cancel (the
        model keeps the last completed step; with ranks, every rank stops after the
        same step when any rank's should_stop() says so).
        """
        steps = self.config.steps if steps is None else steps
        train = list(dataset.train)
        if not train:
            raise ValueError("the dataset has no training views")
        if self.config.bilateral_grid and self.bilateral is None:
            self._make_grid(len(dataset.frames))
        if self.config.method == "mcmc" and self.config.max_gaussians is None:
            from .initial import image_pixels, mcmc_budget

            self.config = replace(self.config, max_gaussians=mcmc_budget(len(self.model), image_pixels(dataset)))
        if self.scene_centre is None:
            self.scene_centre = dataset.scene_centre()
        batch, ranks = self.config.batch_size, self.ranks
        if ranks is not None:
            if batch < ranks.size:
                raise ValueError(f"batch_size {batch} is smaller than the {ranks.size} ranks: each rank renders at least one view of a step")
            ranks.check_same("configuration and dataset", self._run_digest(dataset))
            ranks.check_same("model state at the start", self.state_digest())
        positions = ranks.positions(batch) if ranks is not None else list(range(batch))
        spec = self.training_background(dataset)
        targets = self.sparse_depth_targets(dataset)
        history = []
        for i in range(steps):
            stop = should_stop is not None and should_stop()
            if ranks is not None and should_stop is not None:
                stop = bool(ranks.host_sum(np.array([float(stop)]), "the agreement to stop")[0] > 0)
            if stop:
                break
            # the batch's views and background colours, drawn in the same order on every rank
            drawn = [(train[int(self.rng.integers(len(train)))], self.background_colour(spec)) for _ in range(batch)]
            views = []
            for index, colour in (drawn[p] for p in positions):  # the target is composited on the colour the render uses
                image, weight = dataset.load_image(index, background=colour, rng=self.rng)
                views.append(TrainingView(dataset.frames[index].camera, image, weight, colour, index, targets.get(index)))
            info = self.step_batch(views, [index for index, _ in drawn])
            history.append(info)
            if self.config.checkpoint_every and self.config.checkpoint_dir and self.step_count % self.config.checkpoint_every == 0:
                self.save_checkpoint(os.path.join(self.config.checkpoint_dir, "checkpoint.npz"))
            if progress is not None:
                progress(i + 1, steps, info)
        return history

    def sparse_depth_targets(self, dataset) -> dict:
        """{frame index: ``TrainingView.points``} of the training frames that observe sparse points (the solve's
        ``dataset.observations``), when ``lambda_sparse_depth`` is on; else, or without observations, {}."""
        if not self.config.lambda_sparse_depth > 0 or dataset.observations is None:
            return {}
        targets = {}
        for index in dataset.train:
            pixels, point_index = dataset.observations[index]
            found = sparse_points(dataset.frames[index].camera, dataset.points, pixels, point_index) if len(point_index) else None
            if found is not None:
                targets[index] = found
        return targets

    def _run_digest(self, dataset) -> bytes:
        """Bytes identifying the settings and the training cameras of a run (not where it writes)."""
        from .distributed import digest

        settings = {k: v for k, v in asdict(self.config).items() if k not in ("checkpoint_dir", "extra")}
        cameras = [(f.camera.width, f.camera.height, np.asarray(f.camera.K), np.asarray(f.camera.world_to_camera_matrix))
                   for f in (dataset.frames[i] for i in dataset.train)]
        return digest(sorted(settings.items()), list(dataset.train), *(x for cam in cameras for x in cam))

    def training_background(self, dataset):
        """The background spec training steps on ``dataset`` use: ``opaque_background`` when its
        training photos are opaque (see ``initial.opaque_photos``; checked once per dataset), else ``background``."""
        from .initial import opaque_photos, training_background

        if self._opaque_dataset is not dataset:  # opaque_photos reads a few images: once per dataset
            self._opaque_dataset, self._opaque = dataset, self.config.opaque_background is not None and opaque_photos(dataset)
        return training_background(self.config, self._opaque)

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path) -> None:
        """Parameters, optimizer state, step, schedule and random state in one .npz (written atomically).

        With ``ranks`` every rank calls it: the ranks check they agree and sum their statistics,
        and rank 0 alone writes."""
        from ..io.atomic import atomic_write

        if self.ranks is not None:
            self.ranks.check_same(f"model state at the checkpoint of step {self.step_count}", self.state_digest())
            self.statistics.reduce(self.ranks)  # rank 0 now holds every rank's statistics
            if self.ranks.rank != 0:
                return

        state = {f"param/{k}": np.array(v) for k, v in self.model.params.items()}
        state.update({f"adam/{k}": v for k, v in self.optimizer.state_dict().items()})
        state.update(
            step=np.array(self.step_count), active_sh_degree=np.array(self.active_sh_degree), opacity_resets=np.array(self.opacity_resets),
            grad_accum=self.grad_accum, grad_count=self.grad_count, max_radii=self.max_radii, scene_extent=np.array(self.scene_extent),
            rng_state=np.array(json.dumps(self.rng.bit_generator.state)),
            config=np.array(json.dumps({k: v for k, v in asdict(self.config).items() if k != "extra"})),
        )
        if self.scene_centre is not None:
            state["scene_centre"] = self.scene_centre
        if self.bilateral is not None:
            self.grid_optimizer.sync(self.bilateral)
            state["bilateral_grid"] = np.array(self.bilateral.params)
            state.update({f"grid_adam/{k}": v for k, v in self.grid_optimizer.state_dict().items()})
        with atomic_write(path) as f:
            np.savez(f, **state)

    @staticmethod
    def checkpoint_config(path) -> TrainerConfig | None:
        """The settings a checkpoint was written with (defaults resolved, ``extra`` left out), or None for a
        checkpoint from before they were stored."""
        with np.load(path) as data:
            if "config" not in data.files:
                return None
            stored = json.loads(str(data["config"]))
        for name in ("background", "opaque_background", "bilateral_grid_shape"):
            if isinstance(stored.get(name), list):
                stored[name] = tuple(stored[name])
        known = {f for f in TrainerConfig.__dataclass_fields__}
        return TrainerConfig(**{k: v for k, v in stored.items() if k in known})

    @classmethod
    def load_checkpoint(cls, path, config: TrainerConfig | None = None, ranks=None) -> "GaussianTrainer":
        """A trainer resuming exactly where ``save_checkpoint`` left off (with ``ranks``: every rank
        loads the file; rank 0 keeps its densification statistics, the others start theirs at zero).
        config: None for the checkpoint's own settings (``checkpoint_config``)."""
        if config is None:
            config = cls.checkpoint_config(path)
        with np.load(path) as data:
            state = {k: data[k] for k in data.files}
        model = GaussianModel({k: mx.array(state[f"param/{k}"]) for k in PARAM_NAMES})
        trainer = cls(model, config, float(state["scene_extent"]), scene_centre=state.get("scene_centre"), ranks=ranks)
        trainer.optimizer.load_state_dict({k[5:]: v for k, v in state.items() if k.startswith("adam/")})
        trainer.step_count = int(state["step"])
        trainer.active_sh_degree = int(state["active_sh_degree"])
        trainer.opacity_resets = int(state["opacity_resets"])
        trainer.grad_accum, trainer.grad_count, trainer.max_radii = (np.array(state[k], dtype=np.float64) for k in ("grad_accum", "grad_count", "max_radii"))
        if trainer.ranks is not None and trainer.ranks.rank != 0:  # the sums live on rank 0
            trainer.grad_accum, trainer.grad_count = np.zeros_like(trainer.grad_accum), np.zeros_like(trainer.grad_count)
        trainer.rng.bit_generator.state = json.loads(str(state["rng_state"]))
        if "bilateral_grid" in state:
            trainer._make_grid(state["bilateral_grid"].shape[0])
            trainer.bilateral.params = mx.array(state["bilateral_grid"])
            trainer.grid_optimizer.load_state_dict({k[10:]: v for k, v in state.items() if k.startswith("grid_adam/")})
        return trainer

    def config_dict(self) -> dict:
        return asdict(self.config)
