"""Export a bundle's acting path to ONNX (normalization inside the graph).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch import nn

from rotation.policy.actor import ActorNet
from rotation.policy.bundle import PolicyBundle

# ---------------------------------------------------------------------------------------------------------------------
# ONNX export


class _OnnxActor(nn.Module):
    """Positional wrapper for export: one input per observation group (in config order) -> (action, latent)."""

    def __init__(self, net: ActorNet, keys: list[str]) -> None:
        super().__init__()
        self.net, self.keys = net, keys

    def forward(self, *groups: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        obs = dict(zip(self.keys, groups, strict=True))
        z = self.net.extractor.z(obs)  # (N, Z)
        return self.net.mean(obs, z).clamp(-1.0, 1.0), z  # (N, A), (N, Z)


def export_onnx(bundle: PolicyBundle, path: str | Path, opset: int = 17) -> Path:
    """Export the acting path to ONNX: named float32 inputs = the observation groups (leading batch dim ``N``),
    outputs ``action`` (N, 16) in [-1, 1] and ``latent`` (N, Z). Normalization is inside the graph."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(bundle.config.obs_groups)
    wrapper = _OnnxActor(bundle.net.eval(), keys).eval()
    example = tuple(torch.zeros((1, *bundle.config.obs_groups[k])) for k in keys)
    dynamic = {k: {0: "N"} for k in [*keys, "action", "latent"]}
    with warnings.catch_warnings():
        # the TorchScript exporter: the dynamo one needs onnxscript, which is not a dependency
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(wrapper, example, str(path), input_names=keys, output_names=["action", "latent"],
                          dynamic_axes=dynamic, opset_version=opset, dynamo=False)
    return path
