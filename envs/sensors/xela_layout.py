"""Simulated Xela uSkin on the Allegro hand: the pad layout (numpy only; re-exported by envs.sensors.xela).

Layout (docs/reference/hardware.md section 5, docs/reference/sparsh.md "Sparsh-skin"): 368 taxels on 18 pads, 4 curved
fingertip pads x 30 taxels (a 6 x 6 grid of which 30 are used, 31 x 39 x 29 mm), 11 phalanx pads x 16 (4 x 4,
26 x 24 mm) and 3 palm pads x 24 (4 x 6, 52 x 32 mm); 3 axes per taxel, 16-bit counts around 32768 at rest, 100 Hz.
``PADS`` is the table (the taxel order of every stream and observation is the order of this table, then row-major
inside a pad); ``TAXEL_PAD``, ``TAXEL_TYPE`` and ``taxel_layout()`` give the per-taxel facts the encoder needs.

Which link carries which phalanx pad is not in the reference: we put two pads on each long proximal phalanx (54 mm
holds two 26 mm pads) and one on each medial phalanx of the index, middle and ring fingers, and one on the thumb's
proximal and medial phalanges (3 x 3 + 2 = 11). docs/skin.md shows the result.

Every pad has a *pad frame*: origin at the centre of its outer surface (fingertips: the centre of the dome), x along
the finger toward its tip (palm pads: toward the fingers), z out of the skin on the palmar side, y = z x x. A taxel
reads its local load in its own frame (flat pads: the pad frame; fingertip: x along the meridian toward the apex,
z the surface normal): channel 0 = X shear, 1 = Y shear, 2 = Z normal (pressing raises it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

REST = 32768.0
"""Raw count of an unloaded taxel (16-bit mid-scale, docs/reference/hardware.md section 5)."""
FULL_SCALE = 65535.0
"""Largest raw count (16-bit)."""
VALID_RANGE = (20_000.0, 60_000.0)
"""Raw readings outside this range (16-bit counts, about 32768 at rest) are faults and zeroed
(docs/reference/sparsh.md)."""
SAMPLE_HZ = 100.0
"""Xela sample rate (Hz), = the env's physics rate at the default 10 ms step: one sample per physics step."""
WINDOW = 10
"""Frames of a Sparsh-skin window (0.1 s at 100 Hz, docs/reference/sparsh.md): the length of the `skin` observation."""
AXES = ("x", "y", "z")
"""Channels of a taxel reading: X, Y shear, Z normal."""

TAXEL_TYPES = ("phalanx", "palm", "fingertip")
"""Taxel type names; a taxel's type id is its index here (Sparsh-skin's 3 types: 4x4 pad, 4x6 pad, fingertip)."""

# geometry of the pads (m); sizes from docs/reference/hardware.md section 5
PHALANX_SIZE = (0.026, 0.024)
"""4 x 4 pad: 26 mm along the phalanx x 24 mm across."""
PALM_SIZE = (0.052, 0.032)
"""4 x 6 pad: 52 mm along the palm (toward the fingers, 6 taxels) x 32 mm across (4 taxels)."""
TIP_RADIUS = 0.0145
"""Fingertip shell radius: 29 mm tall (31 mm wide: the model uses one round radius)."""
TIP_LENGTH = 0.039
"""Fingertip shell length along the finger (39 mm), dome included."""
TIP_START = 0.004
"""Where the fingertip shell starts along the distal link (m from the DIP joint); its dome centre is at
TIP_START + TIP_LENGTH - TIP_RADIUS = 28.5 mm, its apex at 43 mm (stock Allegro: 27 mm + a 12 mm tip radius)."""
TIP_PITCH = (0.0056, 0.005)
"""Fingertip taxel pitch: along the meridian (6 rows over the 31.5 mm of palmar surface) and across (5 mm arcs)."""
LINK_RADIUS = 0.0098
"""Radius of the phalanx capsules of the hand model (envs/assets)."""
PAD_THICKNESS = 0.003
"""Thickness of a flat pad (elastomer + board, stand-in); it overlaps the link by 1 mm."""


@dataclass(frozen=True)
class PadSpec:
    """One Xela pad: where it sits on the hand model and its taxel grid."""

    name: str
    kind: str
    """Taxel type, one of TAXEL_TYPES."""
    body: str
    """Body of the hand model (envs/assets) that carries the pad."""
    rows: int
    """Grid rows, along the pad frame's x (proximal to distal)."""
    cols: int
    """Grid columns, along the pad frame's y."""
    taxels: int
    """Taxels used (rows x cols, except on the fingertip: 30 of 36)."""
    size: tuple[float, float]
    """(along x, along y) m; fingertip: (length, width)."""
    pos: tuple[float, float, float]
    """Pad frame origin in the body frame (m)."""
    xaxis: tuple[float, float, float]
    """Pad frame x in the body frame."""
    zaxis: tuple[float, float, float]
    """Pad frame z (out of the skin) in the body frame."""


_FINGER_FRAME = {  # (axis toward the tip, palmar normal) of a finger's links in their body frames (envs/assets)
    "index": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "middle": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "ring": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "thumb": ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0)),
}
_PAD_SURFACE = LINK_RADIUS + PAD_THICKNESS - 0.001
"""Distance of a phalanx pad's outer surface from its link's axis (m)."""


def _on_link(finger: str, link: str, name: str, centre: float) -> PadSpec:
    axis, normal = (np.asarray(v) for v in _FINGER_FRAME[finger])
    pos = axis * centre + normal * _PAD_SURFACE
    return PadSpec(name, "phalanx", f"{finger}_{link}", 4, 4, 16, PHALANX_SIZE, tuple(pos.tolist()),
                   tuple(axis.tolist()), tuple(normal.tolist()))


def _tip(finger: str) -> PadSpec:
    axis, normal = (np.asarray(v) for v in _FINGER_FRAME[finger])
    centre = axis * (TIP_START + TIP_LENGTH - TIP_RADIUS)
    return PadSpec(f"{finger}_tip", "fingertip", f"{finger}_distal", 6, 6, 30, (TIP_LENGTH, 2 * TIP_RADIUS + 0.002),
                   tuple(centre.tolist()), tuple(axis.tolist()), tuple(normal.tolist()))


def _pads() -> tuple[PadSpec, ...]:
    pads: list[PadSpec] = []
    for finger in ("index", "middle", "ring"):
        # proximal 54 mm: two pads side by side; medial 38.4 mm: one pad at its middle
        pads += [_tip(finger), _on_link(finger, "medial", f"{finger}_medial", 0.0192),
                 _on_link(finger, "proximal", f"{finger}_proximal_1", 0.0405),
                 _on_link(finger, "proximal", f"{finger}_proximal_0", 0.0135)]
    pads += [_tip("thumb"), _on_link("thumb", "medial", "thumb_medial", 0.022),
             _on_link("thumb", "proximal", "thumb_proximal", 0.0257)]
    # palm (top face at z = 0, x in [-0.1, 0]): three pads across, one under each finger's column
    for name, y in (("palm_index", -0.036), ("palm_middle", 0.0), ("palm_ring", 0.036)):
        pads.append(PadSpec(name, "palm", "palm", 6, 4, 24, PALM_SIZE, (-0.032, y, PAD_THICKNESS),
                            (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)))
    return tuple(pads)


PADS: tuple[PadSpec, ...] = _pads()
"""The 18 pads in taxel order: per finger (index, middle, ring) tip, medial, proximal_1 (distal), proximal_0; the
thumb's tip, medial, proximal; the palm's three pads. Their bodies and frames are the 'xela' hand's (the older
model); another hand mounts the same pads on its own links (pad_mounts)."""


@dataclass(frozen=True)
class PadMount:
    """Where a pad sits on one hand model: its body, and its frame in that body's frame."""

    body: str
    pos: tuple[float, float, float]
    xaxis: tuple[float, float, float]
    zaxis: tuple[float, float, float]


XELA_HANDS = ("xela", "xela_v4")
"""Hand variants that carry the Xela skin (envs.scene.HANDS)."""
V4_TIP_START = {"finger": TIP_START, "thumb": TIP_START + 0.0423 - 0.0267}
"""Where the fingertip shell starts along the vendor model's last link (m past the last joint): the stock tip it
replaces sits 26.7 mm past a finger's last joint and 42.3 mm past the thumb's (envs.allegro_description), so the
thumb's shell starts that much further out."""
_V4_ALONG, _V4_PALMAR = (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)
"""In every link frame of the vendor's model (and its palm frame) the finger runs along +z and curls toward +x."""
_V4_PALM_FACE = 0.0111
"""The palm's palmar face in its frame (m): the palm box's centre -9.3 mm plus half of its 40.8 mm thickness."""


def _v4_mount(pad: PadSpec) -> PadMount:
    """A pad's mount on the vendor-kinematics hand: the same place along its phalanx as on the older model where the
    link has the same length; the thumb's two pads both on its one long phalanx (after joint 14, 51.4 mm), since
    the vendor's thumb link after joint 13 is 17.7 mm, shorter than a pad."""
    along, palmar = np.asarray(_V4_ALONG), np.asarray(_V4_PALMAR)
    finger, _, link = pad.body.partition("_")
    if pad.kind == "fingertip":
        start = V4_TIP_START["thumb" if finger == "thumb" else "finger"]
        centre = along * (start + TIP_LENGTH - TIP_RADIUS)
        return PadMount(pad.body, tuple(centre.tolist()), _V4_ALONG, _V4_PALMAR)
    if pad.kind == "palm":
        y = {"palm_index": 0.036, "palm_middle": 0.0, "palm_ring": -0.036}[pad.name]  # the index is on +y here
        return PadMount("palm", (_V4_PALM_FACE + PAD_THICKNESS, y, -0.032), _V4_ALONG, _V4_PALMAR)
    if finger == "thumb":
        centre = {"thumb_proximal": 0.0135, "thumb_medial": 0.038}[pad.name]
        body = "thumb_medial"
    else:
        centre = {"medial": 0.0192, "proximal_1": 0.0405, "proximal_0": 0.0135}[pad.name.partition("_")[2]]
        body = pad.body
    pos = along * centre + palmar * _PAD_SURFACE
    return PadMount(body, tuple(pos.tolist()), _V4_ALONG, _V4_PALMAR)


@cache
def pad_mounts(hand: str = "xela") -> tuple[PadMount, ...]:
    """Where each pad of PADS sits on a Xela hand variant (XELA_HANDS), in PADS order."""
    if hand == "xela":
        return tuple(PadMount(p.body, p.pos, p.xaxis, p.zaxis) for p in PADS)
    if hand == "xela_v4":
        return tuple(_v4_mount(p) for p in PADS)
    raise ValueError(f"unknown Xela hand {hand!r}; Xela hands: {', '.join(XELA_HANDS)}")
PAD_NAMES: tuple[str, ...] = tuple(p.name for p in PADS)
PAD_TAXELS: tuple[int, ...] = tuple(p.taxels for p in PADS)
NUM_PADS = len(PADS)
NUM_TAXELS = sum(PAD_TAXELS)
"""368 (docs/reference/hardware.md section 5)."""
TAXEL_PAD = np.repeat(np.arange(NUM_PADS), PAD_TAXELS)
"""(368,) pad index of each taxel."""
TAXEL_TYPE = np.repeat([TAXEL_TYPES.index(p.kind) for p in PADS], PAD_TAXELS)
"""(368,) type id of each taxel (index into TAXEL_TYPES)."""
PAD_SLICES: dict[str, slice] = {p.name: slice(int(a), int(a + p.taxels))
                                for p, a in zip(PADS, np.cumsum([0, *PAD_TAXELS[:-1]]), strict=True)}
"""Pad name -> its taxels' slice in the taxel order."""
assert NUM_TAXELS == 368 and NUM_PADS == 18


def skin_metadata() -> dict:
    """The static taxel facts as JSON-ready data (what sessions store in ``extra["skin"]``)."""
    return {
        "pads": list(PAD_NAMES),
        "pad_kinds": [p.kind for p in PADS],
        "taxels_per_pad": list(PAD_TAXELS),
        "taxel_types": list(TAXEL_TYPES),
        "taxel_type": TAXEL_TYPE.tolist(),
        "axes": list(AXES),
        "rest": REST,
        "sample_hz": SAMPLE_HZ,
    }


def _tip_taxels() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fingertip's 30 taxels in its pad frame: positions (30, 3), frames (30, 3, 3) rows (X, Y, normal), and
    cell areas (30,). The 6 x 6 grid is bent over the shell: rows run along the palmar meridian (arc length s from
    the apex), columns across it in 5 mm arcs; near the apex a parallel circle is too short for six taxels, so the
    rows nearest it keep 4 and 2 (the 6 unused grid places)."""
    r = TIP_RADIUS
    pitch_s, pitch_w = TIP_PITCH
    quarter = math.pi * r / 2  # arc from the apex to where the dome meets the cylinder
    pos, frames = [], []
    for i in range(6):  # row 0: proximal end ... row 5: next to the apex
        s = 0.002 + (5 - i) * pitch_s
        keep = {5: (2, 3), 4: (1, 2, 3, 4)}.get(i, range(6))
        for j in keep:
            w = (j - 2.5) * pitch_w
            if s <= quarter:  # on the dome
                theta = s / r
                rho = r * math.sin(theta)
                phi = w / rho
                normal = np.array([math.cos(theta), math.sin(theta) * math.sin(phi), math.sin(theta) * math.cos(phi)])
                meridian = np.array([math.sin(theta), -math.cos(theta) * math.sin(phi),
                                     -math.cos(theta) * math.cos(phi)])  # toward the apex
            else:  # on the cylinder
                phi = w / r
                normal = np.array([0.0, math.sin(phi), math.cos(phi)])
                meridian = np.array([1.0, 0.0, 0.0])
            p = normal * r
            if s > quarter:
                p[0] = -(s - quarter)
            pos.append(p)
            frames.append(np.stack([meridian, np.cross(normal, meridian), normal]))
    return np.array(pos), np.array(frames), np.full(len(pos), pitch_s * pitch_w)


def _flat_taxels(pad: PadSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    length, width = pad.size
    x = (np.arange(pad.rows) + 0.5) / pad.rows * length - length / 2
    y = (np.arange(pad.cols) + 0.5) / pad.cols * width - width / 2
    xx, yy = np.meshgrid(x, y, indexing="ij")  # row-major: rows along x
    pos = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
    frames = np.broadcast_to(np.eye(3), (len(pos), 3, 3)).copy()
    return pos, frames, np.full(len(pos), length * width / (pad.rows * pad.cols))


@dataclass(frozen=True)
class TaxelLayout:
    """Static per-taxel geometry in the pad frames (taxel order)."""

    pos: np.ndarray
    """(368, 3) taxel positions in their pad's frame (m)."""
    frames: np.ndarray
    """(368, 3, 3) each taxel's reading axes in its pad's frame, rows (X, Y, normal)."""
    area: np.ndarray
    """(368,) skin area a taxel covers (m^2), the share of a spread load it reads."""
    pad_pos: np.ndarray
    """(18, 3) pad frame origins in their bodies' frames (m)."""
    pad_rot: np.ndarray
    """(18, 3, 3) pad frame axes (columns x, y, z) in their bodies' frames."""
    pad_body: tuple[str, ...]
    """The body of the hand model that carries each pad."""


@cache
def taxel_layout(hand: str = "xela") -> TaxelLayout:
    """The taxel layout on a Xela hand variant (XELA_HANDS; computed once per hand): the taxels in their pad
    frames are the same on every hand, the pads' mounts are the hand's (pad_mounts)."""
    tip = _tip_taxels()
    parts = [tip if p.kind == "fingertip" else _flat_taxels(p) for p in PADS]
    mounts = pad_mounts(hand)
    pad_rot = []
    for m in mounts:
        x, z = np.asarray(m.xaxis, float), np.asarray(m.zaxis, float)
        pad_rot.append(np.stack([x, np.cross(z, x), z], axis=1))
    layout = TaxelLayout(np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts]),
                         np.concatenate([q[2] for q in parts]), np.array([m.pos for m in mounts]),
                         np.array(pad_rot), tuple(m.body for m in mounts))
    for a in (layout.pos, layout.frames, layout.area, layout.pad_pos, layout.pad_rot):
        a.setflags(write=False)
    return layout


MAX_PAD_TAXELS = max(PAD_TAXELS)
PAD_TAXEL_INDEX = np.array([np.r_[np.arange(sl.start, sl.stop), np.full(MAX_PAD_TAXELS - (sl.stop - sl.start), -1)]
                            for sl in PAD_SLICES.values()])
"""(18, 30) the taxels of each pad (padded with -1)."""
