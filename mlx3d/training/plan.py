"""What one training step runs, decided in one place (effects on demand).

``step_plan(config, camera, ...)`` lists the stages a step runs for a
configuration, a camera and the point in the schedule: the render stages
(``mlx3d.render.plan_render``: projection mode, antialias compensation, SH
degree evaluated, the channels composited), the colour correction, each loss
term, what is applied after the optimizer step, and the schedule events.
A stage is listed only when its effect is on: a zero weight, a method that
does not use it, or a step before it starts means it does not run at all
(no channel rendered, no term built). ``GaussianTrainer.step`` follows this
plan and reports the stages it actually ran in ``info["stages"]``;
``mlx3d info --plan`` prints it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..render import RenderPlan, plan_render


OPTIONAL_STAGES = (
    "antialias_compensation", "gaussian_normals", "bilateral_grid", "loss_dssim", "loss_depth_variance",
    "loss_normal_consistency", "loss_sparse_depth", "loss_bilateral_tv", "loss_opacity_l1", "loss_scale_l1", "thickness_clamp", "sgld_noise",
    "screen_statistics",
)
GEOMETRY_CHANNELS = ("depth", "depth2", "normals")


@dataclass(frozen=True)
class StepPlan:
    """The stages of one training step, in the order they run."""

    render: RenderPlan
    colour_correction: tuple  # ('bilateral_grid',) or ()
    losses: tuple  # loss terms: 'l1', 'dssim', 'depth_variance', 'normal_consistency', 'sparse_depth', 'bilateral_tv', 'opacity_l1',
    # 'scale_l1'
    after_step: tuple  # 'thickness_clamp' (2dgs), 'sgld_noise' (mcmc), 'screen_statistics' (until the last densification)
    events: tuple  # schedule events after this step (see trainer.events_at)

    @property
    def skipped(self) -> tuple:
        """The optional stages and channels this step does not run, e.g. ``('antialias_compensation', 'channel_normals')``."""
        ran = set(self.stages)
        channels = {c.replace("_planes", "") for c in self.render.channels}
        return tuple(s for s in OPTIONAL_STAGES if s not in ran) + tuple(f"channel_{c}" for c in GEOMETRY_CHANNELS if c not in channels)

    @property
    def stages(self) -> tuple:
        return (
            self.render.stages + self.colour_correction + tuple(f"loss_{name}" for name in self.losses)
            + ("adam",) + self.after_step + self.events
        )


def active_sh_degree(config, steps_done: int, max_degree: int) -> int:
    """The SH degree a step evaluates after ``steps_done`` steps (raised every ``sh_increase_every``, capped at ``max_degree``)."""
    if not config.sh_increase_every:
        return max_degree
    return min(steps_done // config.sh_increase_every, max_degree)


def gathers_screen_statistics(config, step: int) -> bool:
    """Whether step ``step`` (1-based) adds to the statistics that densification reads (screen-space
    gradients and radii): only when a 'densify' event comes at this step or later (vanilla and 2DGS;
    MCMC's relocation and growth read opacities only)."""
    if config.method == "mcmc":
        return False
    first = max(step, config.densify_from + 1)
    event = -(-first // config.densify_every) * config.densify_every  # the next multiple of densify_every
    return event <= config.densify_until


def step_plan(config, camera, sh_degree: int, step: int = 0, backend: str = "auto", sparse_points: bool = False) -> StepPlan:
    """The plan of training step ``step + 1`` (``step`` steps done) for ``config``
    on ``camera`` with SH evaluated up to ``sh_degree`` (the active degree); ``sparse_points``: the view
    observes sparse points (``TrainingView.points``), which ``lambda_sparse_depth`` needs."""
    from .trainer import events_at

    geometry = step >= config.geometry_from
    depth_variance = geometry and config.lambda_2d_depth_variance > 0
    normals = geometry and config.lambda_2d_normal_consistency > 0
    sparse_depth = sparse_points and config.lambda_sparse_depth > 0
    render = plan_render(
        camera, sh=np.zeros((0, (sh_degree + 1) ** 2, 3)), sh_degree=sh_degree, projection=config.projection, antialias=config.antialias,
        render_depth=normals or sparse_depth, backend=backend, render_depth_variance=depth_variance, render_normals=normals,
        planar_depth=config.method == "2dgs",
    )
    losses = ["l1"]
    if config.lambda_dssim > 0:
        losses.append("dssim")
    if depth_variance:
        losses.append("depth_variance")
    if normals:
        losses.append("normal_consistency")
    if sparse_depth:
        losses.append("sparse_depth")
    if config.bilateral_grid is True and config.lambda_bilateral_tv > 0:
        losses.append("bilateral_tv")
    if config.method == "mcmc":
        if config.mcmc_opacity_reg > 0:
            losses.append("opacity_l1")
        if config.mcmc_scale_reg > 0:
            losses.append("scale_l1")
    after = []
    if config.method == "2dgs":
        after.append("thickness_clamp")
    if config.method == "mcmc" and (config.mcmc_noise_lr > 0 or config.mcmc_noise_scale > 0):
        after.append("sgld_noise")
    if gathers_screen_statistics(config, step + 1):
        after.append("screen_statistics")
    return StepPlan(render, ("bilateral_grid",) if config.bilateral_grid is True else (), tuple(losses), tuple(after), events_at(config, step + 1))

