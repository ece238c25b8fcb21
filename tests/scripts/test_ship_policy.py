"""scripts/ship_policy.py: a bundle copied into the package with a model card carrying its evaluation rows."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

POLICIES = Path(__file__).resolve().parents[2] / "rotation" / "policies"


@pytest.fixture(scope="module")
def ship(load_script):
    return load_script("ship_policy")


def _row(policy: str, condition: str, episodes: int, ttf: float) -> dict:
    row = {"policy": policy, "condition": condition, "episodes": episodes}
    for key in ("net_rotation_rate", "rotation_rate", "upright", "vertical_drift", "lin_vel", "torque"):
        row[key] = 0.5
    row["ttf"] = ttf
    return row


def _ship(ship, tmp_path: Path, monkeypatch, rows: list[dict]) -> str:
    bundle = tmp_path / "bundle"
    shutil.copytree(POLICIES / "student", bundle)
    (tmp_path / "results.json").write_text(json.dumps({"rows": rows}))
    monkeypatch.setattr(ship, "PACKAGE_POLICIES", tmp_path / "policies")
    dest = ship.run(ship.Config(bundle=bundle, name="mine", command="rotate distill --out runs/x",
                                evaluation=tmp_path / "results.json", label="candidate"))
    assert (dest / "model.safetensors").read_bytes() == (bundle / "model.safetensors").read_bytes()
    return (dest / "MODEL_CARD.md").read_text()


def test_the_card_holds_the_command_and_only_the_labelled_policys_rows(ship, tmp_path, monkeypatch):
    card = _ship(ship, tmp_path, monkeypatch, [_row("candidate", "nominal", 64, 0.9),
                                                _row("other", "nominal", 64, 0.1),
                                                _row("candidate", "friction_0.25", 64, 0.6)])
    assert "`rotate distill --out runs/x`" in card
    assert "## Evaluation (64 episodes per condition" in card
    assert "| nominal | 0.500 | 0.500 | 0.900 |" in card and "| friction_0.25 | 0.500 | 0.500 | 0.600 |" in card
    assert "0.100" not in card  # the other policy's row


def test_a_pooled_report_gets_an_episodes_column(ship, tmp_path, monkeypatch):
    card = _ship(ship, tmp_path, monkeypatch, [_row("candidate", "nominal", 448, 0.9),
                                                _row("candidate", "friction_0.25", 768, 0.6)])
    assert "per condition" not in card
    assert "| condition | episodes | net_rotation_rate |" in card
    assert "| nominal | 448 | 0.500 | 0.500 | 0.900 |" in card
    assert "| friction_0.25 | 768 | 0.500 | 0.500 | 0.600 |" in card


def test_no_rows_for_the_label_is_a_clear_error_before_the_shipped_one_is_touched(ship, tmp_path, monkeypatch):
    shipped = tmp_path / "policies" / "mine"
    shipped.mkdir(parents=True)
    (shipped / "MODEL_CARD.md").write_text("the one that ships now")
    with pytest.raises(ValueError, match="no rows for policy 'candidate'"):
        _ship(ship, tmp_path, monkeypatch, [_row("other", "nominal", 64, 0.9)])
    assert (shipped / "MODEL_CARD.md").read_text() == "the one that ships now"
