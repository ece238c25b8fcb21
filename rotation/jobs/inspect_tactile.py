"""Plot every touch modality of one session window for a human check (PNG, headless).

    rotate inspect-touch data/touch/shard_000/episode_000000.h5 --out window.png
    rotate inspect-touch SESSION --finger thumb --time 4.2 --out thumb.png

(`rotate inspect-tactile` is the same command under its earlier name.)

One row per fingertip: the two frames of the image window (t-5 and t), both microphones' waveforms, the log-mel
features the encoder sees (224 frames x 2 x 128 bins), the accelerometer (g) and the pressure (hPa), all ending at
the same image timestamp; the labels known at that time are printed in the row's title.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.constants import FINGERS
from envs.sensors.digit360_model import AUDIO_HZ, IMU_HZ, PRESSURE_HZ
from envs.validation import check_int, check_number, check_output_file, check_types

_MODALITY_COLUMNS = 6


@dataclass(frozen=True)
class Config:
    session: Path = Path()
    """Session file (.h5) to inspect."""
    out: Path = Path("tactile_window.png")
    """Output PNG (the name must end in .png: the file written is the one named)."""
    finger: str = "all"
    """Fingertip to plot ('all' for one row per fingertip with touch data)."""
    time: float = -1.0
    """Window end (s since the session start); the last image timestamp at or before it. < 0: mid-session."""
    dpi: int = 80
    """Resolution of the PNG (dots per inch of a 19 x 3.2-per-row inch figure)."""

    def __post_init__(self) -> None:
        check_types(self)
        if self.finger not in ("all", *FINGERS):
            raise ValueError(f"finger: unknown fingertip {self.finger!r}; choose one of all, {', '.join(FINGERS)}")
        check_number("time", self.time, -1e6, 1e6, unit="s")
        check_int("dpi", self.dpi, 10, 1200)
        if Path(self.out).suffix.lower() != ".png":
            raise ValueError(f"out: {self.out} must end in .png (the picture is a PNG)")
        check_output_file("out", self.out)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", type=Path, help="session file (.h5) to inspect")
    parser.add_argument("--out", type=Path, default=Config.out, help=f"output PNG (default: {Config.out})")
    parser.add_argument("--finger", default="all", choices=("all", *FINGERS), help="fingertip (default: all)")
    parser.add_argument("--time", type=float, default=-1.0,
                        help="window end in s since the session start (default: mid-session)")
    parser.add_argument("--dpi", type=int, default=Config.dpi, help=f"PNG resolution (default: {Config.dpi})")


def config_from_args(args: argparse.Namespace) -> Config:
    return Config(session=args.session, out=args.out, finger=args.finger, time=args.time, dpi=args.dpi)


def run(cfg: Config) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rotation.data.audio import fbank
    from rotation.data.dataset import TouchWindows
    from rotation.data.session_reader import SessionReader

    with SessionReader(cfg.session) as r:
        fingers = r.fingers_with_touch()
    if cfg.finger != "all":
        if cfg.finger not in fingers:
            raise ValueError(f"session {cfg.session} has no touch data for {cfg.finger!r} (has: {', '.join(fingers)})")
        fingers = (cfg.finger,)
    if not fingers:
        raise ValueError(f"session {cfg.session} holds no Digit 360 streams")
    ds = TouchWindows([cfg.session], fingers=fingers, audio_features=False)
    if len(ds) == 0:
        raise ValueError(f"session {cfg.session} is too short for a full window (needs about 1.2 s of touch data)")
    rows = []
    for finger in fingers:
        idx = np.flatnonzero(ds.index[:, 1] == FINGERS.index(finger))  # this fingertip's windows, in time order
        ends = ds.end_times[idx]
        target = cfg.time if cfg.time >= 0 else 0.5 * (ends[0] + ends[-1])
        pick = idx[max(0, int(np.searchsorted(ends, target + 1e-9, side="right")) - 1)]  # last end <= target
        rows.append((finger, ds[int(pick)]))

    fig, axes = plt.subplots(len(rows), _MODALITY_COLUMNS, figsize=(3.2 * _MODALITY_COLUMNS, 3.2 * len(rows)),
                             squeeze=False, gridspec_kw={"width_ratios": [1, 1, 1.6, 1.6, 1.4, 1.4]},
                             layout="constrained")
    for (finger, s), ax in zip(rows, axes, strict=True):
        img = s["image"].numpy().reshape(3, 2, 224, 224)  # (6, H, W) -> (color, time, H, W)
        for k, name in enumerate(("t-5", "t")):
            ax[k].imshow(np.moveaxis(img[:, k], 0, -1))
            ax[k].set_title(f"{finger}: image {name}")
            ax[k].axis("off")
        wave = s["audio_wave"].numpy()  # (2, 27000) int16 counts
        t_end = float(s["time"])
        ta = t_end - np.arange(wave.shape[1] - 1, -1, -1) / AUDIO_HZ
        for c in range(wave.shape[0]):
            ax[2].plot(ta, wave[c], lw=0.5, label=f"mic {c}")
        ax[2].set_title("audio (int16 counts)")
        ax[2].legend(loc="upper left", fontsize=7)
        logmel = fbank(s["audio_wave"]).numpy()  # (224, 256)
        ax[3].imshow(logmel.T, origin="lower", aspect="auto", cmap="magma")
        ax[3].axhline(127.5, color="w", lw=0.8)
        ax[3].set_title("log-mel (mic 0 | mic 1)")
        ax[3].set_xlabel("frame (2.5 ms)")
        imu = s["imu"].numpy()
        ti = t_end - np.arange(len(imu) - 1, -1, -1) / IMU_HZ
        for c, axis in enumerate("xyz"):
            ax[4].plot(ti, imu[:, c], lw=0.8, label=axis)
        ax[4].set_title("accelerometer (g)")
        ax[4].legend(loc="upper left", fontsize=7)
        p = s["pressure"].numpy()[:, 0]
        ax[5].plot(t_end - np.arange(len(p) - 1, -1, -1) / PRESSURE_HZ, p, lw=0.8)
        ax[5].set_title("pressure (hPa)")
        labels = [f"{k} {np.round(s[k].numpy().astype(float), 2).tolist()}" for k in ("force", "slip") if k in s]
        ax[0].text(0.0, -0.08, f"t = {t_end:.3f} s\n" + "\n".join(labels), transform=ax[0].transAxes, fontsize=8,
                   va="top")
    fig.suptitle(f"{cfg.session.name}: Sparsh-X windows ending at one image timestamp", fontsize=11)
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(cfg.out, dpi=cfg.dpi)
    plt.close(fig)
    print(f"inspect-touch: wrote {cfg.out}")
    return cfg.out
