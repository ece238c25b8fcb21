"""Every kind of policy bundle behind one loader: what evaluation, the demo, deploy and the scripts call.

Three kinds of bundle directory exist, each with its own ``config.json``:

    plain      a teacher or a student (rotation.policy.bundle.PolicyBundle)
    adapter    a student with a tactile adapter (adapters.bundle.AdaptedPolicy; ``"kind"`` in its config)
    ensemble   several adapters whose corrections add up (adapters.ensemble.EnsemblePolicy)

The adapters are built on the plain bundle, so the one place that knows all three sits above both packages
(docs/ARCHITECTURE.md). Training, which only ever needs a plain bundle, uses
``rotation.policy.bundle.load_policy_bundle``.

    bundle = load_bundle("adapter")       # a shipped name (rotation/policies/<name>) or a directory
    action = bundle.act(obs)
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from adapters.bundle import AdaptedPolicy, load_adapter
from adapters.bundle_config import CONFIG_FILE, is_adapter_dir
from adapters.bundle_config import WEIGHTS_FILE as ADAPTER_WEIGHTS
from adapters.ensemble import EnsemblePolicy, load_ensemble
from adapters.ensemble_config import ensemble_digest, is_ensemble_dir
from envs.sim_identity import bundle_hand, hand_problem
from rotation.policy.bundle import PolicyBundle, resolve_bundle
from rotation.policy.bundle_config import WEIGHTS_FILE, BundleRefused

AnyPolicy = PolicyBundle | AdaptedPolicy | EnsemblePolicy
"""What :func:`load_bundle` returns; all three act through ``act`` / ``act_batch`` on the same observations."""


def load_bundle(name_or_path: str | Path) -> AnyPolicy:
    """Load a bundle by shipped name (``teacher``, ``student``, ``adapter``) or directory path. An adapter bundle
    loads as an ``AdaptedPolicy``: its student with the tactile adapter, which acts like a PolicyBundle and also
    reads touch; an adapter ensemble as an ``EnsemblePolicy``, which acts the same way."""
    path = resolve_bundle(name_or_path)
    if is_adapter_dir(path):
        return load_adapter(path)
    if is_ensemble_dir(path):
        return load_ensemble(path)
    return PolicyBundle.load(path)


def weights_digest(policy: str | Path) -> str:
    """First 16 hex digits of the SHA-256 of a bundle's weights (a path may hold a retrained policy later); for an
    adapter bundle, of its weights and its config, which holds the digests of its student and encoder; for an
    adapter ensemble, of its config and every member's."""
    path = resolve_bundle(policy)
    if is_ensemble_dir(path):
        return ensemble_digest(path)
    if is_adapter_dir(path):
        data = (path / ADAPTER_WEIGHTS).read_bytes() + (path / CONFIG_FILE).read_bytes()
    else:
        data = (path / WEIGHTS_FILE).read_bytes()
    return hashlib.sha256(data).hexdigest()[:16]


def policy_hand(bundle: AnyPolicy) -> str:
    """The hand variant a policy acts on in simulation: the one its touch needs (a skin adapter: the Xela hand),
    otherwise the one it trained on (envs.sim_identity)."""
    needs = bundle.env_needs if isinstance(bundle, AdaptedPolicy | EnsemblePolicy) else {}
    return str(needs.get("hand", bundle_hand(bundle.config.sim)))


def check_policy_hand(label: str, bundle: AnyPolicy, hand: str) -> None:
    """Refuse (BundleRefused, one line) a policy that cannot act on ``hand``: trained on another hand, or on a
    model of this hand that has changed since."""
    problem = hand_problem(bundle.config.sim, hand)
    if problem is not None:
        raise BundleRefused(f"{label}: {problem}; a policy acts only on the hand it was trained on (retrain it with "
                            f"--hand {hand}, or choose a policy trained there)")
