"""DINO self-distillation over token sets: the projection head and the loss with one center per set, and the
additions of DINOv2 that Sparsh-skin uses: the iBOT masked-token loss and the KoLeo regularizer.

Sparsh-X (docs/reference/sparshx_state_dict.md "Pretraining details of the original"): one projection head shared by
the token sets (Linear D->h, GELU, h->h, GELU, h->bottleneck, L2-normalize, weight-normed Linear bottleneck->K
without bias whose norm is fixed to 1), applied to each set's register token; per set a cross-entropy between the
teacher's centered, sharpened softmax on the global view and the student's softmax on every view (same-view pair
included), summed over the student's views and over the sets; a center per set, an EMA of the teacher's outputs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn


class DINOHead(nn.Module):
    """Projection head: (..., in_dim) -> (..., prototypes) logits (cosine similarities to the prototypes).

    The prototypes are stored as free directions ``v`` and used normalized, ``W = v / |v|`` row by row: the
    weight-normed last layer of DINO with its norm g fixed to 1 (so only directions are learned).
    """

    def __init__(self, in_dim: int, hidden: int = 2048, bottleneck: int = 256, prototypes: int = 65536):
        super().__init__()
        if min(in_dim, hidden, bottleneck, prototypes) < 1:
            raise ValueError(f"DINOHead: sizes must be >= 1, got in_dim={in_dim}, hidden={hidden}, "
                             f"bottleneck={bottleneck}, prototypes={prototypes}")
        self.mlp = nn.Sequential(
            nn.Linear(in_dim, hidden), nn.GELU(),
            nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, bottleneck),
        )
        self.prototypes = nn.Parameter(torch.empty(prototypes, bottleneck))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # DINO's initialization: truncated normal (std 0.02) weights, zero biases
        for m in self.mlp:
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)
        nn.init.trunc_normal_(self.prototypes, std=0.02)

    def forward(self, x: Tensor) -> Tensor:
        z = F.normalize(self.mlp(x), dim=-1, eps=1e-6)  # (..., bottleneck), unit norm
        return F.linear(z, F.normalize(self.prototypes, dim=-1, eps=1e-6))  # (..., K) in [-1, 1]


class DINOLoss(nn.Module):
    """Cross-entropy between teacher and student prototype distributions, one center per token set.

    Args:
        names: the token sets (one center each, in this order in the ``center`` buffer).
        prototypes: K, the head's output size.
        student_temp: temperature of the student's softmax (DINO: 0.1).
        center_momentum: EMA momentum of the centers (DINO: 0.9).
    """

    def __init__(self, names: Sequence[str], prototypes: int, student_temp: float = 0.1,
                 center_momentum: float = 0.9):
        super().__init__()
        if not names or len(set(names)) != len(names):
            raise ValueError(f"DINOLoss: token set names must be distinct and non-empty, got {list(names)}")
        if not student_temp > 0 or not 0.0 <= center_momentum < 1.0:
            raise ValueError(f"DINOLoss: need student_temp > 0 and center_momentum in [0, 1), got {student_temp}, "
                             f"{center_momentum}")
        self.names = tuple(names)
        self.student_temp = float(student_temp)
        self.center_momentum = float(center_momentum)
        self.register_buffer("center", torch.zeros(len(self.names), prototypes))  # (S, K)

    def teacher_probs(self, teacher: Mapping[str, Tensor], teacher_temp: float) -> dict[str, Tensor]:
        """{set: (B, K)} softmax((t - center) / teacher_temp), float32, no gradient."""
        return {n: F.softmax((teacher[n].detach().float() - self.center[i]) / teacher_temp, dim=-1)
                for i, n in enumerate(self.names)}

    def forward(self, student: Mapping[str, Tensor], teacher: Mapping[str, Tensor], teacher_temp: float
                ) -> tuple[Tensor, dict[str, Tensor]]:
        """Total loss and the loss per token set.

        Args:
            student: {set: (V, B, K)} logits of the student's V views.
            teacher: {set: (B, K)} logits of the teacher's global view.
            teacher_temp: the teacher's temperature at this step (see ``schedules.teacher_temperature``).
        """
        probs = self.teacher_probs(teacher, teacher_temp)
        per_set: dict[str, Tensor] = {}
        for n in self.names:
            log_p = F.log_softmax(student[n].float() / self.student_temp, dim=-1)  # (V, B, K)
            per_set[n] = -(probs[n][None] * log_p).sum(dim=-1).mean(dim=-1).sum()  # mean over batch, sum over views
        return torch.stack(list(per_set.values())).sum(), per_set

    def views_loss(self, student: Mapping[str, Tensor], teacher: Mapping[str, Tensor], teacher_temp: float
                   ) -> tuple[Tensor, dict[str, Tensor]]:
        """DINOv2's cross-view loss with several teacher views: total and per token set.

        Args:
            student: {set: (V, B, K)} logits of the student's V views; its first T views are the teacher's views
                in the same order (the global views), the others local views.
            teacher: {set: (T, B, K)} logits of the teacher's T views.
            teacher_temp: the teacher's temperature at this step.

        Cross-entropy (mean over the batch) of every (student view s, teacher view t) pair with s != t (a view is
        not its own target), averaged over those pairs and summed over the sets.
        """
        probs = self.teacher_probs(teacher, teacher_temp)  # {set: (T, B, K)}
        per_set: dict[str, Tensor] = {}
        for n in self.names:
            log_p = F.log_softmax(student[n].float() / self.student_temp, dim=-1)  # (V, B, K)
            v, t = log_p.shape[0], probs[n].shape[0]
            if v < t:
                raise ValueError(f"DINOLoss.views_loss: {v} student views for {t} teacher views (the student's first "
                                 "views must be the teacher's)")
            ce = -torch.einsum("tbk,vbk->tv", probs[n], log_p) / log_p.shape[1]  # (T, V) mean over the batch
            keep = ~torch.eye(t, v, dtype=torch.bool, device=ce.device)  # drop the same-view pairs
            per_set[n] = ce[keep].mean()
        return torch.stack(list(per_set.values())).sum(), per_set

    @torch.no_grad()
    def update_center(self, teacher: Mapping[str, Tensor]) -> None:
        """center = m center + (1 - m) mean of the teacher's logits over the batch (and views: (..., K)), over
        every process."""
        batch_center = torch.stack([_rows(teacher[n]).mean(dim=0) for n in self.names])  # (S, K)
        if dist.is_available() and dist.is_initialized():
            dist.all_reduce(batch_center)
            batch_center /= dist.get_world_size()
        self.center.mul_(self.center_momentum).add_(batch_center, alpha=1.0 - self.center_momentum)


def _rows(x: Tensor) -> Tensor:
    """(..., K) -> (N, K) float32 rows, detached (a batch, or views x batch)."""
    return x.detach().float().reshape(-1, x.shape[-1])


class IBOTLoss(DINOLoss):
    """iBOT's masked-token loss (Zhou et al. 2022; DINOv2): at every token the student saw as the mask token, the
    cross-entropy between the teacher's centered, sharpened distribution of the visible token and the student's
    distribution; one center per token set (apart from DINO's, as in DINOv2), an EMA of the teacher's outputs at
    the masked tokens.

    Same arguments as :class:`DINOLoss`.
    """

    def forward(self, student: Mapping[str, Tensor], teacher: Mapping[str, Tensor], teacher_temp: float
                ) -> tuple[Tensor, dict[str, Tensor]]:
        """Total loss and the loss per token set.

        Args:
            student: {set: (M, K)} logits at the masked tokens (all samples and views together).
            teacher: {set: (M, K)} the teacher's logits at the same tokens.
            teacher_temp: the teacher's temperature at this step.

        Mean over the M masked tokens, summed over the sets; a set without masked tokens adds 0.
        """
        probs = self.teacher_probs(teacher, teacher_temp)
        per_set: dict[str, Tensor] = {}
        for n in self.names:
            s = student[n].float()
            if s.shape[0] == 0:
                per_set[n] = s.sum() * 0.0  # keeps the graph (and DDP's gradient hooks) intact
                continue
            log_p = F.log_softmax(s / self.student_temp, dim=-1)  # (M, K)
            per_set[n] = -(probs[n] * log_p).sum(dim=-1).mean()
        return torch.stack(list(per_set.values())).sum(), per_set

    @torch.no_grad()
    def update_center(self, teacher: Mapping[str, Tensor]) -> None:
        """center = m center + (1 - m) mean of the teacher's logits at the masked tokens of every process; a set
        with no masked token anywhere keeps its center."""
        sums = torch.stack([_rows(teacher[n]).sum(dim=0) for n in self.names])  # (S, K)
        counts = torch.tensor([float(_rows(teacher[n]).shape[0]) for n in self.names], device=sums.device)  # (S,)
        if dist.is_available() and dist.is_initialized():
            dist.all_reduce(sums)
            dist.all_reduce(counts)
        seen = counts > 0
        mean = sums / counts.clamp_min(1.0)[:, None]
        updated = self.center * self.center_momentum + mean * (1.0 - self.center_momentum)
        self.center.copy_(torch.where(seen[:, None], updated, self.center))


def koleo_loss(x: Tensor, eps: float = 1e-8) -> Tensor:
    """KoLeo regularizer (DINOv2, from the Kozachenko-Leonenko entropy estimator; Sablayrolles et al. 2019):
    ``-mean_i log(|x_i - x_nn(i)|)`` over the L2-normalized rows of ``x`` (B, D), nn(i) the nearest other row.
    Spreads a batch's features over the sphere. The neighbour is found without gradient; the distance is
    ``|x_i - x_j + eps|`` (as torch's pairwise distance), finite for identical rows. Fewer than 2 rows: 0."""
    if x.shape[0] < 2:
        return x.sum() * 0.0
    z = F.normalize(x.float(), dim=-1, eps=eps)  # (B, D)
    with torch.no_grad():
        sim = z @ z.T  # (B, B)
        sim.fill_diagonal_(-2.0)  # never oneself (cosines are >= -1)
        nearest = sim.argmax(dim=1)  # (B,)
    d = (z - z[nearest] + eps).norm(dim=-1)  # (B,)
    return -torch.log(d + eps).mean()


def teacher_entropy(probs: Mapping[str, Tensor]) -> tuple[float, float]:
    """Collapse monitors: mean entropy of the teacher's per-sample distributions (-> 0 when they become one-hot)
    and entropy of their batch mean (-> 0 when every sample picks the same prototype), averaged over sets (nats).
    Distributions (..., K) of several views count as more samples."""
    per, mean = [], []
    for p in probs.values():
        p = p.reshape(-1, p.shape[-1])
        per.append(-(p * torch.log(p.clamp_min(1e-12))).sum(-1).mean())
        m = p.mean(0)
        mean.append(-(m * torch.log(m.clamp_min(1e-12))).sum())
    return float(torch.stack(per).mean()), float(torch.stack(mean).mean())
