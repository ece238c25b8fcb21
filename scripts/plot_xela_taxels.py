"""Plot the simulated Xela skin's 368 taxels on the hand (docs/images/xela_taxels.png) from the model's kinematics.

Three panels: the hand curled around the grasp pose (3-D, taxels coloured by type, the links as a skeleton), the
flat hand seen from above with every pad named, and one fingertip pad's 30 taxels in its pad frame with their
normals (the 6 x 6 grid bent over the dome).

    python scripts/plot_xela_taxels.py                                   # runs/xela_taxels.png
    python scripts/plot_xela_taxels.py --out docs/images/xela_taxels.png # the picture in docs/skin.md
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs import constants as C  # noqa: E402
from envs.scene import (
    CANONICAL_POSE,  # noqa: E402
    hand_spec,  # noqa: E402
)
from envs.sensors import xela as X  # noqa: E402
from envs.validation import check_output_file  # noqa: E402
from rotation.configs import script_main  # noqa: E402

COLORS = {"phalanx": "tab:blue", "palm": "tab:green", "fingertip": "tab:red"}


@dataclass
class Config:
    out: Path = Path("runs/xela_taxels.png")
    """Output PNG."""
    dpi: int = 110
    """Resolution of the PNG."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.out.suffix.lower() != ".png":  # matplotlib would add ".png" to a bare name and the message would lie
            raise ValueError(f"out must end in .png, got {self.out}")
        check_output_file("out", self.out)
        if not 20 <= self.dpi <= 600:
            raise ValueError(f"dpi must be in [20, 600], got {self.dpi}")


def taxels_at(model: mujoco.MjModel, q: np.ndarray) -> tuple[np.ndarray, mujoco.MjData]:
    """(368, 3) taxel positions (m, hand frame) with the joints at ``q``."""
    data = mujoco.MjData(model)
    data.qpos[:16] = q
    mujoco.mj_kinematics(model, data)
    lay = X.taxel_layout()
    out = np.zeros((X.NUM_TAXELS, 3))
    for pad in X.PADS:
        site = data.site(f"xela_{pad.name}")
        out[X.PAD_SLICES[pad.name]] = site.xpos + lay.pos[X.PAD_SLICES[pad.name]] @ site.xmat.reshape(3, 3).T
    return out, data


def _skeleton(ax, model: mujoco.MjModel, data: mujoco.MjData, dims: tuple[int, ...]) -> None:
    for finger in C.FINGERS:
        chain = [data.body(f"{finger}_{link}").xpos for link in ("base", "proximal", "medial", "distal")]
        chain.append(data.site(f"{finger}_tip").xpos)
        pts = np.array(chain)
        ax.plot(*(pts[:, d] for d in dims), color="0.55", lw=3, alpha=0.6, zorder=1)
    palm = np.array([[-0.1, -0.055, 0], [0, -0.055, 0], [0, 0.055, 0], [-0.1, 0.055, 0], [-0.1, -0.055, 0]])
    ax.plot(*(palm[:, d] for d in dims), color="0.4", lw=1)


def _scatter(ax, pos: np.ndarray, dims: tuple[int, ...], size: float) -> None:
    for k, kind in enumerate(X.TAXEL_TYPES):
        sel = X.TAXEL_TYPE == k
        count = int(sel.sum())
        ax.scatter(*(pos[sel, d] for d in dims), s=size, color=COLORS[kind], label=f"{kind} ({count})", zorder=3)


def run(cfg: Config) -> Path:
    model = hand_spec("xela").compile()
    fig = plt.figure(figsize=(16.5, 5.6))

    ax = fig.add_subplot(1, 3, 1, projection="3d")
    pos, data = taxels_at(model, CANONICAL_POSE)
    _skeleton(ax, model, data, (0, 1, 2))
    _scatter(ax, pos, (0, 1, 2), 6)
    ax.set(xlabel="x (m)", ylabel="y (m)", zlabel="z (m)", title="368 taxels at the grasp pose (hand frame)")
    ax.set_box_aspect(np.ptp(pos, axis=0))
    ax.view_init(elev=28, azim=-125)
    ax.legend(loc="upper left", fontsize=8)

    ax = fig.add_subplot(1, 3, 2)
    q = np.clip(np.zeros(16), C.JOINT_LOWER, C.JOINT_UPPER)
    q[12] = C.JOINT_LOWER[12]
    flat, data = taxels_at(model, q)
    _skeleton(ax, model, data, (1, 0))
    _scatter(ax, flat, (1, 0), 5)
    for p, pad in enumerate(X.PADS):
        centre = flat[X.PAD_SLICES[pad.name]].mean(axis=0)
        ax.annotate(str(p), (centre[1], centre[0]), fontsize=7, ha="center", va="center", zorder=4,
                    bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="0.5", alpha=0.85))
    names = "\n".join(f"{p:2d} {pad.name}" for p, pad in enumerate(X.PADS))
    ax.text(1.02, 1.0, names, transform=ax.transAxes, fontsize=7, va="top", family="monospace")
    ax.set(xlabel="y (m)", ylabel="x (m)", title="18 pads in taxel order, joints at zero, from above\n"
           "(the thumb's pads face the fingers: seen edge-on)", aspect="equal")
    ax.invert_xaxis()

    ax = fig.add_subplot(1, 3, 3)
    lay = X.taxel_layout()
    sl = X.PAD_SLICES["index_tip"]
    tip, normals = lay.pos[sl] * 1000, lay.frames[sl, 2]
    t = np.linspace(0, np.pi / 2, 50)
    r = X.TIP_RADIUS * 1000
    ax.plot(r * np.cos(t), r * np.sin(t), color="0.5")
    ax.plot([0, -(X.TIP_LENGTH - X.TIP_RADIUS) * 1000 + r], [r, r], color="0.5")
    ax.scatter(tip[:, 0], tip[:, 2], c=tip[:, 1], cmap="coolwarm", s=25, zorder=3)
    ax.quiver(tip[:, 0], tip[:, 2], normals[:, 0], normals[:, 2], angles="xy", scale=12, width=0.004, color="k",
              alpha=0.5)
    for i, (x, z) in enumerate(tip[:, [0, 2]]):
        ax.annotate(str(i), (x, z), fontsize=5, xytext=(2, 2), textcoords="offset points")
    ax.set(xlabel="x along the finger (mm)", ylabel="z palmar (mm)", aspect="equal",
           title="fingertip pad: 30 of a bent 6 x 6 grid\n(side view, colour = y across, arrows = normals)")
    fig.tight_layout()
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(cfg.out, dpi=cfg.dpi)
    plt.close(fig)
    print(f"wrote {cfg.out}")
    return cfg.out


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
