"""The imitation policy's bundle: ``config.json`` (kind ``il``, the task, the touch it reads, the network's config,
a card) and ``model.safetensors``; :class:`ILPolicy` acts from an observation with temporal ensembling (ACT: every
step predicts a chunk; the action taken is the exponentially weighted mean of all predictions for this step, the
oldest weighted most, ``exp(-0.01 i)``)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from envs.constants import FINGERS
from rotation.il.data import proprio_of
from rotation.il.model import ChunkPolicy, PolicyConfig

ENSEMBLE_DECAY = 0.01
"""ACT's temporal ensembling weight exp(-decay x age index)."""
SHIPPED_IL = Path(__file__).resolve().parents[1] / "policies"
"""Where shipped bundles live (rotation/policies/<name>)."""


class ILPolicy:
    """An imitation policy loaded from its bundle (see the module docstring)."""

    def __init__(self, model: ChunkPolicy, meta: dict[str, Any], touch_encoder: str | None = None) -> None:
        self.model, self.meta = model.eval(), meta
        self.touch_modalities: str = meta.get("touch", "none")
        self.encoder: str | None = meta.get("encoder")
        self.touch_encoder = touch_encoder
        """An end-to-end policy's own trained encoder (its bundle's touch_encoder.safetensors), read frozen."""
        self._embedder = None
        self.reset()

    @property
    def hand(self) -> str:
        """The hand its demonstrations came from, which it runs on (a bundle from before bundles recorded it: the
        insertion task's default hand)."""
        from envs.insertion import InsertionConfig

        return str(self.meta.get("hand", InsertionConfig.hand))

    @property
    def grip(self) -> str:
        """How its demonstrations held the plug, which its evaluation holds it by (a bundle from before bundles
        recorded it: the first version's grip, 'palm')."""
        from envs.plug_grip import FIRST_GRIP

        return str(self.meta.get("grip", FIRST_GRIP))

    @property
    def wrist(self) -> str:
        """How its demonstrations' arm moved the wrist, which its evaluation moves it by (a bundle from before bundles
        recorded it: the stiff wrist)."""
        from envs.wrist_compliance import FIRST_WRIST

        return str(self.meta.get("wrist", FIRST_WRIST))

    @property
    def reads_touch(self) -> bool:
        return self.touch_modalities != "none"

    def reset(self) -> None:
        """A new episode: forget the earlier predictions."""
        self._pending: list[tuple[int, np.ndarray]] = []  # (step predicted at, chunk (K, 6))
        self._step = 0

    def embed(self, windows: Mapping[str, Mapping[str, np.ndarray]]) -> torch.Tensor:
        if self._embedder is None:
            from rotation.il.touch import TouchEmbedder

            self._embedder = (TouchEmbedder(self.encoder, self.touch_modalities) if self.touch_encoder is None
                              else TouchEmbedder(self.touch_encoder, "all"))
        return self._embedder.embed_raw(windows, FINGERS)

    @torch.no_grad()
    def act(self, obs: Mapping[str, np.ndarray], windows: Mapping[str, Mapping[str, np.ndarray]] | None = None
            ) -> np.ndarray:
        """The action (6,) for this step from the observation (image, wrist, joints) and, for a touch-reading
        policy, the fingertips' raw windows."""
        image = torch.from_numpy(np.ascontiguousarray(obs["image"]))[None]
        proprio = torch.from_numpy(proprio_of(obs["wrist"], obs["joints"]))[None]
        touch = self.embed(windows)[None] if self.reads_touch else None
        chunk = self.model.actions(self.model(image, proprio, touch))[0].numpy()
        self._pending = [(s, c) for s, c in self._pending if self._step - s < len(c)] + [(self._step, chunk)]
        preds = np.stack([c[self._step - s] for s, c in self._pending])  # oldest first
        w = np.exp(-ENSEMBLE_DECAY * np.arange(len(preds)))
        self._step += 1
        return (w[:, None] * preds).sum(0) / w.sum()


def save_il(path: Path, model: ChunkPolicy, meta: dict[str, Any], touch_encoder: torch.nn.Module | None = None
            ) -> Path:
    """Write the bundle; ``touch_encoder``: an end-to-end policy's trained encoder, saved whole (weights and
    structure, touch_encoder.safetensors) so that the bundle does not depend on the encoder it was shaped after."""
    from rotation.tactile.models.encoders import ENCODERS, kind_of

    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path / "model.safetensors"))
    if touch_encoder is not None:
        ENCODERS[kind_of(touch_encoder)].save(touch_encoder, path / "touch_encoder.safetensors")
    (path / "config.json").write_text(json.dumps({"kind": "il", **meta, "policy": model.cfg.to_json()}, indent=2)
                                      + "\n")
    return path


def resolve_il(name_or_path: str | Path) -> Path:
    """The folder of an imitation policy bundle given by directory or shipped name (a path that exists wins)."""
    path = Path(name_or_path)
    if not path.exists() and (SHIPPED_IL / str(name_or_path)).is_dir():
        return SHIPPED_IL / str(name_or_path)
    return path


def load_il(name_or_path: str | Path) -> ILPolicy:
    """An imitation policy bundle by directory or shipped name; ValueError naming what is wrong."""
    path = resolve_il(name_or_path)
    try:
        meta = json.loads((path / "config.json").read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{name_or_path}: not an imitation policy bundle ({err})") from None
    if meta.get("kind") != "il":
        raise ValueError(f"{name_or_path}: a {meta.get('kind', 'plain')} bundle, not an imitation policy (kind 'il')")
    cfg = meta.pop("policy")
    model = ChunkPolicy(PolicyConfig(**{**cfg, "image_size": tuple(cfg["image_size"])}))
    model.load_state_dict(load_file(str(path / "model.safetensors")), strict=True)
    touch_encoder = None
    if meta.get("touch") == "e2e":
        touch_encoder = str(path / "touch_encoder.safetensors")
        if not Path(touch_encoder).is_file():
            raise ValueError(f"{name_or_path}: an end-to-end touch policy without its encoder (no {touch_encoder})")
    return ILPolicy(model, meta, touch_encoder)
