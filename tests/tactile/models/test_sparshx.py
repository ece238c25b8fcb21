"""Sparsh-X: released layout (names, shapes, counts), token counts, fusion semantics, masking, inputs, normalization."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from envs.sensors.digit360_image import pack_image
from envs.sensors.tactile_obs import WINDOW_SHAPES
from rotation.data.audio import fbank
from rotation.data.dataset import TouchWindows
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter
from rotation.tactile.models.posembed import frequency_bands, grid_coordinates
from rotation.tactile.models.sparshx import SIZES, SparshX, SparshXConfig
from rotation.tactile.models.sparshx_inputs import INPUT_SHAPES, MODALITIES, WINDOW_KEYS, normalize
from rotation.tactile.models.tokens import TouchEncoder

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
COUNTS = {"img": 196, "mic": 224, "imu": 56, "pressure": 56}


def reference_keys() -> list[tuple[str, str]]:
    lines = (FIXTURES / "sparshx_base_keys.txt").read_text().splitlines()
    return [tuple(line.split()) for line in lines if line and not line.startswith("#")]


def meta_model(**kw) -> SparshX:
    with torch.device("meta"):
        return SparshX(SparshXConfig(**kw))


def key_shapes(model: SparshX) -> list[tuple[str, str]]:
    return [(k, "x".join(map(str, v.shape)) or "scalar") for k, v in model.state_dict().items()]


def tinier(seed: int = 0, **kw) -> SparshX:
    torch.manual_seed(seed)
    return SparshX(SparshXConfig(size="tinier", **kw)).eval()


def shallow(**kw) -> SparshX:
    """A tinier with 1 unimodal + 2 fusion layers: every code path at 3/8 of the cost (with a single fusion layer
    the averaged bottleneck would never reach a modality: it feeds the next fusion layer only)."""
    return tinier(**{"unimodal_layers": 1, "fusion_layers": 2, **kw})


def inputs(batch: int = 2, seed: int = 0, modalities=MODALITIES) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = {m: torch.randn((batch, *INPUT_SHAPES[m]), generator=g) for m in modalities}
    if "img" in x:
        x["img"] = torch.rand((batch, *INPUT_SHAPES["img"]), generator=g)
    if "pressure" in x:
        x["pressure"] = 1000.0 + x["pressure"]
    return x


# ------------------------------------------------------------------------------------------ released layout
def test_base_state_dict_is_the_released_key_list_in_file_order():
    model = meta_model(size="base")
    assert key_shapes(model) == reference_keys()  # 708 names, shapes, order
    assert model.num_parameters() == 341_695_488


def test_tiny_is_the_base_list_with_d_192():
    scale = {768: 192, 2304: 576, 3072: 768, 192: 48, 384: 96}  # D, 3D, 4D, D/4, D/2

    def to_tiny(shape: str) -> str:
        return shape if shape == "scalar" else "x".join(str(scale.get(int(s), int(s))) for s in shape.split("x"))

    model = meta_model(size="tiny")
    assert key_shapes(model) == [(k, to_tiny(s)) for k, s in reference_keys()]
    assert model.num_parameters() == 21_722_880


@pytest.mark.parametrize("size", list(SIZES))
@pytest.mark.parametrize("mods", [MODALITIES, ("img",), ("mic", "imu"), ("pressure", "img")])
def test_token_counts_and_shapes_per_size_and_subset(size, mods):
    model = meta_model(size=size, modalities=mods)
    d = SIZES[size].embed_dim
    canonical = tuple(m for m in MODALITIES if m in mods)
    assert model.modalities == canonical
    assert model.token_interface.groups == tuple((m, COUNTS[m]) for m in canonical)
    assert model.token_interface.width == d
    assert model.register_tokens.shape == (len(canonical), 1, d)
    with torch.device("meta"):
        x = {m: torch.empty((3, *INPUT_SHAPES[m])) for m in canonical}
    tokens, regs = model(x, registers=True)  # shapes propagate on the meta device
    assert {m: tuple(t.shape) for m, t in tokens.items()} == {m: (3, COUNTS[m], d) for m in canonical}
    assert {m: tuple(r.shape) for m, r in regs.items()} == {m: (3, d) for m in canonical}


def test_vanilla_fusion_names_and_single_modality():
    model = meta_model(size="tinier", fusion="vanilla")
    names = set(model.state_dict())
    assert "bottleneck" not in names
    assert "fusion_blocks.1.attn.qkv.weight" in names and "fusion_blocks.0.img.norm1.weight" not in names
    assert "blocks.5.pressure.ls2.gamma" in names
    no_fusion = meta_model(size="tinier", fusion_layers=0)
    assert "bottleneck" not in no_fusion.state_dict() and len(no_fusion.fusion_blocks) == 0


def test_config_validation_and_canonical_order():
    assert SparshXConfig(modalities=("pressure", "img")).modalities == ("img", "pressure")
    assert SparshXConfig(modalities="mic, img").modalities == ("img", "mic")
    for kw, field in [({"size": "huge"}, "size"), ({"modalities": ()}, "modalities"),
                      ({"modalities": ("img", "touch")}, "modalities"), ({"modalities": ("img", "img")}, "modalities"),
                      ({"fusion": "late"}, "fusion"), ({"drop_path": 1.0}, "drop_path"),
                      ({"fusion_layers": -1}, "fusion_layers"),
                      ({"unimodal_layers": 0, "fusion_layers": 0}, "must be")]:
        with pytest.raises(ValueError, match=field):
            SparshXConfig(**kw)


def test_input_contract_matches_the_env():
    assert {m: INPUT_SHAPES[m] for m in MODALITIES} == {m: WINDOW_SHAPES[WINDOW_KEYS[m]] for m in MODALITIES}


# ------------------------------------------------------------------------------------------------ forward
def test_forward_shapes_registers_and_protocol():
    model = shallow()
    assert isinstance(model, TouchEncoder)
    with torch.no_grad():
        tokens, regs = model(inputs(), registers=True)
    model.token_interface.check(tokens)
    assert all(torch.isfinite(t).all() for t in tokens.values())
    assert {m: tuple(r.shape) for m, r in regs.items()} == {m: (2, 96) for m in MODALITIES}
    sub = shallow(modalities=("img", "imu"))
    with torch.no_grad():
        out = sub(inputs(modalities=("img", "imu")))
    assert {m: tuple(t.shape) for m, t in out.items()} == {"img": (2, 196, 96), "imu": (2, 56, 96)}


def test_keep_gathers_patch_tokens():
    model = shallow()
    x = inputs()
    perm = torch.stack([torch.randperm(196), torch.randperm(196)])  # (B, 196)
    with torch.no_grad():
        full = model(x)
        # attention and the bottleneck mean are permutation-equivariant: keeping every token in another order
        # permutes the output rows exactly as the gathered input rows
        permuted = model(x, keep={"img": perm})
        assert torch.allclose(permuted["img"], torch.gather(full["img"], 1, perm[:, :, None].expand(-1, -1, 96)),
                              atol=1e-5)
        assert torch.allclose(permuted["mic"], full["mic"], atol=1e-5)
        keep = {"mic": torch.tensor([[0, 5, 7], [223, 1, 2]]), "imu": torch.zeros(2, 4, dtype=torch.long)}
        part = model(x, keep=keep)
    assert part["mic"].shape == (2, 3, 96) and part["imu"].shape == (2, 4, 96) and part["img"].shape == (2, 196, 96)
    assert not torch.equal(part["pressure"], full["pressure"])  # fewer mic/imu tokens reach it via the bottleneck


def _change_of_img(model: SparshX) -> float:
    """How much the image tokens move when only the audio input changes."""
    x = inputs()
    y = dict(x, mic=x["mic"] + torch.randn_like(x["mic"]))
    with torch.no_grad():
        return (model(x)["img"] - model(y)["img"]).abs().max().item()


def test_bottleneck_is_the_only_path_between_modalities(monkeypatch):
    assert _change_of_img(shallow(fusion_layers=0)) == 0.0  # no fusion layers: independent streams
    # bottleneck fusion: audio reaches the image tokens (weakly at initialization: 4 of 201 keys are bottleneck)
    assert _change_of_img(shallow()) > 1e-6
    assert _change_of_img(shallow(fusion="vanilla")) > 1e-4
    # cut the exchange (each modality keeps its own bottleneck tokens): audio no longer reaches the image at all
    monkeypatch.setattr(SparshX, "_fuse_bottleneck", staticmethod(lambda outputs: outputs[0]))
    assert _change_of_img(shallow()) == 0.0


def test_one_bottleneck_fusion_layer_fuses_nothing():
    """In the first bottleneck layer every modality attends to the learned initial bottleneck, the same for every
    input; the mixed mean of its outputs feeds only a next fusion layer. So 3 + 1 layers (the shipped
    sparshx-tinier-sim's) pass nothing between modalities, and the config says so."""
    one = shallow(fusion_layers=1)
    assert _change_of_img(one) == 0.0 and not one.cfg.fuses
    assert shallow().cfg.fuses and _change_of_img(shallow()) > 1e-6  # two layers: the mixed bottleneck is read
    assert shallow(fusion="vanilla", fusion_layers=1).cfg.fuses
    assert not shallow(fusion_layers=2, modalities=("img",)).cfg.fuses  # one modality: nothing to fuse


def test_training_mode_drop_path_and_gradients():
    model = shallow(drop_path=0.2).train()
    out, regs = model(inputs(), registers=True)
    sum(r.square().sum() for r in regs.values()).backward()
    assert model.bottleneck.grad is not None and model.patch_embed["img"].proj.weight.grad.abs().sum() > 0
    assert model.blocks[0]["img"].drop_path.p == 0.0 and model.fusion_blocks[-1]["img"].drop_path.p == 0.2
    assert model.fusion_blocks[0]["img"].drop_path.p == pytest.approx(0.1)  # linear in depth


def test_bfloat16_autocast_on_the_cpu_keeps_every_modality_within_rounding():
    """The image tokenizer's convolution runs in float32 on the CPU (some CPUs' bfloat16 kernel for it is wrong)."""
    model, x = shallow(), inputs()
    with torch.no_grad():
        full = model(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            half = model(x)
    for m in MODALITIES:
        assert (half[m].float() - full[m]).abs().max() < 0.2, m


def test_half_precision_keeps_float32_buffers():
    model, x = shallow(), inputs()
    with torch.no_grad():
        full = model(x)
        half = model.to(torch.bfloat16)(x)
    assert model.register_tokens.dtype == torch.bfloat16 and model.mic_avg.dtype == torch.float32
    assert model.pos_embeds["pressure"].frequency_bands.dtype == torch.float32  # positions survive the cast
    for m in MODALITIES:
        assert half[m].dtype == torch.bfloat16 and (half[m].float() - full[m]).abs().max() < 0.2, m


# ------------------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("edit, match", [
    (lambda x: x.pop("mic"), "exactly the modalities"),
    (lambda x: x.update(image=x["img"]), "exactly the modalities"),
    (lambda x: x.update(img=x["img"][:, :3]), r"inputs\['img'\] must be a float tensor \(B, 6, 224, 224\)"),
    (lambda x: x.update(pressure=x["pressure"][:, :, 0]), r"\(B, 224, 1\)"),
    (lambda x: x.update(imu=x["imu"].long()), "float tensor"),
    (lambda x: x.update(imu=x["imu"][:1]), "batch"),
    (lambda x: x["mic"].__setitem__((0, 3, 4), float("nan")), r"non-finite .*\['mic'\]"),
    (lambda x: x["img"].__setitem__((1, 0, 0, 0), float("inf")), r"non-finite .*\['img'\]"),
])
def test_bad_inputs_are_clear_errors(edit, match):
    model = shallow(fusion_layers=0, unimodal_layers=1)
    x = inputs()
    edit(x)
    with pytest.raises(ValueError, match=match):
        model(x)


@pytest.mark.parametrize("keep, match", [
    ({"skin": torch.zeros(2, 3, dtype=torch.long)}, "not a modality"),
    ({"img": torch.zeros(2, 3, dtype=torch.int32)}, "int64"),
    ({"img": torch.zeros(3, 3, dtype=torch.long)}, "B=2"),
    ({"img": torch.full((2, 3), 196)}, r"\[0, 196\)"),
])
def test_bad_keep_indices(keep, match):
    with pytest.raises(ValueError, match=match):
        shallow(fusion_layers=0, unimodal_layers=1)(inputs(), keep=keep)


# ---------------------------------------------------------------------------------- raw windows and normalization
def test_preprocess_from_raw_windows_equals_the_contract_path():
    model = shallow(fusion_layers=0, unimodal_layers=1)
    g = np.random.default_rng(0)
    frames = g.integers(0, 256, (2, 2, 224, 224, 3), dtype=np.uint8)
    wave = g.integers(-3000, 3000, (2, 2, 27000)).astype(np.float32)
    imu, pressure = g.normal(size=(2, 224, 3)).astype(np.float32), 1000 + g.normal(size=(2, 224)).astype(np.float32)
    raw = {"image": frames, "audio": wave, "imu": imu, "pressure": pressure, "finger": np.array([0, 3])}
    got = model.preprocess(raw)
    want = {"img": torch.from_numpy(np.stack([pack_image(f) for f in frames])), "mic": fbank(torch.from_numpy(wave)),
            "imu": torch.from_numpy(imu), "pressure": torch.from_numpy(pressure)[:, :, None]}
    for m in MODALITIES:
        assert got[m].shape == (2, *INPUT_SHAPES[m]) and torch.allclose(got[m], want[m], atol=1e-6), m
    with pytest.raises(ValueError, match="given twice"):
        model.preprocess({**raw, "audio_wave": wave})
    with pytest.raises(ValueError, match="no 'imu' input"):
        model.preprocess({k: v for k, v in raw.items() if k != "imu"})
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(model.encode(raw).values(), model(got).values(), strict=True))


def test_normalization_buffers_and_semantics():
    model = shallow(fusion_layers=0, unimodal_layers=1)
    torch.testing.assert_close(model.img_avg.flatten(), torch.tensor([0.0956, 0.2659, 0.3246] * 2))
    torch.testing.assert_close(model.img_div.flatten(), torch.tensor([0.0818, 0.1726, 0.1851] * 2))
    assert model.imu_div.item() == 4.0 and model.imu_div.dim() == 0 and model.mic_range.tolist() == [-32.0, 32.0]
    x = inputs()
    # pressure: high-passed per window, so the absolute level (weather, altitude) does not matter
    shifted = normalize(model, "pressure", x["pressure"] + 37.0)
    torch.testing.assert_close(shifted, normalize(model, "pressure", x["pressure"]), atol=2e-4, rtol=0)  # float32
    assert normalize(model, "pressure", x["pressure"] + 1e4 * torch.arange(224.0)[None, :, None]).abs().max() == 16
    torch.testing.assert_close(normalize(model, "imu", x["imu"]), x["imu"] / 4)
    # the image normalization folded into the tokenizer equals normalize-then-convolve
    pe = model.patch_embed["img"]
    folded = pe(x["img"], model.img_avg, model.img_div)
    torch.testing.assert_close(folded, pe(normalize(model, "img", x["img"])), atol=1e-4, rtol=1e-4)


def test_fit_normalization_from_windows():
    g = torch.Generator().manual_seed(0)
    windows = []
    for i in range(40):
        img = torch.rand(6, 224, 224, generator=g) * 0.1 + torch.tensor([0.1, 0.1, 0.5, 0.5, 0.9, 0.9])[:, None, None]
        windows.append({"image": img, "audio": 3.0 + 2.0 * torch.randn(224, 256, generator=g),
                        "imu": torch.randn(224, 3, generator=g),
                        "pressure": 990.0 + i + 0.5 * torch.randn(224, 1, generator=g)})
    model = shallow(fusion_layers=0, unimodal_layers=1)
    stats = model.fit_normalization(windows, max_windows=32, batch_size=8)
    assert set(stats) == {"img_avg", "img_div", "mic_avg", "mic_div", "pressure_avg", "pressure_div"}
    torch.testing.assert_close(model.img_avg.flatten(), torch.tensor([0.15, 0.55, 0.95] * 2), atol=2e-3, rtol=0)
    torch.testing.assert_close(model.img_div.flatten(), torch.full((6,), 0.1 / 12**0.5), atol=2e-3, rtol=0)
    assert model.mic_avg.shape == (256,) and abs(model.mic_avg.mean().item() - 3.0) < 0.05
    assert abs(model.mic_div.mean().item() - 4.0) < 0.05  # 2 std
    assert abs(model.pressure_avg.item()) < 0.05 and abs(model.pressure_div.item() - 1.0) < 0.05  # high-passed
    assert model.imu_div.item() == 4.0  # a constant of the contract
    with pytest.raises(ValueError, match="not a normalization buffer"):
        model.set_normalization({"blocks.0.img.ls1.gamma": torch.ones(96)})


def test_positional_embedding_buffers():
    assert torch.allclose(frequency_bands(768, 2)[0, [0, 1, -1]], torch.tensor([1.0, 10000 ** (-1 / 192),
                                                                                 10000 ** (-191 / 192)]))
    coords = grid_coordinates((14, 16))
    assert coords[15].tolist() == [1.0, 1.0] and coords[223].tolist() == [13.0, 15.0]  # (n % H, n // H)
    model = shallow(fusion_layers=0, unimodal_layers=1)
    assert [model.pos_embeds[m].offset.item() for m in MODALITIES] == [0, 196, 420, 476]
    emb = model.pos_embeds["imu"]()
    assert emb.shape == (56, 96) and torch.allclose(emb[0, :48], torch.sin(torch.tensor(420.0) *
                                                                           frequency_bands(96, 1)[0]))
    model.load_state_dict({**model.state_dict(), "pos_embeds.imu.offset": torch.tensor(0.0)})
    assert torch.allclose(model.pos_embeds["imu"]()[0], torch.cat([torch.zeros(48), torch.ones(48)]))  # reloaded


def recorded_session(path, duration=1.4):
    """One recorded fingertip: gray frames (value = frame index), silent audio, pressure = 1000 + t hPa."""
    streams = [StreamSetup("digit360/index/image", shape=(224, 224, 3)), StreamSetup("digit360/index/audio"),
               StreamSetup("digit360/index/imu"), StreamSetup("digit360/index/pressure")]
    with SessionWriter(path, SessionMeta(source="real", object="mug", control_hz=20.0), streams) as w:
        t_img = np.arange(int(duration * 30)) / 30.0
        w.append("digit360/index/image", np.broadcast_to((np.arange(len(t_img)) * 4).astype(np.uint8)[:, None, None,
                                                                                                         None],
                                                          (len(t_img), 224, 224, 3)), t_img)
        ta = np.arange(int(duration * 48000)) / 48000.0
        w.append("digit360/index/audio", np.zeros((len(ta), 2), np.int16), ta)
        ti = np.arange(int(duration * 400)) / 400.0
        w.append("digit360/index/imu", np.zeros((len(ti), 3), np.float32), ti)
        tp = np.arange(int(duration * 200)) / 200.0
        w.append("digit360/index/pressure", (1000.0 + tp)[:, None].astype(np.float32), tp)
    return path


def test_fit_normalization_from_sessions(tmp_path):
    windows = TouchWindows([recorded_session(tmp_path / "s.h5")], fingers=("index",), audio_features=False)
    assert len(windows) >= 4
    model = shallow(modalities=("img", "mic", "pressure"))
    stats = model.fit_normalization(windows, batch_size=4)
    # pressure rises 1 hPa/s: each window high-passed is a centered ramp of 224 samples 1/200 hPa apart
    assert abs(stats["pressure_avg"].item()) < 1e-3
    assert stats["pressure_div"].item() == pytest.approx(2 * ((224**2 - 1) / 12) ** 0.5 / 200, rel=1e-3)
    assert torch.equal(model.pressure_div, stats["pressure_div"])
    # silent audio: every bin sits at the log floor, its spread is floored instead of zero
    assert torch.allclose(model.mic_avg, torch.full((256,), float(np.log(np.finfo(np.float32).eps))))
    assert (model.mic_div > 0).all() and model.img_avg.shape == (6, 1, 1)
