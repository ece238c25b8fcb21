"""Sparsh-X weights: load a downloaded or our own checkpoint strictly, save ours.

Accepted files:

- a released backbone (``d360_sparshx_*.pth``): a bare state dict with the names of
  docs/reference/sparshx_state_dict.md, read with ``torch.load(..., weights_only=True)``;
- a training checkpoint of the original code: the ``teacher_encoder.backbone.*`` entries are the encoder (heads and
  centers are ignored); also found one level down under ``state_dict``;
- our own ``.safetensors`` (:func:`save_checkpoint`), which carries the SparshXConfig as JSON metadata.

Loading is strict, never ``strict=False``: the model is built from the checkpoint's own structure (size from the
width, modalities from the tokenizers, layer counts, fusion kind, the optional tokenizer LayerNorm) or from a
config the caller insists on, and any missing or unexpected name or shape raises :class:`CheckpointMismatch`
listing the first few of each with their counts and what the checkpoint looks like instead.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from envs.errors import RequestRefused
from rotation.configs import from_jsonable, to_jsonable
from rotation.tactile.models.sparshx import SIZES, SparshX, SparshXConfig
from rotation.tactile.models.sparshx_inputs import MODALITIES

TRAINING_PREFIX = "teacher_encoder.backbone."
"""Prefix of the encoder in the original code's training checkpoints."""
SHOW = 5
"""Names shown per kind of mismatch (the counts are always complete)."""
_META_FORMAT = "sparshx"


class CheckpointMismatch(ValueError):
    """A checkpoint whose names or shapes differ from the model's (the message says exactly how)."""


def shape_str(shape: torch.Size | tuple[int, ...]) -> str:
    """``768x6x16x16``; ``scalar`` for a 0-dim tensor (the notation of the released key list)."""
    return "x".join(str(s) for s in shape) or "scalar"


# ------------------------------------------------------------------------------------------------- reading
def read_safetensors(path: str | Path, tensors: bool = True) -> tuple[dict[str, Tensor], dict[str, str]]:
    """Tensors (none with ``tensors=False``) and metadata of a safetensors file; ValueError naming the file if it is
    not one (every encoder file of this project is read through here)."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
        state = load_file(str(path)) if tensors else {}
    except (SafetensorError, OSError, ValueError) as err:
        raise ValueError(f"{path} is not a readable safetensors file: {err}") from err
    return dict(state), meta


def read_state_dict(path: str | Path) -> tuple[dict[str, Tensor], SparshXConfig | None]:
    """The encoder's tensors in a checkpoint file (prefixes removed) and the config it declares (ours only)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no checkpoint file at {path}")
    if path.suffix == ".safetensors":
        state, meta = read_safetensors(path)
        cfg = None
        if meta.get("format") == _META_FORMAT and "config" in meta:
            cfg = from_jsonable(SparshXConfig, json.loads(meta["config"]))
        return dict(state), cfg
    try:
        try:  # memory-mapped: a 1.4 GB base checkpoint is read while it is copied into the model
            obj = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError:  # files of the legacy (non-zip) format cannot be mapped
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as err:
        raise RequestRefused(f"{path} is not a readable torch checkpoint (loaded with weights_only=True): "
                             f"{str(err).splitlines()[0] if str(err) else type(err).__name__}") from err
    return _encoder_entries(obj, path), None


def _encoder_entries(obj: Any, path: Path) -> dict[str, Tensor]:
    if not isinstance(obj, Mapping):
        raise ValueError(f"{path}: expected a state dict (name -> tensor), got {type(obj).__name__}")
    if any(isinstance(k, str) and k.startswith(TRAINING_PREFIX) for k in obj):
        obj = {k[len(TRAINING_PREFIX):]: v for k, v in obj.items() if k.startswith(TRAINING_PREFIX)}
    elif isinstance(obj.get("state_dict"), Mapping):
        return _encoder_entries(obj["state_dict"], path)
    bad = [k for k, v in obj.items() if not isinstance(v, Tensor)]
    if bad:
        raise ValueError(f"{path}: entries that are not tensors ({len(bad)}): {', '.join(map(str, bad[:SHOW]))}; "
                         f"expected a Sparsh-X backbone state dict or a training checkpoint with {TRAINING_PREFIX}*")
    return dict(obj)


def has_patch_layer_norm(state: Mapping[str, Any]) -> bool:
    """Whether a state dict holds the optional IMU/pressure tokenizer LayerNorm."""
    return any(k.startswith(f"patch_embed.{m}.layer_norm.") for m in ("imu", "pressure") for k in state)


def infer_config(state: Mapping[str, Tensor], drop_path: float = 0.0) -> SparshXConfig:
    """The SparshXConfig whose model has a checkpoint's structure (size, modalities, layers, fusion, LayerNorm)."""
    mods = tuple(m for m in MODALITIES if f"patch_embed.{m}.proj.weight" in state)
    if not mods:
        first = ", ".join(list(state)[:SHOW]) or "none"
        raise CheckpointMismatch(f"not a Sparsh-X backbone: no patch_embed.<modality>.proj.weight entry "
                                 f"(modalities {', '.join(MODALITIES)}); first names: {first}")
    width = int(state[f"patch_embed.{mods[0]}.proj.weight"].shape[0])
    size = next((name for name, spec in SIZES.items() if spec.embed_dim == width), None)
    if size is None:
        widths = ", ".join(f"{n} {s.embed_dim}" for n, s in SIZES.items())
        raise CheckpointMismatch(f"Sparsh-X checkpoint of width {width}: no size has it ({widths})")

    def layers(prefix: str) -> int:
        found = [int(mt.group(1)) for k in state if (mt := re.match(rf"{prefix}\.(\d+)\.", k))]
        return max(found) + 1 if found else 0

    n_uni, n_fus = layers("blocks"), layers("fusion_blocks")
    vanilla = any(re.match(r"fusion_blocks\.\d+\.norm1\.weight$", k) for k in state)
    spec = SIZES[size]
    return SparshXConfig(
        size=size, modalities=mods, fusion="vanilla" if vanilla else "bottleneck", drop_path=drop_path,
        patch_layer_norm=has_patch_layer_norm(state),
        unimodal_layers=None if n_uni == spec.unimodal_layers else n_uni,
        fusion_layers=None if n_fus == spec.fusion_layers else n_fus,
    )


# ------------------------------------------------------------------------------------------------ matching
def mismatch_report(expected: Mapping[str, Any], found: Mapping[str, Any]) -> tuple[list[str], list[str], list[str]]:
    """(missing, unexpected, shape mismatches) between a model's state dict and a checkpoint's (model order)."""
    missing = [k for k in expected if k not in found]
    unexpected = [k for k in found if k not in expected]
    shapes = [f"{k} (checkpoint {shape_str(found[k].shape)}, model {shape_str(expected[k].shape)})"
              for k in expected if k in found and tuple(found[k].shape) != tuple(expected[k].shape)]
    return missing, unexpected, shapes


def check_matches(model: SparshX, state: Mapping[str, Tensor], source: str = "checkpoint") -> None:
    """Raise :class:`CheckpointMismatch` unless ``state`` has exactly the model's names and shapes."""
    missing, unexpected, shapes = mismatch_report(model.state_dict(), state)
    if not (missing or unexpected or shapes):
        return
    lines = [f"{source} does not match {model.cfg.describe()}"]
    for what, names in (("missing from the checkpoint", missing), ("unexpected in the checkpoint", unexpected),
                        ("shape mismatches", shapes)):
        if names:
            more = f", ... ({len(names) - SHOW} more)" if len(names) > SHOW else ""
            lines.append(f"  {len(names)} {what}: {', '.join(names[:SHOW])}{more}")
    try:
        lines.append(f"  the checkpoint looks like: {infer_config(state).describe()}")
    except CheckpointMismatch as err:
        lines.append(f"  the checkpoint: {err}")
    raise CheckpointMismatch("\n".join(lines))


def _model_for(state: Mapping[str, Tensor], declared: SparshXConfig | None, config: SparshXConfig | None,
               drop_path: float | None) -> SparshXConfig:
    if config is not None:  # the caller's structure; the optional LayerNorm is a fact of the file
        cfg = dataclasses.replace(config, patch_layer_norm=has_patch_layer_norm(state))
    else:
        cfg = declared if declared is not None else infer_config(state)
    return cfg if drop_path is None else dataclasses.replace(cfg, drop_path=drop_path)


def load_pretrained(path: str | Path, config: SparshXConfig | None = None, device: torch.device | str = "cpu",
                    drop_path: float | None = None) -> SparshX:
    """A SparshX with a checkpoint's weights, loaded strictly (see the module docstring).

    Args:
        path: ``.pth``/``.pt`` (released backbone or training checkpoint) or our ``.safetensors``.
        config: the structure to insist on (e.g. ``SparshXConfig(size="base")``); None = the checkpoint's own.
            ``patch_layer_norm`` always follows the file.
        device: where the weights go (built on the meta device first, so nothing is initialized twice).
        drop_path: override of the config's stochastic depth (for fine-tuning).

    Raises:
        CheckpointMismatch: names or shapes differ; ValueError: unreadable file.
    """
    state, declared = read_state_dict(path)
    cfg = _model_for(state, declared, config, drop_path)
    with torch.device("meta"):
        model = SparshX(cfg)
    check_matches(model, state, source=str(path))
    model = model.to_empty(device=device)
    model.load_state_dict(state, strict=True)
    return model


def check_checkpoint(path: str | Path, config: SparshXConfig) -> tuple[SparshXConfig, int]:
    """Load ``path`` strictly into a meta-device model of ``config`` (no memory for weights); returns the config
    used (``patch_layer_norm`` from the file) and the number of tensors. Raises like :func:`load_pretrained`."""
    state, _ = read_state_dict(path)
    cfg = _model_for(state, None, config, None)
    with torch.device("meta"):
        model = SparshX(cfg)
    check_matches(model, state, source=str(path))
    model.load_state_dict(state, strict=True, assign=True)
    return cfg, len(state)


def stored_tensors(model: torch.nn.Module, weights_dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
    """The model's state dict as a file stores it (contiguous, on the CPU): with ``weights_dtype`` (e.g.
    torch.float16, for a small shipped file) the parameters in that type, the buffers (input statistics, positional
    tables) as they are; loading casts back to the model's float32."""
    params = {name for name, _ in model.named_parameters()}
    return {k: (v.to(weights_dtype) if weights_dtype is not None and k in params else v).detach().contiguous().cpu()
            for k, v in model.state_dict().items()}


def save_checkpoint(model: SparshX, path: str | Path, weights_dtype: torch.dtype | None = None) -> Path:
    """Write the model's state dict (released names) as safetensors with its config in the metadata;
    ``weights_dtype``: see :func:`stored_tensors`."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = stored_tensors(model, weights_dtype)
    meta = {"format": _META_FORMAT, "config": json.dumps(to_jsonable(model.cfg))}
    save_file(tensors, str(path), metadata=meta)
    return path
