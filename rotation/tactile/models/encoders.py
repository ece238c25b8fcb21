"""Registry of touch encoders for the jobs that train or probe them (`rotate pretrain --encoder NAME`, probes).

A job sees an encoder only through rotation.tactile.models.tokens.TouchEncoder (``preprocess``, ``forward(inputs, keep,
registers)``, ``token_interface``) plus what an :class:`EncoderKind` adds here: the layout of each token group (for
block masking), saving and loading weights, a fresh copy of an encoder's structure (end-to-end baselines) and a
view restricted to some token groups (ablations such as image-only). Two kinds: ``sparshx`` (one Digit 360
fingertip) and ``skin`` (Sparsh-skin: the Xela skin of the whole hand).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from envs.sensors.xela import NUM_TAXELS
from rotation.tactile.models.sparsh_skin import FILE_FORMAT as SKIN_FORMAT
from rotation.tactile.models.sparsh_skin import GROUP as SKIN_GROUP
from rotation.tactile.models.sparsh_skin import SIZES as SKIN_SIZES
from rotation.tactile.models.sparsh_skin import SparshSkin, SparshSkinConfig, load_skin, save_skin
from rotation.tactile.models.sparshx import SIZES, SparshX, SparshXConfig
from rotation.tactile.models.sparshx_checkpoint import load_pretrained, read_safetensors, save_checkpoint
from rotation.tactile.models.sparshx_inputs import MODALITIES, TOKEN_GRIDS


@dataclass(frozen=True)
class EncoderKind:
    """How the jobs build, save, load and restrict one kind of encoder."""

    build: Callable[..., nn.Module]
    """(size, groups, fusion, drop_path[, (unimodal, fusion) layers]) -> a freshly initialized encoder."""
    grids: Callable[[nn.Module], dict[str, tuple[int, ...]]]
    """Token layout per group: (h, w) grids get 2-D block masks, (n,) sequences 1-D segments."""
    save: Callable[..., Path]
    """(encoder, file[, weights_dtype]) -> the file: write the weights and structure to one file, the parameters in
    ``weights_dtype`` if given (sparshx_checkpoint.stored_tensors)."""
    load: Callable[[Path, float | None], nn.Module]
    """(file, drop_path override) -> the encoder it holds (strict)."""
    restrict: Callable[[nn.Module, tuple[str, ...]], nn.Module]
    """An encoder of the same weights that reads only some token groups."""
    describe: Callable[[nn.Module], str]
    sizes: tuple[str, ...]
    groups: tuple[str, ...]
    """Every token group this kind can have, in canonical order."""
    rebuild: Callable[[nn.Module], nn.Module]
    """A freshly initialized encoder of the same structure (weights random; buffers as built)."""
    file_format: str
    """``format`` metadata of the kind's saved files (how load_encoder tells the kinds apart)."""


def _sparshx_build(size: str, groups: tuple[str, ...], fusion: str, drop_path: float,
                   layers: tuple[int | None, int | None] = (None, None)) -> nn.Module:
    """``layers``: (unimodal, fusion) layer counts instead of the size's (None: the size's)."""
    return SparshX(SparshXConfig(size=size, modalities=groups, fusion=fusion, drop_path=drop_path,
                                 unimodal_layers=layers[0], fusion_layers=layers[1]))


def _skin_build(size: str, groups: tuple[str, ...], fusion: str, drop_path: float,
                layers: tuple[int | None, int | None] = (None, None)) -> nn.Module:
    if layers != (None, None):
        raise ValueError("layers: the skin encoder's layers come with its size")
    return SparshSkin(SparshSkinConfig(size=size, drop_path=drop_path))


def _sparshx_restrict(model: nn.Module, groups: tuple[str, ...]) -> nn.Module:
    """The same Sparsh-X weights for a subset of its modalities (their blocks, tokenizers, registers, statistics;
    the shared bottleneck). The positional embeddings keep the offsets they were trained with."""
    assert isinstance(model, SparshX)
    missing = [g for g in groups if g not in model.modalities]
    if missing:
        raise ValueError(f"the encoder has no modality {missing} (it has {', '.join(model.modalities)})")
    cfg = SparshXConfig(**{**model.cfg.__dict__, "modalities": tuple(groups)})
    drop = set(model.modalities) - set(cfg.modalities)
    keep_rows = [model.modalities.index(m) for m in cfg.modalities]
    state = {}
    for k, v in model.state_dict().items():
        parts = k.split(".")
        if drop & set(parts) or any(parts[0].startswith(f"{m}_") for m in drop):
            continue
        state[k] = v[keep_rows] if k == "register_tokens" else v  # (M, 1, D) -> (M', 1, D)
    sub = SparshX(cfg).to(model.register_tokens.device)
    sub.load_state_dict(state, strict=True)
    return sub


def _skin_restrict(model: nn.Module, groups: tuple[str, ...]) -> nn.Module:
    """Sparsh-skin has one token group: restricting to it is the encoder itself."""
    if tuple(groups) != (SKIN_GROUP,):
        raise ValueError(f"the encoder has no modality {[g for g in groups if g != SKIN_GROUP]} (it has {SKIN_GROUP})")
    return model


ENCODERS: dict[str, EncoderKind] = {
    "sparshx": EncoderKind(
        build=_sparshx_build,
        grids=lambda m: {g: TOKEN_GRIDS[g] for g in m.modalities},  # type: ignore[union-attr]
        save=lambda m, path, weights_dtype=None: save_checkpoint(m, path, weights_dtype),  # type: ignore[arg-type]
        load=lambda path, drop_path: load_pretrained(path, drop_path=drop_path),
        restrict=_sparshx_restrict,
        describe=lambda m: m.cfg.describe(),  # type: ignore[union-attr]
        sizes=tuple(SIZES),
        groups=MODALITIES,
        rebuild=lambda m: SparshX(m.cfg),  # type: ignore[arg-type] (its layer counts and tokenizers too)
        file_format="sparshx",
    ),
    "skin": EncoderKind(
        build=_skin_build,
        grids=lambda m: {SKIN_GROUP: (NUM_TAXELS,)},  # blocks over the taxel order
        save=lambda m, path, weights_dtype=None: save_skin(m, path, weights_dtype),  # type: ignore[arg-type]
        load=lambda path, drop_path: load_skin(path, drop_path=drop_path),
        restrict=_skin_restrict,
        describe=lambda m: m.cfg.describe(),  # type: ignore[union-attr]
        sizes=tuple(SKIN_SIZES),
        groups=(SKIN_GROUP,),
        rebuild=lambda m: SparshSkin(m.cfg),  # type: ignore[arg-type]
        file_format=SKIN_FORMAT,
    ),
}
"""Encoder name -> kind; `rotate pretrain --encoder` chooses among these."""


def encoder_kind(name: str) -> EncoderKind:
    if name not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; encoders: {', '.join(ENCODERS)}")
    return ENCODERS[name]


def kind_of(model: nn.Module) -> str:
    """The registry name of a built encoder."""
    if isinstance(model, SparshX):
        return "sparshx"
    if isinstance(model, SparshSkin):
        return "skin"
    raise ValueError(f"not a registered touch encoder: {type(model).__name__}")


def fresh_like(model: nn.Module) -> nn.Module:
    """The same encoder structure with fresh random weights (the caller seeds torch) and ``model``'s input
    statistics (buffers: data facts, not learned): the end-to-end baseline a frozen encoder is compared with."""
    fresh = encoder_kind(kind_of(model)).rebuild(model)
    theirs = dict(model.named_buffers())
    with torch.no_grad():
        for name, buf in fresh.named_buffers():
            buf.copy_(theirs[name])
    return fresh


def parse_groups(text: str | Sequence[str], kind: str) -> tuple[str, ...]:
    """'img,mic' or ('img', 'mic') -> the groups in the kind's canonical order (ValueError on unknown names); an
    empty string: every group of the kind."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text) if t.strip()]
    allowed = encoder_kind(kind).groups
    if isinstance(text, str) and not text.strip():
        return allowed
    bad = [t for t in items if t not in allowed]
    if bad or not items or len(set(items)) != len(items):
        raise ValueError(f"modalities: need a non-empty subset of {', '.join(allowed)} without repeats, got "
                         f"{items or text!r}")
    return tuple(g for g in allowed if g in items)


SHIPPED_ENCODERS = Path(__file__).resolve().parents[1] / "pretrained"
"""Encoders shipped with the package, one directory each (encoder.safetensors + card.md), loaded by name."""


def shipped_encoders() -> list[str]:
    """Names of the shipped encoders (``load_encoder(name)``)."""
    if not SHIPPED_ENCODERS.is_dir():
        return []
    return sorted(p.name for p in SHIPPED_ENCODERS.iterdir() if (p / "encoder.safetensors").is_file())


def load_encoder(path: str | Path, drop_path: float | None = None, device: torch.device | str = "cpu") -> nn.Module:
    """An encoder from a file written by ``EncoderKind.save`` (or a released Sparsh-X checkpoint), from a
    `rotate pretrain` run directory (its ``encoder.safetensors``), or a shipped encoder by name
    (:func:`shipped_encoders`, e.g. ``sparshx-tinier-sim``)."""
    path = Path(path)
    if not path.exists() and str(path) in shipped_encoders():
        path = SHIPPED_ENCODERS / str(path)
    if path.is_dir():
        if not (path / "encoder.safetensors").is_file():
            raise ValueError(f"{path}: no encoder.safetensors (a `rotate pretrain` run writes it at each checkpoint)")
        path = path / "encoder.safetensors"
    if not path.is_file():
        shipped = ", ".join(shipped_encoders()) or "none"
        raise ValueError(f"no encoder checkpoint at {path} (shipped encoders: {shipped})")
    return ENCODERS[file_kind(path)].load(path, drop_path).to(device)


def file_kind(path: Path) -> str:
    """The encoder kind of a checkpoint file: from its safetensors ``format`` metadata; a torch file (.pth, .pt)
    or our safetensors without a known format is a Sparsh-X checkpoint (released weights)."""
    if path.suffix != ".safetensors":
        return "sparshx"
    fmt = read_safetensors(path, tensors=False)[1].get("format")
    return next((name for name, kind in ENCODERS.items() if kind.file_format == fmt), "sparshx")
