"""scripts/plot_xela_taxels.py writes the picture of docs/skin.md."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "plot_xela_taxels.py"


def test_plot_xela_taxels(tmp_path):
    spec = importlib.util.spec_from_file_location("plot_xela_taxels", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    out = tmp_path / "taxels.png"
    assert module.main(["--out", str(out), "--dpi", "30"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
