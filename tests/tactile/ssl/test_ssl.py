"""SSL pieces: block masks and their bounds, the DINO head and loss on hand-worked numbers, centering, EMA,
schedules and optimizer groups."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from rotation.tactile.ssl import (
    DINOHead,
    DINOLoss,
    MaskConfig,
    block_shape,
    cosine,
    ema_momentum,
    ema_update,
    param_groups,
    sample_set_views,
    sample_views,
    set_hyperparameters,
    step_rng,
    teacher_temperature,
    warmup_cosine,
)

GRIDS = {"img": (14, 14), "mic": (14, 16), "imu": (56,), "pressure": (56,)}


@pytest.mark.parametrize("name", list(GRIDS))
def test_masks_respect_their_bounds(name):
    grid = GRIDS[name]
    n = math.prod(grid)
    cfg = MaskConfig()
    avoided = total = 0
    for step in range(40):
        views = sample_set_views(grid, 16, cfg, step_rng(0, step))
        assert len(views) == 1 + cfg.num_local
        for v in views:
            assert v.dtype == np.int64 and v.ndim == 2 and v.shape[0] == 16
            assert cfg.min_keep <= v.shape[1] <= n
            assert v.min() >= 0 and v.max() < n
            assert (np.diff(v, axis=1) > 0).all()  # sorted, no repeats
        g, locals_ = views[0], views[1:]
        # global: at most its block, at least the scale's lower bound unless the locals took the rest
        assert g.shape[1] <= max(block_shape(grid, 1.0, cfg.min_keep)[0] * block_shape(grid, 1.0)[1], n)
        lsize = locals_[0].shape[1]
        assert all(v.shape[1] == lsize for v in locals_)  # one local block size per step and set
        assert cfg.min_keep <= lsize <= math.ceil(cfg.local_scale[1] * n) + max(grid)
        for b in range(16):
            union = set(np.concatenate([v[b] for v in locals_]).tolist())
            total += 1
            avoided += not (set(g[b].tolist()) & union)
    assert avoided / total > 0.9  # the fallback (overlap) is rare at the default scales


def test_local_blocks_are_contiguous_blocks():
    views = sample_set_views((14, 16), 8, MaskConfig(local_scale=(0.25, 0.25)), step_rng(1, 0))
    bh, bw = block_shape((14, 16), 0.25, 4)
    assert (bh, bw) == (7, 8)
    for v in views[1:]:
        rows, cols = v // 16, v % 16
        for b in range(8):
            assert rows[b].max() - rows[b].min() == bh - 1 and cols[b].max() - cols[b].min() == bw - 1
    seg = sample_set_views((56,), 4, MaskConfig(local_scale=(0.25, 0.25)), step_rng(1, 0))[1]
    assert seg.shape == (4, 14) and (np.diff(seg, axis=1) == 1).all()  # contiguous 1-D segments


def test_global_avoids_locals_and_keeps_min_when_crowded():
    # locals that cover almost everything: the global view still keeps >= min_keep tokens
    cfg = MaskConfig(global_scale=(0.5, 0.5), local_scale=(0.48, 0.48), num_local=4, min_keep=4)
    for step in range(20):
        views = sample_set_views((10,), 32, cfg, step_rng(2, step))
        assert views[0].shape[1] >= 4
    # roomy locals: the global view never shares a token with them
    cfg = MaskConfig(global_scale=(1.0, 1.0), local_scale=(0.1, 0.1), num_local=4)
    views = sample_set_views((14, 14), 32, cfg, step_rng(3, 0))
    for b in range(32):
        assert not set(views[0][b].tolist()) & set(np.concatenate([v[b] for v in views[1:]]).tolist())
    # truncated to the batch minimum: 196 tokens minus at most 4 local blocks of 4 x 5 tokens
    assert block_shape((14, 14), 0.1) == (4, 5)
    assert 196 - 80 <= views[0].shape[1] <= 196 - 20


def test_block_shape_and_min_keep():
    assert block_shape((14, 14), 1.0) == (14, 14)
    assert block_shape((14, 16), 1.0) == (14, 16)  # wider than a square: stretched to keep the area
    assert block_shape((56,), 0.25) == (1, 14)
    assert block_shape((14, 14), 0.001, min_keep=4) == (2, 2)
    assert block_shape((3,), 0.01, min_keep=2) == (1, 2)
    with pytest.raises(ValueError, match="min_keep"):
        sample_set_views((3,), 2, MaskConfig(min_keep=4), step_rng(0, 0))


def test_views_are_a_pure_function_of_seed_and_step():
    a = sample_views(GRIDS, 4, MaskConfig(), step_rng(5, 7))
    b = sample_views(GRIDS, 4, MaskConfig(), step_rng(5, 7))
    c = sample_views(GRIDS, 4, MaskConfig(), step_rng(5, 8))
    assert len(a) == 5 and set(a[0]) == set(GRIDS)
    assert all(torch.equal(x[k], y[k]) for x, y in zip(a, b, strict=True) for k in GRIDS)
    assert not all(torch.equal(x[k], y[k]) for x, y in zip(a, c, strict=True) for k in GRIDS)


@pytest.mark.parametrize("bad", [dict(global_scale=(0.0, 1.0)), dict(local_scale=(0.5, 0.4)),
                                 dict(global_scale=(0.5, 1.5)), dict(num_local=-1), dict(min_keep=0),
                                 dict(tries=0), dict(local_scale=(float("nan"), 0.4))])
def test_mask_config_rejects_bad_values(bad):
    with pytest.raises(ValueError, match=r"mask\."):
        MaskConfig(**bad)


def test_dino_loss_by_hand():
    loss = DINOLoss(["a"], prototypes=2, student_temp=1.0, center_momentum=0.9)
    teacher = {"a": torch.tensor([[0.0, math.log(3.0)]])}  # softmax at T=1: [1/4, 3/4]
    student = {"a": torch.zeros(1, 1, 2)}  # uniform: -log p = log 2 for both prototypes
    total, per = loss(student, teacher, teacher_temp=1.0)
    assert total.item() == pytest.approx(math.log(2.0))
    # student [0, log 3] too: CE = -(1/4 log 1/4 + 3/4 log 3/4)
    student = {"a": torch.tensor([[[0.0, math.log(3.0)]], [[0.0, 0.0]]])}  # two views: summed
    total, per = loss(student, teacher, teacher_temp=1.0)
    h = -(0.25 * math.log(0.25) + 0.75 * math.log(0.75))
    assert total.item() == pytest.approx(h + math.log(2.0), rel=1e-6)
    # the teacher temperature sharpens: at T -> 0 the target is one-hot on prototype 1
    total, _ = loss({"a": torch.zeros(1, 1, 2)}, teacher, teacher_temp=1e-4)
    assert total.item() == pytest.approx(math.log(2.0))
    # student temperature 0.5 on logits [0, log 3]: softmax of [0, 2 log 3] = [1/10, 9/10]
    loss2 = DINOLoss(["a"], prototypes=2, student_temp=0.5)
    total, _ = loss2({"a": torch.tensor([[[0.0, math.log(3.0)]]])}, teacher, teacher_temp=1.0)
    assert total.item() == pytest.approx(-(0.25 * math.log(0.1) + 0.75 * math.log(0.9)), rel=1e-6)


def test_centering_per_token_set():
    loss = DINOLoss(["a", "b"], prototypes=2, student_temp=1.0, center_momentum=0.9)
    teacher = {"a": torch.tensor([[1.0, 3.0], [1.0, 1.0]]), "b": torch.tensor([[4.0, 0.0], [0.0, 0.0]])}
    loss.update_center(teacher)
    assert torch.allclose(loss.center, torch.tensor([[0.1, 0.2], [0.2, 0.0]]))
    loss.update_center(teacher)
    assert torch.allclose(loss.center, torch.tensor([[0.19, 0.38], [0.38, 0.0]]))
    # the center is subtracted before the teacher's softmax: a center equal to the logits gives uniform targets
    loss.center.copy_(torch.tensor([[0.0, math.log(3.0)], [0.0, 0.0]]))
    probs = loss.teacher_probs({"a": torch.tensor([[0.0, math.log(3.0)]]), "b": torch.zeros(1, 2)}, 1.0)
    assert torch.allclose(probs["a"], torch.tensor([[0.5, 0.5]]))


def test_dino_head_shapes_and_fixed_norm():
    torch.manual_seed(0)
    head = DINOHead(8, hidden=16, bottleneck=4, prototypes=10)
    x = torch.randn(3, 5, 8)
    y = head(x)
    assert y.shape == (3, 5, 10) and y.abs().max() <= 1.0 + 1e-6  # cosine similarities
    with torch.no_grad():
        head.prototypes.mul_(7.0)  # the norm of the prototypes does not matter: only directions
    assert torch.allclose(head(x), y, atol=1e-6)
    assert set(dict(head.named_parameters())) == {"mlp.0.weight", "mlp.0.bias", "mlp.2.weight", "mlp.2.bias",
                                                   "mlp.4.weight", "mlp.4.bias", "prototypes"}


def test_ema_update_by_hand():
    teacher, student = nn.Linear(1, 1), nn.Linear(1, 1)
    with torch.no_grad():
        teacher.weight.fill_(1.0), teacher.bias.fill_(-1.0)
        student.weight.fill_(3.0), student.bias.fill_(1.0)
    ema_update(teacher, student, 0.75)
    assert teacher.weight.item() == 1.5 and teacher.bias.item() == -0.5
    ema_update(teacher, student, 1.0)
    assert teacher.weight.item() == 1.5  # momentum 1: frozen
    ema_update(teacher, student, 0.0)
    assert teacher.weight.item() == 3.0  # momentum 0: a copy


def test_schedules_are_pure_functions_of_the_step():
    assert cosine(0, 100, 1.0, 0.0) == 1.0 and cosine(100, 100, 1.0, 0.0) == 0.0
    assert cosine(50, 100, 1.0, 0.0) == pytest.approx(0.5) and cosine(200, 100, 1.0, 0.0) == 0.0
    lr = [warmup_cosine(s, 110, 10, 1e-4, 1e-5, 1e-6) for s in range(111)]
    assert lr[0] == 1e-5 and lr[5] == pytest.approx(5.5e-5) and lr[10] == pytest.approx(1e-4)
    assert lr[60] == pytest.approx((1e-4 + 1e-6) / 2) and lr[110] == pytest.approx(1e-6)
    assert all(a >= b for a, b in zip(lr[10:], lr[11:], strict=False))
    assert ema_momentum(0, 10, 0.996) == 0.996 and ema_momentum(10, 10, 0.996) == 1.0
    assert ema_momentum(5, 10, 0.996) == pytest.approx(0.998)
    assert teacher_temperature(0, 10) == 0.04 and teacher_temperature(5, 10) == pytest.approx(0.055)
    assert teacher_temperature(10, 10) == 0.07 and teacher_temperature(99, 10) == 0.07
    assert teacher_temperature(0, 0) == 0.07


def test_no_weight_decay_on_1d_parameters():
    model = nn.Sequential(nn.Linear(4, 4), nn.LayerNorm(4))
    model.register_parameter("token", nn.Parameter(torch.zeros(1, 2, 4)))
    groups = param_groups([model, model], weight_decay=0.05)
    decay = {id(p) for p in groups[0]["params"]}
    assert decay == {id(model[0].weight), id(model.token)}
    assert {id(p) for p in groups[1]["params"]} == {id(model[0].bias), id(model[1].weight), id(model[1].bias)}
    opt = torch.optim.AdamW(groups)
    set_hyperparameters(opt, lr=0.5, weight_decay=0.2)
    assert [g["lr"] for g in opt.param_groups] == [0.5, 0.5]
    assert [g["weight_decay"] for g in opt.param_groups] == [0.2, 0.0]
