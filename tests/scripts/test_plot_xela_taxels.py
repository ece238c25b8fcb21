"""scripts/plot_xela_taxels.py writes the picture of docs/skin.md."""

from __future__ import annotations


def test_plot_xela_taxels(load_script, tmp_path):
    module = load_script("plot_xela_taxels")
    out = tmp_path / "taxels.png"
    assert module.main(["--out", str(out), "--dpi", "30"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
