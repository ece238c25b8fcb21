"""Put tactile adapters of one student together as an ensemble (`rotate ensemble-adapters`): their corrections are
added with fixed weights (adapters.ensemble describes the bundle and how it acts).

    z_hat = phi(history) + sum_k w_k * c_k(touch)         (w_k a number, or one number per dimension of z)

Put one together (each member is checked; by default copied into the new bundle, so it stands alone and a member
retrained later in place does not change it)::

    rotate ensemble-adapters --members adapter runs/adapter_ip --out runs/ensemble        # weights 1/2 and 1/2
    rotate ensemble-adapters --members adapter runs/adapter_ip --weights 0.7 0.3 --out runs/ensemble_73
    rotate evaluate --policy adapter --policy ensemble=runs/ensemble --suite perturbations

Weights can also be per dimension of the latent (``--dim-weights``, K x Z numbers): member k's correction of
dimension d is weighted ``w_k * dim_weights_k[d]``, so each member can correct the directions of z it knows best
(``experiments/tools/latent_sensitivity.py`` shows which dimensions friction and mass move).

A gate can make some dimensions' correction conditional on what the rest of the correction says (``--gate-dims``,
``--gate-signal``, ``--gate-width``; :class:`CorrectionGate`). With c the weighted sum above, the gate reads
``g = clip(signal . c / width, 0, 1)`` and multiplies the correction of the gated dimensions by g. For example, z[1]
(the direction the teacher's encoder moves for grippy cups) can be corrected only as far as the ensemble's own z[3]
and z[4] corrections read the cup as slippery (experiments/adapter/gated_z1)::

    rotate ensemble-adapters --members adapter runs/adapter_ip --gate-dims 1 --gate-signal 0 0 0 -1 -1 0 0 0 \
        --gate-width 0.2 --out runs/gated

``--touch-smoothing a`` averages the corrections over refreshes (adapters.touch_delay.smooth): each refresh keeps
a share a of the held correction, so the ensemble reads an episode's friction and mass from many touch windows
rather than from the newest alone.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

from adapters.bundle_config import read_adapter
from adapters.ensemble import load_ensemble
from adapters.ensemble_config import (
    CONFIG_FILE,
    KIND,
    MAX_WEIGHT,
    CorrectionGate,
    EnsembleConfig,
    EnsembleMember,
    check_dim_weights,
    check_gate_width,
    config_path,
)
from adapters.touch_delay import check_smoothing
from envs.errors import RequestRefused
from envs.validation import check_int, check_output_dir, check_types
from rotation.configs import to_jsonable


@dataclass
class Config:
    members: tuple[str, ...] = ()
    """Adapter bundles to combine (shipped names or directories), all for the same student and the same sensors."""
    weights: tuple[float, ...] = ()
    """One weight per member (default 1/K each: the mean of the K corrections)."""
    dim_weights: tuple[float, ...] = ()
    """Per-latent-dimension factors on top of --weights: K x Z numbers, the first member's Z factors first (e.g. for
    two members and an 8-dimensional z, 16 numbers); empty: every dimension alike."""
    touch_every: int = 0
    """Control steps between touch refreshes (0: the first member's)."""
    touch_smoothing: float = 0.0
    """How much of the held correction each refresh keeps, in [0, 1): the correction after a refresh is
    a * held + (1 - a) * new, the episode's first taken as it is (0: each refresh replaces it). Friction and mass
    stay put while one touch window reads them poorly, so averaging over refreshes can read them better; the time
    constant is touch_every / (1 - a) control steps."""
    gate_dims: tuple[int, ...] = ()
    """Latent dimensions whose correction is gated (empty: no gate); see --gate-signal and --gate-width."""
    gate_signal: tuple[float, ...] = ()
    """With --gate-dims: Z coefficients; the gate is clip(signal . correction / width, 0, 1) and scales the gated
    dimensions' correction (e.g. 0 0 0 -1 -1 0 0 0: open as far as z[3] and z[4] are corrected downwards)."""
    gate_width: float = 0.2
    """With --gate-dims: the signal that opens the gate fully."""
    copy: bool = True
    """Copy the members into OUT/members/ (the bundle stands alone); --no-copy references them where they are."""
    out: Path = Path("runs/ensemble")
    """The ensemble bundle's directory (refused if it already holds a bundle)."""

    def __post_init__(self) -> None:
        check_types(self)
        if not self.members:
            raise ValueError("--members: name at least one adapter bundle")
        if self.weights and len(self.weights) != len(self.members):
            raise ValueError(f"--weights: {len(self.weights)} weights for {len(self.members)} members")
        if any(not (math.isfinite(w) and 0 < w <= MAX_WEIGHT) for w in self.weights):
            raise ValueError(f"--weights must be in (0, {MAX_WEIGHT:g}], got {list(self.weights)}")
        if len(self.dim_weights) % len(self.members):
            raise ValueError(f"--dim-weights: {len(self.dim_weights)} numbers is not the same count for each of the "
                             f"{len(self.members)} members (K x Z numbers, the first member's first)")
        for k, part in enumerate(self.split_dim_weights()):
            check_dim_weights(part, f"--dim-weights of member {k + 1} ({self.members[k]})")
        check_int("touch_every", self.touch_every, 0, 10_000, unit="control steps")
        check_smoothing(self.touch_smoothing)
        check_gate_width(self.gate_width, ValueError, "--gate-width")
        if bool(self.gate_dims) != bool(self.gate_signal):
            raise ValueError("--gate-dims and --gate-signal go together (give both or neither)")
        if self.gate_dims:
            self.gate().check(len(self.gate_signal), ValueError, "--gate-")
        check_output_dir("out", self.out)

    def gate(self) -> CorrectionGate | None:
        """The gate these options describe (None without --gate-dims)."""
        if not self.gate_dims:
            return None
        return CorrectionGate(tuple(self.gate_dims), tuple(float(v) for v in self.gate_signal), float(self.gate_width))

    def split_dim_weights(self) -> list[tuple[float, ...]]:
        """--dim-weights cut into each member's factors (empty tuples when not given)."""
        if not self.dim_weights:
            return [() for _ in self.members]
        z = len(self.dim_weights) // len(self.members)
        return [tuple(float(v) for v in self.dim_weights[k * z:(k + 1) * z]) for k in range(len(self.members))]


def run(cfg: Config) -> Path:
    """Write the ensemble bundle in ``cfg.out`` and load it once (every member checked); returns its directory."""
    if (cfg.out / CONFIG_FILE).exists():
        raise RequestRefused(f"{cfg.out} already holds a bundle; choose another --out (nothing is overwritten)")
    dirs = [read_adapter(ref)[0] for ref in cfg.members]  # adapter bundles (an ensemble is not a member)
    weights = cfg.weights or tuple(1.0 / len(dirs) for _ in dirs)
    if cfg.copy:
        names: list[str] = []
        for d in dirs:
            name = d.resolve().name
            while f"members/{name}" in names:
                name += "_"
            names.append(f"members/{name}")
    else:
        names = [str(d.resolve()) for d in dirs]
    touch_every = cfg.touch_every or read_adapter(dirs[0])[1].touch_every
    ens = EnsembleConfig(members=tuple(EnsembleMember(n, float(w), d) for n, w, d in
                                       zip(names, weights, cfg.split_dim_weights(), strict=True)),
                         touch_every=touch_every, touch_smoothing=float(cfg.touch_smoothing), gate=cfg.gate(),
                         card={"kind": KIND, "made_by": "rotate ensemble-adapters",
                               "members": {n: str(r) for n, r in zip(names, cfg.members, strict=True)},
                               # the touch delay each member trained with (older members' cards lack it: none)
                               "member_touch_delays": {n: read_adapter(d)[1].card.get("touch_delay", "none recorded")
                                                       for n, d in zip(names, dirs, strict=True)}})
    cfg.out.mkdir(parents=True, exist_ok=True)
    try:
        if cfg.copy:
            for d, n in zip(dirs, names, strict=True):
                shutil.copytree(d, cfg.out / n)
        config_path(cfg.out).write_text(json.dumps(to_jsonable(ens), indent=2) + "\n")
        policy = load_ensemble(cfg.out)
    except BaseException:
        shutil.rmtree(cfg.out / "members", ignore_errors=True)
        config_path(cfg.out).unlink(missing_ok=True)
        raise
    print(f"adapter ensemble in {cfg.out}: {len(dirs)} members "
          + ", ".join(f"{r} x {w:g}" + (f" x [{', '.join(f'{v:g}' for v in d)}]" if d else "")
                      for r, w, d in zip(cfg.members, weights, cfg.split_dim_weights(), strict=True))
          + (f"; gate on z{list(ens.gate.dims)} by {list(ens.gate.signal)} / {ens.gate.width:g}" if ens.gate else "")
          + f"; touch every {touch_every} steps"
          + (f", smoothed by {cfg.touch_smoothing:g}" if cfg.touch_smoothing else "")
          + f"; windows {', '.join(policy.windows)}")
    return cfg.out
