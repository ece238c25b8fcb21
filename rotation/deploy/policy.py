"""The policy side of deploy: the env's observation/target bookkeeping for one hand, and a deadline-bounded worker.

:class:`PolicyState` is what ``envs.core.RotateCupVec`` does for N = 1, with the same code
(:class:`envs.observation.ProprioHistory`) and nothing added:

- start: the history is filled with the start pose (measured q as both position and target), targets = q0;
- each step: ``targets = clip(targets + clip(action, -1, 1) * action_scale, lower, upper)``, then, one control
  period later, a frame of (measured q scaled to [-1, 1], targets in rad) is pushed.

No observation noise is added (the env adds it only as a training-time randomization) and no filtering is done.
All joint vectors are (16,) in the Allegro bus order, radians, Allegro frame (the drivers map LEAP at the
hardware boundary).

:class:`PolicyWorker` runs ``bundle.act`` on its own thread, so a slow or hung policy can never block the control
loop: the loop waits for an action only until a deadline and holds the last safe target otherwise. (A tactile
adapter's touch correction is computed on another thread, rotation.deploy.touch, and handed in with the request.)
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from envs import constants as C
from envs.observation import ProprioHistory
from rotation.policy.bundle_config import BundleConfig

log = logging.getLogger(__name__)

DEPLOYABLE_GROUPS: dict[str, tuple[int, ...]] = {
    "proprio": (C.PROPRIO_STEPS, C.PROPRIO_DIM),
    "proprio_hist": (C.HISTORY_STEPS, C.PROPRIO_DIM),
}
"""Observation groups a hand can provide (name -> shape): only proprioception. ``priv`` (object pose, mass,
friction) exists only in simulation, so a teacher bundle cannot be deployed."""


class PolicyFault(RuntimeError):
    """The policy could not produce usable actions (it raised, stalled or returned non-finite values too long)."""


def check_deployable(config: BundleConfig, name: str, reads_touch: bool = False) -> None:
    """ValueError unless the bundle reads only groups a hand provides, with the shapes ProprioHistory builds.

    ``reads_touch``: the policy is a tactile adapter bundle (its touch comes from the Digit 360 readers, not from
    the observation: rotation.deploy.touch); a config that references an adapter must be one."""
    unknown = sorted(set(config.obs_groups) - set(DEPLOYABLE_GROUPS))
    if unknown:
        hint = (" ('priv' is privileged simulator state: deploy the student bundle, which estimates it from the "
                "joint history)" if "priv" in unknown else "")
        raise ValueError(f"policy {name!r} reads observation group(s) {unknown} that a hand cannot provide; deploy "
                         f"provides {sorted(DEPLOYABLE_GROUPS)}{hint}")
    for key, shape in config.obs_groups.items():
        if tuple(shape) != DEPLOYABLE_GROUPS[key]:
            raise ValueError(f"policy {name!r} expects group {key!r} of shape {tuple(shape)}, but the env's "
                             f"observation builder makes {DEPLOYABLE_GROUPS[key]}")
    if config.action_dim != C.NUM_JOINTS:
        raise ValueError(f"policy {name!r} has {config.action_dim} actions; a hand has {C.NUM_JOINTS} joints")
    if config.adapter and not reads_touch:
        raise ValueError(f"policy {name!r} references the tactile adapter {config.adapter!r} but loads without it; "
                         "deploy the adapter bundle itself (--policy ADAPTER_DIR), which names its student")


class PolicyState:
    """Joint targets and the proprioceptive history of one deployed policy (see the module docstring).

    ``q0``: the measured start pose (16,) rad; ``lower``/``upper``: the target limits (16,) rad and
    ``action_scale`` (rad per unit action), both from the bundle config (= the env's).
    """

    def __init__(self, q0: np.ndarray, lower: np.ndarray, upper: np.ndarray, action_scale: float) -> None:
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape != (C.NUM_JOINTS,) or not np.all(np.isfinite(q0)):
            raise ValueError(f"start pose must be {C.NUM_JOINTS} finite joint angles, got {q0}")
        self.lower = np.asarray(lower, dtype=np.float64)
        self.upper = np.asarray(upper, dtype=np.float64)
        self.action_scale = float(action_scale)
        self.history = ProprioHistory(1)
        self.history.reset(np.array([0]), q0[None])  # as the env at reset: (q0, q0) in every frame
        # as the env at reset: the targets start at the start pose, also where it sits a hair outside the limits (a
        # cached grasp is a settled pose, up to ~9 mrad past a joint's soft limit; a measured pose likewise); the
        # first action clips them as the env's does, and the driver's safety layer clamps whatever it sends
        self.targets = q0.copy()

    def observation(self) -> dict[str, np.ndarray]:
        """The groups the env returns: ``proprio`` (3, 32) and ``proprio_hist`` (30, 32), float32, newest last."""
        return {"proprio": self.history.proprio[0], "proprio_hist": self.history.history[0]}

    def apply(self, action: np.ndarray) -> np.ndarray:
        """Integrate one finite action (16,) in [-1, 1] into the targets as the env does; returns the new targets."""
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.targets = np.clip(self.targets + a * self.action_scale, self.lower, self.upper)
        return self.targets.copy()

    def push(self, q: np.ndarray) -> None:
        """Append the frame of one control step: measured q (16,) rad after the step, with the current targets."""
        self.history.push(np.asarray(q, dtype=np.float64)[None], self.targets[None])


REAL_ALLEGRO_MODEL = "digit360_v4"
"""The simulated hand built from the vendor's Allegro kinematics (envs.hand_model): the only one whose policies
a real Allegro runs."""


def deploy_sim_hand(hand: str, bundle: Any, name: str, allow_mismatch: bool = False) -> str:
    """The simulated hand variant ``bundle`` acts on, checked against the hand ``rotate deploy --hand`` names.

    A real LEAP hand runs no policy yet: every policy here trained on an Allegro model, and the LEAP's kinematics
    are not the Allegro's (an angle offset does not make one the other). A real Allegro runs only policies of the
    vendor-kinematics model; the older 'digit360' / 'xela' model puts the thumb and the finger roll joints
    elsewhere (its cup grasps open by 26-50 mm on the real kinematics: experiments/hand_v4). The emulated hands
    simulate the policy's own model. Raises BundleRefused (one line); ``allow_mismatch`` (deploy's
    --allow-model-mismatch) lets a real hand run a policy of another model."""
    from rotation.bundles import check_policy_hand, policy_hand
    from rotation.policy.bundle_config import BundleRefused

    trained = policy_hand(bundle)
    check_policy_hand(f"--policy {name}", bundle, trained)  # its own model has not changed since
    if allow_mismatch:
        return trained
    if hand == "leap":
        raise BundleRefused(f"--policy {name}: it was trained on the {trained} hand (an Allegro model); a real LEAP "
                            "hand needs a policy trained on a LEAP model, which this stack does not have yet "
                            "(--hand sim-leap rehearses the LEAP bus with an Allegro body; --allow-model-mismatch runs "
                            "it anyway)")
    if hand == "allegro" and trained != REAL_ALLEGRO_MODEL:
        raise BundleRefused(f"--policy {name}: it was trained on the {trained} hand model, whose kinematics are not "
                            f"the real Allegro's (its grasps open by 26-50 mm there); deploy a policy trained with "
                            f"--hand {REAL_ALLEGRO_MODEL}, rehearse with --hand sim-allegro, or run it anyway with "
                            "--allow-model-mismatch")
    return trained


def action_problem(action: object) -> str | None:
    """Why ``action`` cannot be used (wrong shape, NaN/inf), or None if it is a usable (16,) action."""
    a = np.asarray(action)
    if a.shape != (C.NUM_JOINTS,):
        return f"shape {a.shape}, expected ({C.NUM_JOINTS},)"
    if not np.issubdtype(a.dtype, np.number):
        return f"dtype {a.dtype}"
    bad = np.flatnonzero(~np.isfinite(a.astype(np.float64)))
    if bad.size:
        return f"non-finite values at joints {bad.tolist()}"
    return None


class PolicyWorker:
    """Computes ``act(request)`` on a daemon thread; the caller waits for each result only until a deadline.

    ``request`` is whatever the caller's ``act`` takes: an observation dict, or (observation, touch correction) in
    the control loop.

    One request at a time: :meth:`submit` refuses a new observation while the previous one is still being
    computed. A result that arrives after its deadline is dropped (it was computed for an old observation).
    An exception raised by ``act`` is handed to the caller of :meth:`wait`.
    """

    def __init__(self, act: Callable[[Any], np.ndarray], name: str = "policy") -> None:
        self._act = act
        self._cv = threading.Condition()
        self._request: tuple[int, Any] | None = None
        self._result: tuple[int, np.ndarray | None, BaseException | None] | None = None
        self._busy = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=f"{name}-worker", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        with self._cv:
            return self._busy

    def submit(self, seq: int, obs: Any) -> bool:
        """Queue request (observation) number ``seq``; False (nothing queued) while the previous one is still
        running."""
        with self._cv:
            if self._busy or self._stop:
                return False
            self._request, self._busy = (seq, obs), True
            self._cv.notify_all()
            return True

    def wait(self, seq: int, timeout: float) -> np.ndarray | None:
        """The action for request ``seq``, or None if it is not ready within ``timeout`` s; re-raises its error."""
        with self._cv:
            ready = self._cv.wait_for(lambda: self._result is not None and self._result[0] == seq,
                                      timeout=max(timeout, 0.0))
            if not ready:
                return None
            _, action, error = self._result  # type: ignore[misc]
            self._result = None
        if error is not None:
            raise PolicyFault(f"the policy raised {type(error).__name__}: {error}") from error
        return action

    def warm_up(self, obs: Any, timeout_s: float = 10.0) -> float:
        """Run one inference on the worker thread and wait for it; returns its duration (s).

        The first call allocates buffers and loads kernels, which can take many control periods; doing it before
        the control clock starts keeps that out of the loop. Raises PolicyFault if it does not finish in time.
        """
        start = time.monotonic()
        if not self.submit(-1, obs) or self.wait(-1, timeout_s) is None:
            raise PolicyFault(f"the policy's first inference did not finish within {timeout_s:.0f} s")
        return time.monotonic() - start

    def close(self, join_timeout_s: float = 0.5) -> None:
        """Stop the thread, waiting at most ``join_timeout_s`` (a running request is finished first; a hung one
        is left behind: the thread is a daemon)."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if join_timeout_s > 0:
            self._thread.join(timeout=join_timeout_s)
            if self._thread.is_alive():
                log.warning("policy worker still busy at shutdown; leaving it behind (daemon thread)")

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._request is not None or self._stop)
                if self._stop:
                    return
                seq, obs = self._request  # type: ignore[misc]
                self._request = None
            action: np.ndarray | None = None
            error: BaseException | None = None
            try:
                action = self._act(obs)
            except Exception as err:  # handed to the control loop, which ends the run with motors off
                error = err
            with self._cv:
                self._result = (seq, action, error)
                self._busy = False
                self._cv.notify_all()
