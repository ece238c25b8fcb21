"""The Kaldi log-mel filterbank (torch, and the numpy twin the env uses) against torchaudio's reference output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from envs.sensors import kaldi
from rotation.data.audio import EPS, SPARSH_FBANK, FbankConfig, fbank

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "kaldi_fbank_48k_128mel.npz"
"""torchaudio's output for three signals (provenance: tests/fixtures/README.md)."""
CASES = ("noise", "chirp_impacts", "int16_scale")


@pytest.fixture(scope="module")
def reference():
    if not FIXTURE.is_file():
        pytest.fail(f"missing fixture {FIXTURE} (it is part of the repository: tests/fixtures/)")
    with np.load(FIXTURE) as f:
        return {k: f[k] for k in f.files}


@pytest.mark.parametrize("case", CASES)
def test_torch_fbank_matches_torchaudio(reference, case):
    out = fbank(torch.from_numpy(reference[f"{case}_wave"]))
    assert out.shape == (224, 256) and out.dtype == torch.float32
    assert np.abs(out.numpy() - reference[f"{case}_fbank"]).max() < 1e-3


@pytest.mark.parametrize("case", CASES)
def test_numpy_fbank_matches_torchaudio(reference, case):
    out = kaldi.fbank(reference[f"{case}_wave"])
    assert out.shape == (224, 256) and out.dtype == np.float32
    assert np.abs(out - reference[f"{case}_fbank"]).max() < 1e-3


def test_batched_equals_one_by_one_and_keeps_the_floor(reference):
    waves = torch.from_numpy(np.stack([reference[f"{c}_wave"] for c in CASES]))  # (3, 2, 27000)
    out = fbank(waves)
    assert out.shape == (3, 224, 256)
    for i in range(len(CASES)):
        assert torch.allclose(out[i], fbank(waves[i]), atol=1e-5)
    # mel bins that receive no FFT bin at 187.5 Hz spacing sit exactly at log(float32 eps)
    floor = float(np.log(EPS))
    assert np.isclose(out.min().item(), floor) and np.isclose(reference["noise_fbank"].min(), floor)


def test_float64_and_integer_inputs(reference):
    wave = reference["int16_scale_wave"]
    ref = reference["int16_scale_fbank"]
    out64 = fbank(torch.from_numpy(wave.astype(np.float64)))
    assert out64.dtype == torch.float64 and np.abs(out64.numpy() - ref).max() < 1e-3
    out16 = fbank(torch.from_numpy(wave.astype(np.int16)))
    assert out16.dtype == torch.float32 and np.abs(out16.numpy() - ref).max() < 1e-3


def test_frame_count_and_errors():
    assert SPARSH_FBANK.window_size == 240 and SPARSH_FBANK.window_shift == 120 and SPARSH_FBANK.fft_size == 256
    assert SPARSH_FBANK.num_frames(27000) == 224 and SPARSH_FBANK.num_frames(239) == 0
    assert fbank(torch.zeros(1, 2, 480)).shape == (1, 3, 256)
    with pytest.raises(ValueError, match="at least 240 samples"):
        fbank(torch.zeros(2, 100))
    with pytest.raises(ValueError, match=r"\(B, C, T\)"):
        fbank(torch.zeros(27000))
    with pytest.raises(ValueError, match="high_freq"):
        fbank(torch.zeros(1, 480), FbankConfig(low_freq=30000.0))
