"""experiments/tools/oracle_latent.py: the student's actor on the teacher's z, saved as a bundle evaluate can load."""

from __future__ import annotations

import pytest
import torch

from rotation.bundles import load_bundle
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig


@pytest.fixture(scope="module")
def oracle_script(load_script):
    return load_script("oracle_latent")


def test_writes_the_oracle_bundle_and_keeps_an_existing_one(oracle_script, tmp_path, capsys):
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig())
    student = teacher.to_student()
    with torch.no_grad():
        for p in student.net.actor.parameters():  # the student's actor moved away from the teacher's
            p.add_(0.1 * torch.randn_like(p))
    args = ["--student", str(student.save(tmp_path / "student")), "--teacher", str(teacher.save(tmp_path / "teacher")),
            "--out", str(tmp_path / "oracle")]
    assert oracle_script.main(args) == 0
    oracle = load_bundle(tmp_path / "oracle")
    assert oracle.config.latent_source == "privileged" and oracle.config.card["role"] == "oracle-latent student"
    for mine, want in zip(oracle.net.actor.parameters(), student.net.actor.parameters(), strict=True):
        torch.testing.assert_close(mine, want)
    before = (tmp_path / "oracle" / "model.safetensors").read_bytes()
    assert oracle_script.main(args) == 2
    assert "already holds a bundle" in capsys.readouterr().err
    assert (tmp_path / "oracle" / "model.safetensors").read_bytes() == before
