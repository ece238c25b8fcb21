"""Touch for the imitation policies: raw Digit 360 windows -> the encoder's inputs -> one embedding per fingertip.

A window comes either from a recorded demonstration (rotation.data.dataset.TouchWindows, already in the encoder's
input format) or from the live contact history of a simulation (envs.held_hand.TouchHistory.windows, raw):
:func:`window_inputs` brings the raw ones to the loader's format (the image pair packed channel-major in [0, 1],
the audio as its Kaldi filterbank, pressure as (224, 1)), so the two paths feed the encoder the same numbers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from envs.sensors.digit360_image import pack_image
from rotation.data.audio import fbank

MODALITY_SETS = {"all": ("img", "mic", "imu", "pressure"), "image": ("img",)}
"""Token groups a policy's frozen touch reads, by the names of the benchmark's rows."""


def window_inputs(raw: Mapping[str, np.ndarray]) -> dict[str, Tensor]:
    """One raw window (envs.sensors.digit360_render.render_window) -> the loader's sample tensors (no batch)."""
    return {"image": torch.from_numpy(pack_image(raw["image"])),
            "audio": fbank(torch.from_numpy(np.ascontiguousarray(raw["audio"], dtype=np.float32))),
            "imu": torch.from_numpy(np.ascontiguousarray(raw["imu"], dtype=np.float32)),
            "pressure": torch.from_numpy(np.ascontiguousarray(raw["pressure"], dtype=np.float32).reshape(-1, 1))}


class TouchEmbedder:
    """A frozen touch encoder reading ``modalities``; :meth:`embed` maps a batch of windows to their mean token."""

    def __init__(self, encoder: str, modalities: str) -> None:
        from rotation.tactile.models.encoders import ENCODERS, kind_of, load_encoder

        if modalities not in MODALITY_SETS:
            raise ValueError(f"touch modalities must be one of {', '.join(MODALITY_SETS)}, got {modalities!r}")
        enc = load_encoder(encoder)
        self.encoder = ENCODERS[kind_of(enc)].restrict(enc, MODALITY_SETS[modalities]).eval().requires_grad_(False)
        self.width = int(self.encoder.token_interface.width)

    @torch.no_grad()
    def embed(self, batch: Mapping[str, Tensor]) -> Tensor:
        """(N, D): the mean of the encoder's tokens for each of N windows (loader-format tensors, batched)."""
        tokens = self.encoder.token_interface.concat(self.encoder(self.encoder.preprocess(dict(batch))))
        return tokens.mean(dim=1)

    def embed_raw(self, windows: Mapping[str, Mapping[str, np.ndarray]], fingers: Sequence[str]) -> Tensor:
        """(F, D): one embedding per fingertip of raw windows ({finger: raw window})."""
        samples = [window_inputs(windows[f]) for f in fingers]
        return self.embed({k: torch.stack([s[k] for s in samples]) for k in samples[0]})
