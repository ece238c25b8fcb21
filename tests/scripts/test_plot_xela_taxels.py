"""scripts/plot_xela_taxels.py writes the picture of docs/skin.md."""

from __future__ import annotations


def test_plot_xela_taxels(load_script, tmp_path):
    module = load_script("plot_xela_taxels")
    out = tmp_path / "taxels.png"
    assert module.main(["--out", str(out), "--dpi", "30"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_output_name_without_png_is_refused(load_script, tmp_path, capsys):
    """matplotlib would write `noext.png` for `--out noext`; the script refuses the name instead of reporting a file
    that does not exist, and writes nothing."""
    module = load_script("plot_xela_taxels")
    assert module.main(["--out", str(tmp_path / "noext")]) == 2
    assert "out must end in .png" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
