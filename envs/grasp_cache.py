"""The grasp cache: the file of initial grasps per object scale, its checks, and sampling at reset.

The cache file (.npz) holds `object` (name), `scales` (S,), `grasps` (S, G, 23), `seed`, the `hand` variant and the
`hold` rule it passed; one bucket per randomization scale. A row is 16 joint positions + 7 object pose numbers.
Reset picks the bucket of the env's scale and a row uniformly. envs.grasps generates caches.
"""

from __future__ import annotations

import hashlib
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs import constants as C
from envs.constants import DEFAULT_HAND
from envs.objects import OBJECTS
from envs.scene import HANDS, hand_variant
from envs.task import pick_grasps

GRASP_DIM = C.NUM_JOINTS + 7
"""A cached row: 16 joint positions + the object's position (3) and quaternion (4)."""


@dataclass
class GraspCache:
    """Cached grasps per object scale bucket."""

    object: str
    scales: np.ndarray
    """(S,) bucket scales."""
    grasps: np.ndarray
    """(S, G, 23): 16 joint positions (rad, bus order) + object position (3, m) and quaternion (4, wxyz)."""
    seed: int = 0
    source: str = ""
    """Where the cache was read from (named in error messages); empty for a cache built in memory."""
    hand: str = DEFAULT_HAND
    """Hand variant the grasps were generated with (envs.scene.HANDS); caches of older versions are 'digit360'."""
    hold: tuple[float, ...] = ()
    """The HoldRule every grasp passed (seconds, friction, mass, max_tilt), or () for a cache generated without one."""

    def __post_init__(self) -> None:
        where = self.where
        self.hold = tuple(float(x) for x in self.hold)
        self.scales = np.asarray(self.scales, dtype=np.float64)
        self.grasps = np.asarray(self.grasps, dtype=np.float64)
        if self.scales.ndim != 1 or not np.all(np.isfinite(self.scales) & (self.scales >= 0.1) & (self.scales <= 3.0)):
            raise ValueError(f"{where}: scales must be finite numbers in [0.1, 3.0] (one per bucket), got "
                             f"{self.scales.tolist()}")
        if self.grasps.ndim != 3 or self.grasps.shape[2] != GRASP_DIM or self.grasps.shape[0] != len(self.scales):
            raise ValueError(
                f"{where}: grasps must have shape (S={len(self.scales)}, G, {GRASP_DIM}), got {self.grasps.shape}"
            )
        if self.grasps.shape[1] == 0:
            raise ValueError(f"{where} is empty")
        _check_rows(self.grasps, self.scales, where, self.hand)

    @property
    def where(self) -> str:
        return f"grasp cache {self.source}" if self.source else f"grasp cache for {self.object!r}"

    def sample(self, bucket: np.ndarray, scale: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows for envs with the given scales; ``u`` in [0, 1) picks the row. Returns q (k, 16), pose (k, 7)."""
        return pick_grasps(np, self.scales, self.grasps, np.asarray(scale), np.asarray(u))  # envs.task

    def save(self, path: str | Path) -> None:
        """Write the cache to exactly ``path`` (through a file object: numpy would append '.npz' to a name), via a
        temporary file renamed into place: a write that fails (a full disk) leaves no file behind, and an earlier
        cache at ``path`` as it was."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".tmp_{path.name}")
        try:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, object=self.object, scales=self.scales, grasps=self.grasps.astype(np.float32),
                                    seed=self.seed, hand=self.hand, hold=np.asarray(self.hold, dtype=np.float64))
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path) -> GraspCache:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"grasp cache {path} does not exist (generate one with `rotate grasps`)")
        damaged = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)  # what numpy / zipfile raise
        try:
            f = np.load(path, allow_pickle=False)
        except damaged as err:
            raise ValueError(f"grasp cache {path} is not a readable .npz file ({type(err).__name__}: {err}); "
                             f"regenerate it with `rotate grasps`") from err
        if not isinstance(f, np.lib.npyio.NpzFile):
            raise ValueError(f"grasp cache {path} is a single .npy array, not an .npz grasp cache; "
                             f"regenerate it with `rotate grasps`")
        with f:
            missing = {"object", "scales", "grasps"} - set(f.files)
            if missing:
                raise ValueError(f"grasp cache {path} is missing {sorted(missing)}")
            try:  # members are read (decompressed, CRC-checked) here
                name, scales, grasps = str(f["object"]), f["scales"], f["grasps"]
                seed = int(f["seed"]) if "seed" in f.files else 0
                hand = str(f["hand"]) if "hand" in f.files else "digit360"
                hold = tuple(float(x) for x in f["hold"]) if "hold" in f.files else ()
            except damaged as err:
                raise ValueError(f"grasp cache {path} is corrupted ({type(err).__name__}: {err}); "
                                 f"regenerate it with `rotate grasps`") from err
        if name not in OBJECTS:
            raise ValueError(f"grasp cache {path}: unknown object {name!r}; known objects: "
                             f"{', '.join(sorted(OBJECTS))}")
        if hand not in HANDS:
            raise ValueError(f"grasp cache {path}: unknown hand {hand!r}; hands: {', '.join(HANDS)}")
        if hold and (len(hold) not in (4, 5) or not all(math.isfinite(x) for x in hold)):
            raise ValueError(f"grasp cache {path}: 'hold' must be 4 or 5 finite numbers (seconds, friction, mass, "
                             f"max_tilt[, surface]), got {list(hold)}; regenerate it with `rotate grasps`")
        return cls(name, scales, grasps, seed, source=str(path), hand=hand, hold=hold)


JOINT_TOLERANCE = 0.02
"""How far (rad) a cached joint may lie outside its limit: the PD settles a few mrad past it (the shipped caches:
at most 7.5 mrad)."""
QUAT_TOLERANCE = 1e-4
"""How far a cached quaternion's norm may be from 1 (rows are stored as float32: about 3e-8)."""
MAX_OBJECT_OFFSET = 0.10
"""How far (m) a cached object centre may be from the hand's object start (envs.scene.VARIANTS), where grasps
are generated: Hora's rule keeps every
fingertip within 10 cm of it (the shipped caches: at most 5 cm)."""


def _check_rows(grasps: np.ndarray, scales: np.ndarray, where: str, hand: str = DEFAULT_HAND) -> None:
    """Every row is finite, its joints within the limits, its quaternion a unit one, its object in the hand."""

    def fail(mask: np.ndarray, what: str) -> None:
        b, g = (int(i) for i in np.argwhere(mask)[0][:2])
        raise ValueError(f"{where}: bucket {b} (scale {scales[b]:g}), row {g}: {what(b, g)}; "
                         f"{int(mask.sum())} row(s) like it. Regenerate the cache with `rotate grasps`")

    finite = np.all(np.isfinite(grasps), axis=2)
    if not finite.all():
        fail(~finite, lambda b, g: f"non-finite values {grasps[b, g].tolist()}")
    q = grasps[..., : C.NUM_JOINTS]
    outside = (q < C.JOINT_LOWER - JOINT_TOLERANCE) | (q > C.JOINT_UPPER + JOINT_TOLERANCE)  # (S, G, 16)
    if outside.any():
        def joint(b: int, g: int) -> str:
            j = int(np.flatnonzero(outside[b, g])[0])
            return (f"joint {j} ({C.JOINT_NAMES[j]}) = {q[b, g, j]:.4f} rad is outside its limits "
                    f"[{C.JOINT_LOWER[j]}, {C.JOINT_UPPER[j]}] (+-{JOINT_TOLERANCE})")
        fail(outside.any(axis=2), joint)
    norm = np.linalg.norm(grasps[..., C.NUM_JOINTS + 3 :], axis=2)
    bad = np.abs(norm - 1.0) > QUAT_TOLERANCE
    if bad.any():
        fail(bad, lambda b, g: f"the object quaternion has norm {norm[b, g]:.6f}, not 1 (+-{QUAT_TOLERANCE})")
    start = hand_variant(hand).object_start
    offset = np.linalg.norm(grasps[..., C.NUM_JOINTS : C.NUM_JOINTS + 3] - start, axis=2)
    far = offset > MAX_OBJECT_OFFSET
    if far.any():
        fail(far, lambda b, g: f"the object centre {grasps[b, g, 16:19].tolist()} m is {offset[b, g]:.3f} m from "
                               f"the hand's grasp point {start.tolist()} (at most {MAX_OBJECT_OFFSET} m)")


def default_cache_path(object_name: str, hand: str = DEFAULT_HAND) -> Path:
    """The shipped cache of an object: grasps_<object>.npz for the Digit 360 hand, grasps_<object>_<hand>.npz for
    another hand variant."""
    suffix = "" if hand == "digit360" else f"_{hand}"
    return Path(__file__).resolve().parent / "assets" / f"grasps_{object_name}{suffix}.npz"


def _shipped_objects(folder: Path, hand: str) -> list[str]:
    """Objects with a shipped cache for ``hand`` (file names as in default_cache_path)."""
    names = [p.stem.removeprefix("grasps_") for p in folder.glob("grasps_*.npz")]
    if hand == "digit360":
        tags = tuple(f"_{h}" for h in HANDS if h != "digit360")
        return sorted(n for n in names if not n.endswith(tags))
    return sorted(n.removesuffix(f"_{hand}") for n in names if n.endswith(f"_{hand}"))


def load_default_cache(object_name: str, path: str = "", hand: str = DEFAULT_HAND) -> GraspCache:
    """The cache at ``path``, or the one shipped for ``object_name`` and ``hand``; errors name the object and the
    fix."""
    if path:
        cache = GraspCache.load(path)
    else:
        shipped = default_cache_path(object_name, hand)
        if not shipped.is_file():
            have = _shipped_objects(shipped.parent, hand)
            flag, on = ("", "") if hand == "digit360" else (f" --hand {hand}", f" on the {hand} hand")
            raise ValueError(
                f"no grasp cache ships for object {object_name!r}{on} (shipped: {', '.join(have) or 'none'}); "
                f"generate one with `rotate grasps --objects {object_name}{flag} --out DIR` and pass "
                f"grasp_cache=DIR/{default_cache_path(object_name, hand).name}"
            )
        cache = GraspCache.load(shipped)
    if cache.object != object_name:
        raise ValueError(f"grasp cache was generated for {cache.object!r}, not for {object_name!r}")
    if cache.hand != hand:
        raise ValueError(f"{cache.where} was generated for the {cache.hand} hand, not for the {hand} hand; "
                         f"generate one with `rotate grasps --hand {hand}`")
    return cache


def cache_digest(path: str | Path, object_name: str, hand: str = DEFAULT_HAND) -> str:
    """First 16 hex digits of the SHA-256 of the grasp cache episodes start from: the file at ``path``, or the one
    shipped for the object and hand when ``path`` is empty (a regenerated cache changes every episode's start);
    ``"(none)"`` when there is no such file."""
    file = Path(path) if path else default_cache_path(object_name, hand)
    return hashlib.sha256(file.read_bytes()).hexdigest()[:16] if file.is_file() else "(none)"
