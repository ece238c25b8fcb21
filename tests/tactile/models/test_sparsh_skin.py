"""Sparsh-skin: tokens and shapes per size, input conditioning, masked views (bounds, the same taxels across time),
iBOT / KoLeo / multi-view DINO on hand-worked numbers, and a strict save/load round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from envs.sensors.xela import NUM_TAXELS, REST, TAXEL_TYPE
from rotation.tactile.models.encoders import ENCODERS, kind_of, load_encoder
from rotation.tactile.models.sparsh_skin import SIZES, SparshSkin, SparshSkinConfig, load_skin, save_skin, skin_inputs
from rotation.tactile.models.sparshx_checkpoint import CheckpointMismatch
from rotation.tactile.models.tokens import TouchEncoder
from rotation.tactile.ssl import DINOLoss, IBOTLoss, ViewMaskConfig, koleo_loss, sample_multi_views, step_rng


def tinier(seed: int = 0) -> SparshSkin:
    torch.manual_seed(seed)
    return SparshSkin(SparshSkinConfig(size="tinier")).eval()


def window(batch: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random raw windows: counts around the rest reading, positions of a hand (m)."""
    g = torch.Generator().manual_seed(seed)
    counts = REST + 500.0 * torch.randn(batch, 10, NUM_TAXELS, 3, generator=g)
    pos = 0.1 * torch.rand(batch, 10, NUM_TAXELS, 3, generator=g)
    return {"skin": torch.cat([counts, pos], dim=-1)}


@pytest.mark.parametrize("size", list(SIZES))
def test_tokens_and_shapes_per_size(size):
    spec = SIZES[size]
    with torch.device("meta"):
        model = SparshSkin(SparshSkinConfig(size=size))
        x = {"skin": torch.empty(3, 10, NUM_TAXELS, 6)}
        keep = {"skin": torch.zeros(3, 50, dtype=torch.int64)}
        tokens, regs = model(x, keep=keep, registers=True, token_mask={"skin": torch.zeros(3, 50, dtype=torch.bool)})
        full = model(x)
    assert isinstance(model, TouchEncoder)
    assert model.token_interface.groups == (("skin", 368),) and model.token_interface.width == spec.embed_dim
    assert len(model.blocks) == spec.depth and model.blocks[0].attn.num_heads == spec.num_heads
    assert tuple(full["skin"].shape) == (3, 368, spec.embed_dim)
    assert tuple(tokens["skin"].shape) == (3, 50, spec.embed_dim) and tuple(regs["skin"].shape) == (3, spec.embed_dim)
    assert model.patch_embed.proj.kernel_size == (10,) and model.patch_embed.proj.in_channels == 6
    assert model.type_embed.shape == (3, spec.embed_dim) and model.taxel_embed.shape == (368, spec.embed_dim)


def test_sizes_grow_and_tinier_runs():
    counts = [SparshSkin(SparshSkinConfig(size=s)).num_parameters() for s in ("tinier", "tiny")]
    assert counts[0] < counts[1]
    model = tinier()
    out = model.encode(window())
    assert out["skin"].shape == (2, 368, 96) and torch.isfinite(out["skin"]).all()
    assert torch.equal(model.taxel_type, torch.as_tensor(TAXEL_TYPE))


def test_preprocess_subtracts_the_baseline_and_zeroes_invalid_counts():
    raw = torch.full((2, 4, 10, NUM_TAXELS, 6), REST)  # a batch of 2 sequences of 4 windows
    raw[..., 3:] = 0.05
    raw[0, 1, 3, 7, 2] = 61_000.0  # above the valid range
    raw[1, 0, 0, 0, 0] = 19_000.0  # below it
    raw[1, 2, 5, 100, 1] = REST + 250.0
    base = torch.full((2, NUM_TAXELS, 3), REST - 10.0)
    x = skin_inputs({"skin": raw, "xela_baseline": base})["skin"]
    assert x.shape == (2, 4, 10, NUM_TAXELS, 6)
    assert x[0, 1, 3, 7, 2] == 0 and x[1, 0, 0, 0, 0] == 0  # faults zeroed, not baseline-subtracted
    assert x[1, 2, 5, 100, 1] == 260.0 and x[0, 0, 0, 0, 0] == 10.0
    assert torch.equal(x[..., 3:], raw[..., 3:])  # positions pass unchanged
    # without a baseline: the nominal rest reading
    assert skin_inputs({"skin": raw[0, 0:1]})["skin"][0, 0, 0, 0] == 0.0
    with pytest.raises(ValueError, match="must be \\(B, \\[S,\\] 10, 368, 6\\)"):
        skin_inputs({"skin": torch.zeros(2, 10, 368, 3)})
    with pytest.raises(ValueError, match="expected 'skin'"):
        skin_inputs({"xela": torch.zeros(2, 10, 368, 3)})


def test_a_dropped_taxel_is_dropped_at_every_frame_and_masked_tokens_hide_their_input():
    model = tinier()
    x = model.preprocess(window(batch=1))
    keep = {"skin": torch.arange(0, 200, dtype=torch.int64)[None]}  # taxels 0..199 kept, 200.. dropped
    base = model(x, keep=keep)["skin"]
    for frame in (0, 5, 9):  # any frame of a dropped taxel: no influence
        y = {"skin": x["skin"].clone()}
        y["skin"][0, frame, 300] += 1e4
        assert torch.equal(model(y, keep=keep)["skin"], base)
    y = {"skin": x["skin"].clone()}
    y["skin"][0, 9, 50] += 1e4  # one frame of a kept taxel: the view changes
    assert not torch.allclose(model(y, keep=keep)["skin"], base)
    # iBOT: a masked token's input is replaced by the mask token (its own content no longer matters)
    mask = {"skin": torch.zeros(1, 200, dtype=torch.bool)}
    mask["skin"][0, 40:60] = True
    masked = model(x, keep=keep, token_mask=mask)["skin"]
    assert not torch.allclose(masked, base)
    y = {"skin": x["skin"].clone()}
    y["skin"][0, :, 45] += 1e4  # taxel 45 sits at view position 45, under the mask
    assert torch.equal(model(y, keep=keep, token_mask=mask)["skin"], masked)


def test_bad_inputs_are_clear_errors():
    model = tinier()
    with pytest.raises(ValueError, match="expected inputs"):
        model({"img": torch.zeros(1)})
    with pytest.raises(ValueError, match=r"must be a float tensor \(B, 10, 368, 6\)"):
        model({"skin": torch.zeros(1, 10, 368, 3)})
    bad = {"skin": torch.zeros(1, 10, 368, 6)}
    bad["skin"][0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        model(bad)
    ok = {"skin": torch.zeros(1, 10, 368, 6)}
    with pytest.raises(ValueError, match=r"indices must lie in \[0, 368\)"):
        model(ok, keep={"skin": torch.tensor([[368]])})
    with pytest.raises(ValueError, match="token_mask"):
        model(ok, keep={"skin": torch.tensor([[1, 2]])}, token_mask={"skin": torch.zeros(1, 3, dtype=torch.bool)})


# ------------------------------------------------------------------------------------------------- masks
def test_view_masks_respect_their_bounds():
    cfg = ViewMaskConfig()
    n, batch = NUM_TAXELS, 16
    masked_samples = total = 0
    for step in range(30):
        views = sample_multi_views({"skin": (n,)}, batch, cfg, step_rng(0, step))
        assert len(views.globals) == 2 and len(views.locals) == 8 and len(views.masks) == 2
        kg = views.globals[0]["skin"].shape[1]
        kl = views.locals[0]["skin"].shape[1]
        assert round(0.4 * n) <= kg <= n and round(0.1 * n) <= kl <= round(0.4 * n)  # 40-100 %, 10-40 %
        for v in views.globals + views.locals:
            idx = v["skin"].numpy()
            assert idx.dtype == np.int64 and idx.shape[0] == batch and idx.min() >= 0 and idx.max() < n
            assert (np.diff(idx, axis=1) == 1).all()  # contiguous blocks over the taxel order
        assert all(v["skin"].shape[1] == kg for v in views.globals)
        assert all(v["skin"].shape[1] == kl for v in views.locals)
        for m in views.masks:
            m = m["skin"].numpy()
            assert m.shape == (batch, kg) and m.dtype == bool
            for row in m:
                total += 1
                if not row.any():
                    continue
                masked_samples += 1
                where = np.flatnonzero(row)
                assert (np.diff(where) == 1).all()  # one contiguous run
                assert max(1, round(0.1 * kg)) - 1 <= len(where) <= round(0.5 * kg) + 1  # 10-50 % of the view
    assert 0.35 < masked_samples / total < 0.65  # iBOT on about half of the samples (DINOv2)
    # a pure function of the generator
    a = sample_multi_views({"skin": (n,)}, 4, cfg, step_rng(7, 3))
    b = sample_multi_views({"skin": (n,)}, 4, cfg, step_rng(7, 3))
    assert all(torch.equal(x["skin"], y["skin"]) for x, y in zip(a.globals + a.masks, b.globals + b.masks,
                                                                  strict=True))
    with pytest.raises(ValueError, match="skin.num_global"):
        ViewMaskConfig(num_global=0)
    with pytest.raises(ValueError, match="skin.mask_ratio"):
        ViewMaskConfig(mask_ratio=(0.5, 0.1))


# ------------------------------------------------------------------------------------------------ losses
def test_multi_view_dino_skips_same_view_pairs():
    loss = DINOLoss(["skin"], prototypes=2, student_temp=0.1)
    teacher = {"skin": torch.tensor([[[0.0, 0.0]], [[math.log(3.0), 0.0]]])}  # (T=2, B=1, K=2) -> [.5 .5], [.75 .25]
    student = {"skin": 0.1 * torch.tensor([[[0.0, 0.0]], [[math.log(3.0), 0.0]], [[0.0, 0.0]]])}  # (V=3, B=1, K=2)
    total, per = loss.views_loss(student, teacher, teacher_temp=1.0)
    # pairs (t, v): (0, 1) -(.5 ln .75 + .5 ln .25); (0, 2), (1, 0), (1, 2): ln 2 each; same-view pairs skipped
    want = (-(0.5 * math.log(0.75) + 0.5 * math.log(0.25)) + 3 * math.log(2.0)) / 4
    assert math.isclose(float(total), want, rel_tol=1e-6) and math.isclose(float(per["skin"]), want, rel_tol=1e-6)
    loss.update_center({"skin": torch.tensor([[[1.0, 0.0]], [[3.0, 2.0]]])})  # views x batch: mean [2, 1]
    assert torch.allclose(loss.center, torch.tensor([[0.2, 0.1]]))


def test_ibot_loss_on_hand_worked_numbers():
    loss = IBOTLoss(["skin"], prototypes=2, student_temp=0.1, center_momentum=0.9)
    teacher = {"skin": torch.tensor([[0.0, 0.0], [math.log(3.0), 0.0]])}  # (M=2, K): [.5 .5], [.75 .25]
    student = {"skin": (0.1 * torch.tensor([[math.log(3.0), 0.0], [0.0, 0.0]])).requires_grad_()}
    total, per = loss(student, teacher, teacher_temp=1.0)
    want = (-(0.5 * math.log(0.75) + 0.5 * math.log(0.25)) + math.log(2.0)) / 2  # mean over the masked tokens
    assert math.isclose(float(total.detach()), want, rel_tol=1e-6)
    total.backward()
    assert student["skin"].grad is not None
    # no masked token: 0, still differentiable; the center keeps its value
    empty = {"skin": torch.zeros(0, 2, requires_grad=True)}
    zero, _ = loss(empty, {"skin": torch.zeros(0, 2)}, teacher_temp=1.0)
    zero.backward()
    assert float(zero.detach()) == 0.0
    loss.update_center({"skin": torch.zeros(0, 2)})
    assert torch.equal(loss.center, torch.zeros(1, 2))
    loss.update_center({"skin": torch.tensor([[1.0, 0.0], [3.0, 2.0]])})
    assert torch.allclose(loss.center, torch.tensor([[0.2, 0.1]]))


def test_koleo_on_hand_worked_numbers():
    def on_circle(degrees):
        a = torch.tensor(degrees, dtype=torch.float64) * math.pi / 180
        return torch.stack([torch.cos(a), torch.sin(a)], dim=1)

    # 0, 90, 180 degrees: every nearest neighbour at sqrt(2)
    assert math.isclose(float(koleo_loss(on_circle([0.0, 90.0, 180.0]))), -math.log(math.sqrt(2)), rel_tol=1e-6)
    # 0, 60, 180: neighbours at 1, 1, sqrt(3) -> -(0 + 0 + ln sqrt 3) / 3; rows are normalized first
    x = on_circle([0.0, 60.0, 180.0]) * torch.tensor([[5.0], [0.5], [2.0]], dtype=torch.float64)
    assert math.isclose(float(koleo_loss(x)), -math.log(3.0) / 6, rel_tol=1e-6)
    # identical rows stay finite; a single row adds nothing
    same = torch.ones(3, 4, requires_grad=True)
    value = koleo_loss(same)
    value.backward()
    assert math.isfinite(float(value.detach())) and torch.isfinite(same.grad).all()
    assert float(koleo_loss(torch.ones(1, 4))) == 0.0


# ------------------------------------------------------------------------------------------------- files
def test_save_load_round_trip_is_strict(tmp_path):
    model = tinier(seed=3)
    with torch.no_grad():
        model.skin_avg.copy_(torch.arange(6.0))
        model.skin_div.copy_(torch.arange(1.0, 7.0))
    path = save_skin(model, tmp_path / "enc" / "encoder.safetensors")
    loaded = load_skin(path)
    assert loaded.cfg == model.cfg and kind_of(loaded) == "skin"
    assert set(loaded.state_dict()) == set(model.state_dict())
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in model.state_dict().items())
    x = window(batch=1)
    assert torch.equal(loaded.eval().encode(x)["skin"], model.encode(x)["skin"])
    again = load_encoder(tmp_path / "enc")  # a run directory: dispatched on the file's format
    assert isinstance(again, SparshSkin) and load_encoder(path, drop_path=0.2).cfg.drop_path == 0.2
    assert ENCODERS["skin"].restrict(again, ("skin",)) is again
    # a file that lacks a tensor, or is not a Sparsh-skin file, is refused with what differs
    from safetensors.torch import load_file, save_file

    state = load_file(str(path))
    del state["mask_token"]
    save_file(state, str(tmp_path / "cut.safetensors"), metadata={"format": "sparsh_skin",
                                                                  "config": '{"size": "tinier", "drop_path": 0.0}'})
    with pytest.raises(CheckpointMismatch, match="1 missing: mask_token"):
        load_skin(tmp_path / "cut.safetensors")
    save_file(state, str(tmp_path / "other.safetensors"), metadata={"format": "something"})
    with pytest.raises(ValueError, match="not a Sparsh-skin encoder"):
        load_skin(tmp_path / "other.safetensors")


def test_the_envs_skin_observation_is_an_encoder_input():
    from envs.config import EnvConfig
    from envs.core import RotateCupVec

    env = RotateCupVec(EnvConfig(hand="xela", skin=True), num_envs=2, seed=0)
    try:
        env.reset()
        obs, *_ = env.step(np.zeros((2, 16), np.float32))
    finally:
        env.close()
    with torch.no_grad():
        tokens = tinier().encode({"skin": obs["skin"]})  # raw counts + positions, REST as the baseline
    assert tokens["skin"].shape == (2, 368, 96) and torch.isfinite(tokens["skin"]).all()
