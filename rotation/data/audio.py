"""Kaldi-compatible log-mel filterbank features in pure torch (batched, CPU or GPU; no torchaudio).

Reproduces ``torchaudio.compliance.kaldi.fbank`` with the options of the Sparsh-X audio contract
(docs/reference/sparsh.md "Sparsh-X input contract", tests/fixtures/README.md): per microphone channel,

1. frames of ``frame_length`` ms every ``frame_shift`` ms, ``snip_edges`` (only whole frames: 1 + (T - L) // S);
2. DC removal (subtract each frame's mean);
3. pre-emphasis 0.97: ``x[n] -= 0.97 x[n-1]`` with ``x[-1] = x[0]`` (Kaldi replicates the first sample);
4. a symmetric Hann window ``0.5 - 0.5 cos(2 pi n / (N - 1))`` (Kaldi's "hanning");
5. zero padding to the next power of two and the power spectrum ``|rfft|^2``;
6. a triangular mel filterbank on Kaldi's mel scale ``1127 ln(1 + f / 700)`` from ``low_freq`` (20 Hz) to Nyquist,
   weights computed on the mel axis as Kaldi does (not HTK's linear-frequency triangles);
7. ``log(max(energy, eps))`` with eps = float32 machine epsilon, the floor that mel bins without any FFT bin hit.

With ``use_energy=False`` and ``htk_compat=True`` nothing else changes (htk_compat only moves the energy column).
The channels' features are concatenated on the feature axis, as the contract's (224, 256) audio input expects:
a (B, 2, 27000) batch at 48 kHz gives (B, 224, 256).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch

EPS = torch.finfo(torch.float32).eps
"""Kaldi's log floor: float32 machine epsilon (log(eps) = -15.9424), torchaudio's ``EPSILON``."""


@dataclass(frozen=True)
class FbankConfig:
    """Filterbank options; the defaults are the Sparsh-X audio contract (docs/reference/sparsh.md)."""

    sample_rate: float = 48000.0
    """Sampling rate of the waveform (Hz); Digit 360 microphones run at 48 kHz (docs/reference/hardware.md section
    4)."""
    num_mel_bins: int = 128
    """Mel bins per channel."""
    frame_length_ms: float = 5.0
    """Analysis window (ms): 240 samples at 48 kHz."""
    frame_shift_ms: float = 2.5
    """Hop between frames (ms): 120 samples at 48 kHz."""
    preemphasis: float = 0.97
    """Pre-emphasis coefficient (Kaldi default)."""
    low_freq: float = 20.0
    """Lower edge of the first mel triangle (Hz, Kaldi default)."""
    high_freq: float = 0.0
    """Upper edge of the last triangle (Hz); <= 0 means Nyquist + high_freq (Kaldi convention)."""

    @property
    def window_size(self) -> int:
        return int(self.sample_rate * self.frame_length_ms * 0.001)

    @property
    def window_shift(self) -> int:
        return int(self.sample_rate * self.frame_shift_ms * 0.001)

    @property
    def fft_size(self) -> int:
        """Window size rounded up to a power of two (Kaldi ``round_to_power_of_two``): 256 for 240 samples."""
        return 1 << (self.window_size - 1).bit_length()

    def num_frames(self, num_samples: int) -> int:
        """Frames of a waveform with ``snip_edges``: 1 + (T - L) // S, 0 when T < L."""
        if num_samples < self.window_size:
            return 0
        return 1 + (num_samples - self.window_size) // self.window_shift


SPARSH_FBANK = FbankConfig()
"""The Sparsh-X contract: 48 kHz, 128 mel bins, 5 ms frames every 2.5 ms; 27000 samples -> 224 frames."""


def mel_scale(freq: torch.Tensor) -> torch.Tensor:
    """Kaldi's mel scale: 1127 ln(1 + f / 700) (f in Hz)."""
    return 1127.0 * torch.log1p(freq / 700.0)


@lru_cache(maxsize=8)
def _mel_banks_cpu(cfg: FbankConfig) -> torch.Tensor:
    """(num_mel_bins, fft_size // 2 + 1) triangular weights on the mel axis (float64, CPU), Kaldi ``MelBanks``."""
    num_fft_bins = cfg.fft_size // 2
    nyquist = 0.5 * cfg.sample_rate
    high = cfg.high_freq if cfg.high_freq > 0.0 else nyquist + cfg.high_freq
    if not (0.0 <= cfg.low_freq < high <= nyquist):
        raise ValueError(f"fbank: need 0 <= low_freq < high_freq <= Nyquist ({nyquist} Hz), got {cfg.low_freq}, {high}")
    mel_low, mel_high = mel_scale(torch.tensor(cfg.low_freq, dtype=torch.float64)), mel_scale(
        torch.tensor(high, dtype=torch.float64)
    )
    delta = (mel_high - mel_low) / (cfg.num_mel_bins + 1)  # equal spacing of the triangles' corners on the mel axis
    b = torch.arange(cfg.num_mel_bins, dtype=torch.float64)[:, None]  # (M, 1)
    left, center, right = mel_low + b * delta, mel_low + (b + 1) * delta, mel_low + (b + 2) * delta
    fft_bin_width = cfg.sample_rate / cfg.fft_size
    mel = mel_scale(fft_bin_width * torch.arange(num_fft_bins, dtype=torch.float64))[None, :]  # (1, F/2)
    up = (mel - left) / (center - left)
    down = (right - mel) / (right - center)
    banks = torch.clamp(torch.minimum(up, down), min=0.0)  # (M, F/2)
    # Kaldi has no weight on the Nyquist bin: one zero column makes the bank match the rfft's F/2 + 1 bins
    return torch.nn.functional.pad(banks, (0, 1))  # (M, F/2 + 1)


def fbank(wave: torch.Tensor, cfg: FbankConfig = SPARSH_FBANK) -> torch.Tensor:
    """Log-mel filterbank features of multichannel audio, channels concatenated on the feature axis.

    Args:
        wave: (B, C, T) or (C, T) waveform at ``cfg.sample_rate`` in any amplitude scale (features of an int16
            recording fed as raw counts differ from the same recording in [-1, 1] by 2 ln(32768) per bin).
            Integer tensors are converted to float32.
        cfg: filterbank options.

    Returns:
        (B, frames, C * num_mel_bins) float features (frames = 1 + (T - L) // S), or (frames, C * num_mel_bins)
        for a (C, T) input; computed in the input's floating dtype (float32 for integers).
    """
    if not isinstance(wave, torch.Tensor):
        raise ValueError(f"fbank: wave must be a torch.Tensor, got {type(wave).__name__}")
    squeeze = wave.dim() == 2
    if squeeze:
        wave = wave[None]
    if wave.dim() != 3:
        raise ValueError(f"fbank: wave must be (B, C, T) or (C, T), got shape {tuple(wave.shape)}")
    if not wave.is_floating_point():
        wave = wave.to(torch.float32)
    bsz, chans, num_samples = wave.shape
    n_frames = cfg.num_frames(num_samples)
    if n_frames < 1:
        raise ValueError(f"fbank: need at least {cfg.window_size} samples for one frame, got {num_samples}")
    dtype, device = wave.dtype, wave.device
    size, shift = cfg.window_size, cfg.window_shift

    frames = wave.unfold(-1, size, shift)  # (B, C, F, L): frame f = samples [f S, f S + L)
    frames = frames - frames.mean(dim=-1, keepdim=True)  # DC removal per frame
    previous = torch.cat([frames[..., :1], frames[..., :-1]], dim=-1)  # (B, C, F, L), x[n-1] with x[-1] = x[0]
    frames = frames - cfg.preemphasis * previous
    # symmetric Hann 0.5 - 0.5 cos(2 pi n / (N - 1)) (Kaldi's "hanning"), built in the working dtype as Kaldi does
    frames = frames * torch.hann_window(size, periodic=False, dtype=dtype, device=device)
    spectrum = torch.fft.rfft(frames, n=cfg.fft_size, dim=-1)  # zero-padded to the FFT size: (B, C, F, K)
    power = spectrum.real.square() + spectrum.imag.square()  # (B, C, F, K), K = fft_size // 2 + 1
    banks = _mel_banks_cpu(cfg).to(device=device, dtype=dtype)  # (M, K)
    mel = torch.matmul(power, banks.T)  # (B, C, F, M)
    logmel = torch.log(torch.clamp(mel, min=EPS))
    out = logmel.permute(0, 2, 1, 3).reshape(bsz, n_frames, chans * cfg.num_mel_bins)  # (B, F, C*M)
    return out[0] if squeeze else out
