"""Training losses: the BAN tracking loss (L_trc), the conditional eps-MSE (L_align, eq. 6)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .denoiser import Denoiser


def ban_cls_loss(cls: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """0.5 * NLL over positive points + 0.5 * NLL over negative points (label -1 is ignored)."""
    logp = F.log_softmax(cls, dim=1)
    pos, neg = label == 1, label == 0
    loss_pos = -logp[:, 1][pos].mean() if pos.any() else cls.sum() * 0
    loss_neg = -logp[:, 0][neg].mean() if neg.any() else cls.sum() * 0
    return 0.5 * loss_pos + 0.5 * loss_neg


def regression_points(target: torch.Tensor, label: torch.Tensor, region: str = "ellipse") -> torch.Tensor:
    """Where the box is regressed: BAN's positive points ("ellipse"), or also every point inside the box
    ("box", as Ocean/LightTrack train theirs): the tracker often picks a cell off the target's centre (the
    window and the size penalty move it), and its box is only as good as that cell was trained."""
    points = label == 1
    if region == "box":
        points = points | (target > 0).all(dim=1)
    return points


def distances_at_regression_points(loc: torch.Tensor, target: torch.Tensor, label: torch.Tensor,
                                   region: str) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Predicted and target (l, t, r, b) as (N, 4) rows at the regression points; None where there are none."""
    points = regression_points(target, label, region)
    if not points.any():
        return None
    return loc.permute(0, 2, 3, 1)[points], target.permute(0, 2, 3, 1)[points]


def ban_iou_loss(loc: torch.Tensor, target: torch.Tensor, label: torch.Tensor, region: str = "ellipse") -> torch.Tensor:
    """Linear IoU loss 1 - IoU between predicted and target (l, t, r, b) boxes at the regression points."""
    pairs = distances_at_regression_points(loc, target, label, region)
    if pairs is None:
        return loc.sum() * 0
    p, t = pairs
    pl, pt, pr, pb = p.unbind(1)
    tl, tt, tr, tb = t.unbind(1)
    inter = (torch.minimum(pl, tl) + torch.minimum(pr, tr)) * (torch.minimum(pt, tt) + torch.minimum(pb, tb))
    union = (pl + pr) * (pt + pb) + (tl + tr) * (tt + tb) - inter
    iou = (inter + 1.0) / (union + 1.0)
    return (1.0 - iou).mean()


def ban_side_log_loss(loc: torch.Tensor, target: torch.Tensor, label: torch.Tensor, region: str = "ellipse",
                      floor: float = 4.0) -> torch.Tensor:
    """Mean |log((p + f) / (t + f))| over the four distances at the regression points, f in crop px.

    The IoU loss weighs an error on a side by the whole box: from a point a quarter of a thin target off its
    centre, reading the near side 4 px long costs it what the width grows by, a few percent. Measured per
    side it costs that side's own ratio, so the near side is read as carefully as the far one. The floor
    keeps a point at the target's very edge (t -> 0) from dominating."""
    pairs = distances_at_regression_points(loc, target, label, region)
    if pairs is None:
        return loc.sum() * 0
    p, t = pairs
    return ((p + floor).log() - (t.clamp_min(0.0) + floor).log()).abs().mean()


def align_loss(denoiser: Denoiser, alpha_bar: torch.Tensor, x0: torch.Tensor, cond: torch.Tensor,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """E ||eps - eps_theta([X_t || N_f], t)||^2 with t uniform over the schedule and X_t noised from X_0."""
    n = x0.shape[0]
    t = torch.randint(0, alpha_bar.numel(), (n,), generator=generator, device=x0.device)
    eps = torch.randn(x0.shape, generator=generator, device=x0.device)
    ab = alpha_bar[t].view(n, 1, 1, 1)
    xt = ab.sqrt() * x0 + (1.0 - ab).sqrt() * eps
    pred = denoiser(torch.cat([xt, cond], dim=1), t.float())
    return F.mse_loss(pred, eps)


def relative_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """MSE against a detached target, relative to the target's power (so feature scale does not set the weight)."""
    target = target.detach()
    return F.mse_loss(pred, target) / target.pow(2).mean().clamp_min(1e-6)


def chain_align_loss(night_out: torch.Tensor, day_out: torch.Tensor) -> torch.Tensor:
    """MSE between the sampler's output on night features and its (detached) output on the paired day frame,
    relative to the day output's power: the x0 form of eq. 6 on the deterministic chain used at inference.

    With the release's schedule (alpha-bar >= 0.82) the eps form weights the x0 error by alpha-bar/(1 - alpha-bar),
    up to 1e6 at t = 0, so on paired day/night features it stays at ~1.0 (eps_theta cannot beat predicting 0);
    the x0 form drops that weighting and measures the alignment itself.
    """
    return relative_mse(night_out, day_out)


def restore_loss(night_aligned: torch.Tensor, day_aligned: torch.Tensor, day_neck: torch.Tensor) -> torch.Tensor:
    """Paired feature restoration: the aligned features of a night crop should be the neck features of the
    same crop by day (detached), and by day the block should leave the neck features as they are; each term
    relative to the day features' power. Needs night rendered from the day frames (paired)."""
    return relative_mse(night_aligned, day_neck) + relative_mse(day_aligned, day_neck)


def distill_cls_loss(cls: torch.Tensor, teacher_prob: torch.Tensor) -> torch.Tensor:
    """Soft-target cross-entropy of the student's foreground probability against the teacher's, every cell."""
    return F.binary_cross_entropy_with_logits(cls[:, 1] - cls[:, 0], teacher_prob)


def distill_loc_loss(loc: torch.Tensor, teacher_loc: torch.Tensor, teacher_prob: torch.Tensor) -> torch.Tensor:
    """L1 between log box distances where the teacher sees the target (its probability > 0.5)."""
    sure = teacher_prob > 0.5
    if not sure.any():
        return loc.sum() * 0
    diff = (loc.clamp_min(1e-3).log() - teacher_loc.clamp_min(1e-3).log()).abs()
    return diff.permute(0, 2, 3, 1)[sure].mean()


def feature_distill_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """1 - cosine similarity per position between adapted student features and the teacher's (scale-free)."""
    return (1.0 - F.cosine_similarity(student, teacher, dim=1)).mean()
