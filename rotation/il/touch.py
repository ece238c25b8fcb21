"""Touch for the imitation policies: raw Digit 360 windows -> the encoder's inputs -> one embedding per fingertip;
or the Xela skin's window -> Sparsh-skin -> one embedding of the whole hand.

A Digit 360 window comes either from a recorded demonstration (rotation.data.dataset.TouchWindows, already in the
encoder's input format) or from the live contact history of a simulation (envs.held_hand.TouchHistory.windows, raw):
:func:`window_inputs` brings the raw ones to the loader's format (the image pair packed channel-major in [0, 1],
the audio as its Kaldi filterbank, pressure as (224, 1)), so the two paths feed the encoder the same numbers. A skin
window is the same (10, 368, 6) array either way (rotation.data.skin.SkinWindows, envs.held_skin.SkinHistory), with
the session's baseline.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from envs.sensors.digit360_image import pack_image
from rotation.data.audio import fbank

MODALITY_SETS = {"all": ("img", "mic", "imu", "pressure"), "image": ("img",), "e2e": ("img", "mic", "imu", "pressure"),
                 "skin": ("skin",)}
"""Token groups a policy's touch reads, by the names of the benchmark's rows: 'e2e' reads all four through an encoder
of the named one's structure trained from random weights with the policy (no pretraining); 'skin' is a Sparsh-skin
encoder's one group (the Xela hand)."""


def window_inputs(raw: Mapping[str, np.ndarray]) -> dict[str, Tensor]:
    """One raw window (envs.sensors.digit360_render.render_window) -> the loader's sample tensors (no batch)."""
    return {"image": torch.from_numpy(pack_image(raw["image"])),
            "audio": fbank(torch.from_numpy(np.ascontiguousarray(raw["audio"], dtype=np.float32))),
            "imu": torch.from_numpy(np.ascontiguousarray(raw["imu"], dtype=np.float32)),
            "pressure": torch.from_numpy(np.ascontiguousarray(raw["pressure"], dtype=np.float32).reshape(-1, 1))}


class TouchEmbedder:
    """A touch encoder reading ``modalities``; :meth:`embed` maps a batch of windows to their mean token.

    Frozen (the pretrained weights of ``encoder``) unless ``modalities`` is 'e2e': then an encoder of the same
    structure and input statistics with fresh random weights (seeded by ``seed``), trainable."""

    def __init__(self, encoder: str, modalities: str, seed: int = 0) -> None:
        from rotation.tactile.models.encoders import ENCODERS, fresh_like, kind_of, load_encoder

        if modalities not in MODALITY_SETS:
            raise ValueError(f"touch modalities must be one of {', '.join(MODALITY_SETS)}, got {modalities!r}")
        enc = load_encoder(encoder)
        self.skin = kind_of(enc) == "skin"
        if self.skin != (modalities == "skin"):
            want = "a Sparsh-skin encoder" if modalities == "skin" else "a Sparsh-X encoder (Digit 360)"
            raise ValueError(f"touch {modalities!r} reads {want}; {encoder} is a {kind_of(enc)} encoder")
        self.trainable = modalities == "e2e"
        if self.trainable:
            torch.manual_seed(seed)
            enc = fresh_like(enc)
        enc = ENCODERS[kind_of(enc)].restrict(enc, MODALITY_SETS[modalities])
        self.encoder = enc.train() if self.trainable else enc.eval().requires_grad_(False)
        self.width = int(self.encoder.token_interface.width)

    def tokens_mean(self, batch: Mapping[str, Tensor]) -> Tensor:
        """(N, D) with gradients to a trainable encoder: the mean of its tokens for each of N windows."""
        tokens = self.encoder.token_interface.concat(self.encoder(self.encoder.preprocess(dict(batch))))
        return tokens.mean(dim=1)

    @torch.no_grad()
    def embed(self, batch: Mapping[str, Tensor]) -> Tensor:
        """(N, D): the mean of the encoder's tokens for each of N windows (loader-format tensors, batched)."""
        return self.tokens_mean(batch)

    def embed_raw(self, windows: Mapping[str, Any], fingers: Sequence[str]) -> Tensor:
        """(F, D): one embedding per fingertip of raw Digit 360 windows ({finger: raw window}); (1, D) for the skin's
        window ({"skin": (10, 368, 6), "xela_baseline": (368, 3)})."""
        if self.skin:
            return self.embed({k: torch.as_tensor(np.asarray(windows[k], np.float32))[None]
                               for k in ("skin", "xela_baseline")})
        samples = [window_inputs(windows[f]) for f in fingers]
        return self.embed({k: torch.stack([s[k] for s in samples]) for k in samples[0]})
