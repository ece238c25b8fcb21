"""One-off: the shipped student's actor on edited latents, to see how much any latent can move it.

    python probe_latents.py OUT oracle --friction-scale 0.5     # the teacher's z of a cup read as twice as slippery
    python probe_latents.py OUT oracle --mass-offset 0.1        # ... read as 0.1 kg heavier
    python probe_latents.py OUT oracle --z1-offset -1.0         # the teacher's z with z[1] pushed toward 'slippery'
    python probe_latents.py OUT student --z1-offset -1.0        # the student's own phi, the same push

'oracle' is scripts/oracle_latent.py's bundle (the student's actor on the teacher's z); the friction and mass edits
scale or shift that input of the teacher's env-factor encoder (its first layer; the privileged vector is fed raw),
the z[1] offset is added before the last tanh (of the env-factor encoder, or of phi for 'student'). Each result is
an ordinary policy bundle for `rotate evaluate`. Probes only: they read privileged state or are constant edits.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from envs.constants import PRIV_FIELDS
from rotation.bundles import load_bundle


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("kind", choices=("oracle", "student"))
    ap.add_argument("--friction-scale", type=float, default=1.0)
    ap.add_argument("--mass-offset", type=float, default=0.0)
    ap.add_argument("--z1-offset", type=float, default=0.0)
    a = ap.parse_args()
    if a.kind == "oracle":
        bundle = load_bundle("student").with_teacher_latent(load_bundle("teacher"), card={"role": "probe"})
        first, last = bundle.net.extractor.encoder.mlp[0], bundle.net.extractor.encoder.mlp[-1]
    else:
        if a.friction_scale != 1.0 or a.mass_offset != 0.0:
            raise SystemExit("friction and mass edits need 'oracle' (phi does not read them)")
        bundle = load_bundle("student")
        first, last = None, bundle.net.extractor.adaptation.proj
    with torch.no_grad():
        if first is not None:
            first.bias += first.weight[:, PRIV_FIELDS.index("mass")] * a.mass_offset
            first.weight[:, PRIV_FIELDS.index("friction")] *= a.friction_scale
        last.bias[1] += a.z1_offset
    bundle.save(a.out)
    print(a.out)


if __name__ == "__main__":
    main()
