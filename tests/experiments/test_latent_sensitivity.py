"""experiments/tools/latent_sensitivity.py: how much each dimension of the teacher's z moves under friction and mass."""

from __future__ import annotations

import json

import numpy as np
import torch

from envs.constants import PRIV_FIELDS
from envs.rotate_cup import RotateCupEnv
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig


def test_changes_and_mass_shares_per_dimension(load_script, tmp_path, capsys):
    script = load_script("latent_sensitivity")
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig())
    layers = [m for m in teacher.net.extractor.encoder.mlp if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():  # z[0] = tanh(2 mass), z[1] = tanh(0.5 friction), the others 0 (ELU is the identity on x > 0)
        for layer in layers:
            layer.weight.zero_(), layer.bias.zero_()
        layers[0].weight[0, PRIV_FIELDS.index("mass")] = 2.0
        layers[0].weight[1, PRIV_FIELDS.index("friction")] = 0.5
        for layer in layers[1:]:
            layer.weight[0, 0] = layer.weight[1, 1] = 1.0
    path = teacher.save(tmp_path / "teacher")
    assert script.main(["--teacher", str(path), "--episodes", "6", "--seed", "5"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    share = np.array(result["mass_share"])
    assert share[0] == 1.0 and share[1] == 0.0 and np.all(share[2:] == 0.0)
    assert np.all(np.array(result["friction_change"])[2:] == 0) and result["mass_change"][1] == 0
    # z[0] = tanh(2 m): its change under +0.2 kg, from the same resets the script draws
    env = RotateCupEnv()
    mass = np.array([env.reset(seed=5 + i)[0]["priv"][PRIV_FIELDS.index("mass")] for i in range(6)])
    env.close()
    want = np.mean(np.tanh(2 * (mass + 0.2)) - np.tanh(2 * mass))
    assert abs(result["mass_change"][0] - want) < 1e-3


def test_bad_input_is_one_line(load_script, capsys):
    script = load_script("latent_sensitivity")
    for args, message in ((["--episodes", "0"], "--episodes"), (["--friction-scale", "2"], "--friction-scale"),
                          (["--teacher", "student"], "teacher")):
        assert script.main(args) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
