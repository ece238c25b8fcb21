"""Sparsh-X inputs: the per-modality contract, raw windows -> model inputs, in-model normalization, tokenizers.

Model inputs, one fingertip per sample (docs/reference/sparsh.md "Sparsh-X input contract"), keyed by the released
model's modality names::

    img       (B, 6, 224, 224)  pixel / 255, channels [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)]
    mic       (B, 224, 256)     Kaldi log-mel frames x (128 bins x 2 microphones), rotation.data.audio.fbank
    imu       (B, 224, 3)       accelerometer, g (400 Hz)
    pressure  (B, 224, 1)       absolute pressure, hPa (200 Hz)

:func:`window_inputs` builds them from what the dataset (rotation.data.dataset.TouchWindows), the env's `tactile`
observation or the simulated sensor's raw render give (names ``image``/``audio``/``imu``/``pressure``; raw audio
waveforms go through the filterbank on the target device). Normalization lives in the model as buffers with the
released names (:func:`register_normalization`), so a checkpoint carries its own statistics;
:func:`fit_statistics` recomputes them from a set of sessions.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, Subset

from rotation.data.audio import SPARSH_FBANK, fbank
from rotation.interrupt import ignore_stop_signals
from rotation.tactile.models.blocks import LN_EPS

MODALITIES = ("img", "mic", "imu", "pressure")
"""The released model's modality names, in the canonical order (state-dict and register-token order)."""
WINDOW_KEYS = {"img": "image", "mic": "audio", "imu": "imu", "pressure": "pressure"}
"""Modality -> key of the same window in dataset batches and the env's `tactile` observation."""
INPUT_SHAPES: dict[str, tuple[int, ...]] = {
    "img": (6, 224, 224),
    "mic": (224, 2 * SPARSH_FBANK.num_mel_bins),
    "imu": (224, 3),
    "pressure": (224, 1),
}
"""Per-sample model input shapes (the contract; envs.sensors.tactile_obs.WINDOW_SHAPES is the same, tested)."""
PATCH_2D, PATCH_1D = 16, 4
"""Patch sizes: 16 x 16 on the image and audio grids, 4 samples on IMU and pressure (docs/reference/sparsh.md)."""
TOKEN_GRIDS: dict[str, tuple[int, ...]] = {
    "img": (14, 14), "mic": (14, 16), "imu": (56,), "pressure": (56,),
}
"""Patch-token grid of each modality: 196, 224, 56, 56 tokens."""
IN_CHANNELS = {"img": 6, "mic": 1, "imu": 3, "pressure": 1}
"""Tokenizer input channels (audio features get one channel axis)."""

IMAGE_MEAN = (0.0956, 0.2659, 0.3246)
"""Released image mean per color of pixel / 255 (docs/reference/sparsh.md)."""
IMAGE_STD = (0.0818, 0.1726, 0.1851)
"""Released image std per color (docs/reference/sparsh.md); ``img_div`` = std."""
MIC_MEAN, MIC_DIV = 0.0, 1.0
"""Default audio statistics (per bin): the identity. The released values are not public; a checkpoint brings its
own and :func:`fit_statistics` computes them from sessions (mean, 2 std per bin)."""
MIC_RANGE = (-32.0, 32.0)
"""Clamp of the normalized audio features (docs/reference/sparsh.md)."""
IMU_DIV, IMU_AVG = 4.0, 0.0
"""IMU in g is divided by 4 inside the model and not centered (``imu_avg`` is stored but unused by the forward)."""
PRESSURE_MEAN, PRESSURE_DIV = 0.0, 2.0
"""Default statistics of the high-passed pressure (hPa): zero mean, div = 2 std for a 1 hPa std (about 0.25 N of
normal force on the simulated sensor, envs.sensors.digit360_model.Digit360Model.pressure_per_newton); chosen."""
PRESSURE_RANGE = (-16.0, 16.0)
"""Clamp of the normalized pressure (docs/reference/sparsh.md)."""
_STD_FLOOR = 1e-6


def pressure_highpass(x: Tensor) -> Tensor:
    """Per-window high-pass of absolute pressure (B, L, 1): the window's mean removed.

    The reference only says "high-pass filtered per window"; removing the window's DC component is the simplest
    filter that drops the absolute level (weather, altitude, the sensor's offset: about 1000 hPa) and keeps every
    change within the window.
    """
    return x - x.mean(dim=1, keepdim=True)


# ----------------------------------------------------------------------------------------- normalization buffers
def default_statistics(modalities: Sequence[str]) -> dict[str, Tensor]:
    """Buffer name -> default value for the given modalities, in the released checkpoint's order."""
    out: dict[str, Tensor] = {}
    if "img" in modalities:
        out["img_avg"] = torch.tensor(IMAGE_MEAN * 2).reshape(6, 1, 1)  # [c0, c1, c2, c0, c1, c2]
        out["img_div"] = torch.tensor(IMAGE_STD * 2).reshape(6, 1, 1)
    if "mic" in modalities:
        out["mic_avg"] = torch.full((INPUT_SHAPES["mic"][1],), MIC_MEAN)
        out["mic_div"] = torch.full((INPUT_SHAPES["mic"][1],), MIC_DIV)
        out["mic_range"] = torch.tensor(MIC_RANGE)
    if "imu" in modalities:
        out["imu_div"] = torch.tensor(IMU_DIV)
        out["imu_avg"] = torch.tensor(IMU_AVG)
    if "pressure" in modalities:
        out["pressure_avg"] = torch.tensor(PRESSURE_MEAN)
        out["pressure_div"] = torch.tensor(PRESSURE_DIV)
        out["pressure_range"] = torch.tensor(PRESSURE_RANGE)
    return out


def register_normalization(module: nn.Module, modalities: Sequence[str]) -> None:
    """Register the normalization buffers of ``modalities`` on ``module`` (released names, shapes and order)."""
    for name, value in default_statistics(modalities).items():
        module.register_buffer(name, value)


def normalize(module: nn.Module, m: str, x: Tensor) -> Tensor:
    """Model input of modality ``m`` -> what its tokenizer sees, with ``module``'s buffers (released semantics).

    img: (x - avg) / div, no clamp; mic: (x - avg) / div clamped to mic_range, + a channel axis (B, 1, 224, 256);
    imu: x / imu_div (no centering); pressure: high-pass, (x - avg) / div clamped to pressure_range.
    """
    if m == "img":
        return (x - module.img_avg.to(x)) / module.img_div.to(x)  # (B, 6, 224, 224)
    if m == "mic":
        lo, hi = module.mic_range.to(x)  # 0-dim tensor bounds: no device sync
        x = ((x - module.mic_avg.to(x)) / module.mic_div.to(x)).clamp(lo, hi)
        return x[:, None]  # (B, 1, 224, 256)
    if m == "imu":
        return x / module.imu_div.to(x)  # (B, 224, 3)
    if m == "pressure":
        lo, hi = module.pressure_range.to(x)
        x = (pressure_highpass(x) - module.pressure_avg.to(x)) / module.pressure_div.to(x)
        return x.clamp(lo, hi)  # (B, 224, 1)
    raise ValueError(f"unknown modality {m!r}; modalities: {', '.join(MODALITIES)}")


# ------------------------------------------------------------------------------------------------- tokenizers
class PatchEmbed2d(nn.Module):
    """(B, C, H, W) -> (B, (H/16)(W/16), D): 16 x 16 Conv2d, tokens flattened row-major over the patch grid."""

    def __init__(self, in_channels: int, dim: int, patch: int = PATCH_2D):
        super().__init__()
        self.proj = nn.Conv2d(in_channels, dim, kernel_size=patch, stride=patch)

    def forward(self, x: Tensor, avg: Tensor | None = None, div: Tensor | None = None) -> Tensor:
        """With ``avg``/``div`` (C, 1, 1) the input is normalized as (x - avg) / div, folded into the convolution:
        conv(W, (x - a) / d) = conv(W / d, x) + b - sum(W / d * a), so no normalized copy of the image is made
        (a fresh multi-megabyte tensor per call costs more than the convolution on a small CPU).

        On the CPU the convolution always runs in float32: the reduced-precision 16 x 16, stride-16 convolution of
        some CPU builds returns values wrong by as much as the output itself (bfloat16 weights or autocast), while
        every other layer of the encoder stays within rounding."""
        if x.device.type == "cpu" and (x.dtype != torch.float32 or torch.is_autocast_enabled("cpu")):
            with torch.autocast("cpu", enabled=False):
                return self._tokens(x.float(), avg, div).to(x.dtype)
        return self._tokens(x, avg, div)

    def _tokens(self, x: Tensor, avg: Tensor | None, div: Tensor | None) -> Tensor:
        w, b = self.proj.weight, self.proj.bias
        if avg is not None and div is not None:
            w = w.float() / div.float()[None]  # (D, C, p, p), folded in float32
            b = b.float() - (w * avg.float()[None]).sum(dim=(1, 2, 3))  # (D,)
        y = F.conv2d(x, w.to(x.dtype), b.to(x.dtype), stride=self.proj.stride)  # (B, D, h, w)
        return y.flatten(2).transpose(1, 2)  # (B, h w, D)


class PatchEmbed1d(nn.Module):
    """(B, L, C) -> (B, L/4, D): channel-first Conv1d with kernel = stride = 4, then an optional LayerNorm.

    ``layer_norm`` (eps 1e-6 over D) exists only when built with ``layer_norm=True``: whether the released
    checkpoints have it is not confirmed, so a loader builds it when a checkpoint holds its keys.
    """

    def __init__(self, in_channels: int, dim: int, patch: int = PATCH_1D, layer_norm: bool = False):
        super().__init__()
        self.proj = nn.Conv1d(in_channels, dim, kernel_size=patch, stride=patch)
        if layer_norm:
            self.layer_norm = nn.LayerNorm(dim, eps=LN_EPS)

    def forward(self, x: Tensor) -> Tensor:
        x = self.proj(x.transpose(1, 2)).transpose(1, 2)  # (B, C, L) -> (B, D, N) -> (B, N, D)
        return self.layer_norm(x) if hasattr(self, "layer_norm") else x


def make_tokenizer(m: str, dim: int, layer_norm: bool = False) -> nn.Module:
    """The tokenizer of modality ``m`` (released name ``patch_embed.{m}.proj``)."""
    if m in ("img", "mic"):
        return PatchEmbed2d(IN_CHANNELS[m], dim)
    return PatchEmbed1d(IN_CHANNELS[m], dim, layer_norm=layer_norm)


# -------------------------------------------------------------------------------------- raw windows -> inputs
def _candidates(m: str) -> tuple[str, ...]:
    names = (m, WINDOW_KEYS[m], "audio_wave") if m == "mic" else (m, WINDOW_KEYS[m])
    return tuple(dict.fromkeys(names))  # imu and pressure have one name


def window_inputs(batch: Mapping[str, Any], modalities: Sequence[str], device: torch.device | str = "cpu",
                  dtype: torch.dtype = torch.float32) -> dict[str, Tensor]:
    """Batched windows (tensors or numpy arrays) -> model inputs of ``modalities`` on ``device``.

    Each modality is read from its model name or its window name (``WINDOW_KEYS``; ``audio_wave`` for audio), in
    any of these forms:

    - image: contract (B, 6, 224, 224) in [0, 1], or raw frames (B, 2, 224, 224, 3) [t-5, t], uint8 (/ 255) or
      float in [0, 1], packed to the contract's channel order;
    - audio: features (B, 224, 256), or a waveform (B, 2, T) (int16 counts, as the sensor and sessions store it),
      turned into features by the Kaldi filterbank on ``device`` (T = 27000 gives 224 frames);
    - imu (B, 224, 3); pressure (B, 224, 1) or (B, 224).

    Other keys (labels, finger, time, modalities the model does not use) are ignored; shapes are checked by the
    model's forward.
    """
    out: dict[str, Tensor] = {}
    for m in modalities:
        keys = [k for k in _candidates(m) if k in batch]
        if not keys:
            raise ValueError(f"windows: no {m!r} input; expected one of the keys {list(_candidates(m))} "
                             f"(got {sorted(batch)})")
        if len(keys) > 1:
            raise ValueError(f"windows: {m!r} is given twice, as {keys}; pass one of them")
        x = torch.as_tensor(batch[keys[0]]).to(device)
        if m == "img" and x.dim() == 5 and x.shape[1] == 2 and x.shape[-1] == 3:
            scale = x.dtype == torch.uint8
            x = x.permute(0, 4, 1, 2, 3).reshape(x.shape[0], 6, *x.shape[2:4])  # (B, 3, 2, H, W) -> (B, 6, H, W)
            x = x.to(dtype).div_(255.0) if scale else x.to(dtype)  # permuted as bytes, one float copy
        elif m == "mic" and x.dim() == 3 and (keys[0] == "audio_wave" or x.shape[1] == 2 != x.shape[2]):
            x = fbank(x.to(torch.float32))  # (B, 2, T) -> (B, frames, 256)
        elif m == "pressure" and x.dim() == 2:
            x = x[:, :, None]  # (B, L) -> (B, L, 1)
        out[m] = x.to(dtype)
    return out


# ------------------------------------------------------------------------------------ statistics from sessions
def fit_statistics(windows: Dataset, modalities: Sequence[str], max_windows: int = 2048, batch_size: int = 32,
                   num_workers: int = 0, seed: int = 0) -> dict[str, Tensor]:
    """Normalization statistics of ``modalities`` over (a random subset of) ``windows`` (e.g. TouchWindows).

    Returns buffer name -> value as the model stores them: ``img_avg``/``img_div`` (6, 1, 1) per color over both
    frames and every pixel, [c0, c1, c2, c0, c1, c2] (div = std); ``mic_avg``/``mic_div`` (256,) per mel bin
    (div = 2 std); ``pressure_avg``/``pressure_div`` () of the high-passed pressure (div = 2 std). Clamp ranges and
    the IMU scale are constants of the contract and are not returned. Sums run in float64.
    """
    n = len(windows)  # type: ignore[arg-type]
    if n == 0:
        raise ValueError("fit_statistics: no windows")
    if max_windows < 1 or batch_size < 1:
        raise ValueError(f"fit_statistics: max_windows and batch_size must be >= 1, got {max_windows}, {batch_size}")
    pick = np.sort(np.random.default_rng(seed).permutation(n)[: min(n, max_windows)])
    loader = DataLoader(Subset(windows, pick.tolist()), batch_size=batch_size, num_workers=num_workers,
                        worker_init_fn=ignore_stop_signals)
    sums: dict[str, list[Tensor]] = {}  # modality -> [count, sum, sum of squares] over its reduced axes

    def accumulate(m: str, x: Tensor, dims: tuple[int, ...]) -> None:
        x = x.to(torch.float64)
        s = [torch.tensor(float(np.prod([x.shape[d] for d in dims]))), x.sum(dims), x.square().sum(dims)]
        sums[m] = s if m not in sums else [a + b for a, b in zip(sums[m], s, strict=True)]

    for batch in loader:
        inputs = window_inputs(batch, [m for m in modalities if m != "imu"])
        if "img" in inputs:  # (B, 6, H, W): colors are channel pairs (t-5, t)
            x = inputs["img"]
            accumulate("img", x.reshape(x.shape[0], 3, 2, -1).transpose(0, 1).reshape(3, -1), (1,))
        if "mic" in inputs:
            accumulate("mic", inputs["mic"], (0, 1))  # per bin
        if "pressure" in inputs:
            accumulate("pressure", pressure_highpass(inputs["pressure"].to(torch.float64)), (0, 1, 2))

    def mean_std(m: str) -> tuple[Tensor, Tensor]:
        count, s, sq = sums[m]
        mean = s / count
        std = (sq / count - mean.square()).clamp_min(0.0).sqrt().clamp_min(_STD_FLOOR)
        return mean.to(torch.float32), std.to(torch.float32)

    out: dict[str, Tensor] = {}
    if "img" in sums:
        mean, std = mean_std("img")
        out["img_avg"], out["img_div"] = mean.repeat(2).reshape(6, 1, 1), std.repeat(2).reshape(6, 1, 1)
    if "mic" in sums:
        mean, std = mean_std("mic")
        out["mic_avg"], out["mic_div"] = mean, 2.0 * std
    if "pressure" in sums:
        mean, std = mean_std("pressure")
        out["pressure_avg"], out["pressure_div"] = mean, 2.0 * std
    return out
