"""Export a pretrained touch encoder (Sparsh-X or Sparsh-skin) for shipping: its weights in float16 (half the
file), buffers kept.

    python scripts/export_encoder.py --checkpoint runs/pretrain_tinier --out rotation/tactile/pretrained/NAME

Writes OUT/encoder.safetensors (loads with ``rotation.tactile.models.encoders.load_encoder(OUT)`` or, once under
rotation/tactile/pretrained/, by NAME) and prints the largest difference of the tokens it encodes on random inputs
from the float32 original's, so the export's cost is measured, not assumed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from rotation.configs import script_main
from rotation.tactile.models.encoders import ENCODERS, kind_of, load_encoder
from rotation.tactile.models.sparsh_skin import GROUP
from rotation.tactile.models.sparshx_inputs import INPUT_SHAPES


@dataclass
class Config:
    checkpoint: Path = Path("runs/pretrain")
    """A `rotate pretrain` run directory or an encoder.safetensors (Sparsh-X or Sparsh-skin)."""
    out: Path = Path("runs/encoder_export")
    """Directory to write encoder.safetensors into (created)."""
    dtype: str = "float16"
    """Stored type of the weights: float16 or bfloat16 (float32: a plain copy)."""


def run(cfg: Config) -> dict:
    dtypes = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32}
    if cfg.dtype not in dtypes:
        raise ValueError(f"dtype: one of {', '.join(dtypes)}, got {cfg.dtype!r}")
    model = load_encoder(cfg.checkpoint).eval()
    kind = kind_of(model)
    path = ENCODERS[kind].save(model, Path(cfg.out) / "encoder.safetensors", dtypes[cfg.dtype])
    exported = load_encoder(path).eval()
    g = torch.Generator().manual_seed(0)
    shapes = {GROUP: model.cfg.input_shape} if kind == "skin" else {m: INPUT_SHAPES[m] for m in model.modalities}
    inputs = {m: torch.randn((2, *shape), generator=g) for m, shape in shapes.items()}
    with torch.no_grad():
        a, b = model(inputs), exported(inputs)
    err = max(float((a[k] - b[k]).abs().max() / a[k].abs().max()) for k in a)
    print(f"export: {path} ({path.stat().st_size / 1e6:.1f} MB, weights {cfg.dtype}); largest token difference "
          f"from float32: {err:.2e} of the largest token")
    return {"path": str(path), "bytes": path.stat().st_size, "relative_error": err}


if __name__ == "__main__":
    raise SystemExit(script_main(Config, run, __doc__))
