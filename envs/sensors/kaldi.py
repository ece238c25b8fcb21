"""Kaldi-compatible log-mel filterbank in numpy, for the env's `tactile` observation (envs/ has no torch).

The same computation as ``rotation.data.audio.fbank`` (whose docstring lists the steps and options, from the
Sparsh-X audio contract in docs/reference/sparsh.md); both are tested against tests/fixtures/kaldi_fbank_48k_128mel.npz.
The torch one serves the data loaders (batched, GPU); this one serves the simulator's per-step windows.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

SAMPLE_RATE = 48000
NUM_MEL_BINS = 128
WINDOW_SIZE = 240
"""5 ms frames at 48 kHz (docs/reference/sparsh.md)."""
WINDOW_SHIFT = 120
"""2.5 ms hop at 48 kHz."""
FFT_SIZE = 256
"""WINDOW_SIZE rounded up to a power of two (Kaldi ``round_to_power_of_two``)."""
PREEMPHASIS = 0.97
LOW_FREQ = 20.0
"""Lower edge of the first triangle (Hz), Kaldi's default."""
EPS = float(np.finfo(np.float32).eps)
"""Kaldi's log floor (float32 machine epsilon)."""


@lru_cache(maxsize=1)
def mel_banks() -> np.ndarray:
    """(128, 129) triangular weights on Kaldi's mel axis 1127 ln(1 + f / 700), 20 Hz .. Nyquist, float32."""

    def mel(f):
        return 1127.0 * np.log1p(np.asarray(f, dtype=np.float64) / 700.0)

    lo, hi = mel(LOW_FREQ), mel(SAMPLE_RATE / 2)
    delta = (hi - lo) / (NUM_MEL_BINS + 1)
    b = np.arange(NUM_MEL_BINS, dtype=np.float64)[:, None]  # (M, 1)
    left, center, right = lo + b * delta, lo + (b + 1) * delta, lo + (b + 2) * delta
    m = mel(SAMPLE_RATE / FFT_SIZE * np.arange(FFT_SIZE // 2))[None, :]  # (1, 128)
    banks = np.maximum(0.0, np.minimum((m - left) / (center - left), (right - m) / (right - center)))  # (M, 128)
    return np.pad(banks, ((0, 0), (0, 1))).astype(np.float32)  # no weight on the Nyquist bin -> (M, 129)


@lru_cache(maxsize=1)
def _banks_t() -> np.ndarray:
    """(129, 128) contiguous transpose of :func:`mel_banks`."""
    return np.ascontiguousarray(mel_banks().T)


@lru_cache(maxsize=1)
def hann_window() -> np.ndarray:
    """Symmetric Hann window 0.5 - 0.5 cos(2 pi n / (N - 1)) (Kaldi's "hanning"), float32."""
    n = np.arange(WINDOW_SIZE, dtype=np.float32)
    return (0.5 - 0.5 * np.cos(2.0 * np.pi * n / (WINDOW_SIZE - 1))).astype(np.float32)


def fbank(wave: np.ndarray) -> np.ndarray:
    """Log-mel features of (..., C, T) audio at 48 kHz -> (..., frames, C * 128) float32, channels side by side.

    frames = 1 + (T - 240) // 120 (snip_edges); 27000 samples give the contract's 224 frames.
    """
    x = np.asarray(wave, dtype=np.float32)
    if x.ndim < 2 or x.shape[-1] < WINDOW_SIZE:
        raise ValueError(f"fbank: wave must be (..., C, T) with T >= {WINDOW_SIZE}, got shape {x.shape}")
    frames = np.lib.stride_tricks.sliding_window_view(x, WINDOW_SIZE, axis=-1)[..., ::WINDOW_SHIFT, :]
    frames = np.ascontiguousarray(frames)  # (..., C, F, L): frame f = samples [f S, f S + L)
    frames = frames - frames.mean(axis=-1, keepdims=True)  # DC removal
    previous = np.concatenate([frames[..., :1], frames[..., :-1]], axis=-1)  # x[n-1] with x[-1] = x[0]
    frames = (frames - PREEMPHASIS * previous) * hann_window()
    spectrum = np.fft.rfft(frames, n=FFT_SIZE, axis=-1)  # (..., C, F, 129)
    power = (spectrum.real**2 + spectrum.imag**2).astype(np.float32)  # (..., C, F, 129)
    # one 2-D product with contiguous operands (BLAS); a batched product with a transposed view is ~30x slower
    mel = power.reshape(-1, FFT_SIZE // 2 + 1) @ _banks_t()  # (... * C * F, 128)
    mel = mel.reshape(*power.shape[:-1], NUM_MEL_BINS)  # (..., C, F, 128)
    logmel = np.log(np.maximum(mel, EPS))
    logmel = np.moveaxis(logmel, -3, -2)  # (..., F, C, 128)
    return logmel.reshape(*logmel.shape[:-2], -1).astype(np.float32)  # (..., F, C*128)
