"""`rotate train-il`: train an imitation policy (rotation.il.model) on demonstrations (`rotate demos`).

    rotate train-il --demos data/demos --touch none --out runs/il_camera                 # camera only
    rotate train-il --demos data/demos --touch image --encoder sparshx-tinier-sim --out runs/il_touch_image
    rotate train-il --demos data/demos --touch all --encoder sparshx-tinier-sim --out runs/il_touch_all
    rotate train-il --demos data/demos --touch e2e --encoder sparshx-tinier-sim --batch-size 8 --steps 1500 \
        --out runs/il_touch_e2e                                                         # no pretraining
    rotate train-il --demos data/demos_xela --touch skin --encoder SKIN_ENCODER --out runs/il_skin  # Xela hand
    rotate train-il --demos data/demos data/dagger_1 --touch all --out runs/il_touch_all_r1  # with a DAgger round

``--touch`` picks what the policy reads besides the wrist camera and proprioception: nothing (``none``), the frozen
encoder's image tokens (``image``) or all of its modalities (``all``), one embedding per fingertip, computed once
per step of the demonstrations and cached in OUT; or all four modalities through an encoder of the named one's
structure trained from random weights with the policy (``e2e``, the benchmark's baseline without pretraining: its
windows are rendered for every batch, so a step costs about as much as a pretraining step of that encoder on
``4 x batch_size`` windows; on 2 CPU cores use a smaller --batch-size); or, on demonstrations of the Xela hand
(`rotate demos --hand xela_v4`), a frozen Sparsh-skin encoder's mean token of the whole hand's skin window
(``skin``). The bundle records the demonstrations' hand, which its evaluation runs on.

Loss: L1 between the predicted and the demonstrated chunk of the next ``chunk`` actions (standardized; steps past an
episode's end masked out), AdamW over the policy (and the e2e encoder). A checkpoint is written every
``checkpoint_every`` steps; the same command with ``--resume`` continues it exactly. OUT: bundle/ (rotation.il.bundle,
with a card: the command's settings, the demonstrations, steps, wall time), curves.jsonl, checkpoint.pt.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tqdm import tqdm

from envs.errors import RequestRefused
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import save_config, to_jsonable
from rotation.il.bundle import save_il
from rotation.il.data import Demos, touch_embeddings
from rotation.il.model import ChunkPolicy, PolicyConfig


@dataclass(frozen=True)
class Config:
    demos: tuple[Path, ...] = (Path("data/demos"),)
    """Demonstration sessions: one or more folders of `rotate demos` (the expert's, and the DAgger rounds'
    `rotate demos --policy`), read together."""
    out: Path = Path("runs/il")
    """Run folder."""
    touch: Literal["none", "image", "all", "e2e", "skin"] = "none"
    """What touch the policy reads (see the module docstring)."""
    encoder: str = "sparshx-tinier-sim"
    """The frozen touch encoder (a shipped name, a `rotate pretrain` run or an encoder file); with --touch e2e, the
    encoder whose structure is trained from random weights."""
    chunk: int = 10
    """Actions predicted at once."""
    width: int = 128
    """Transformer width."""
    steps: int = 3000
    """Optimizer steps."""
    batch_size: int = 32
    lr: float = 3e-4
    weight_decay: float = 1e-4
    checkpoint_every: int = 500
    seed: int = 0
    resume: bool = False
    """Continue the run in OUT from its checkpoint."""
    torch_threads: int = 2
    progress: bool = True

    def __post_init__(self) -> None:
        demos = (self.demos,) if isinstance(self.demos, (str, Path)) else self.demos  # one folder, from Python
        if isinstance(demos, (tuple, list)) and all(isinstance(d, (str, Path)) for d in demos):
            object.__setattr__(self, "demos", tuple(Path(d) for d in demos))
        check_types(self)
        if not self.demos:
            raise ValueError("demos: give at least one folder of demonstrations")
        check_output_dir("out", self.out)
        for name, low, high in (("chunk", 1, 100), ("width", 16, 1024), ("steps", 1, 10**7), ("batch_size", 1, 4096),
                                ("checkpoint_every", 1, 10**7), ("torch_threads", 1, 256)):
            check_int(name, getattr(self, name), low, high)
        check_number("lr", self.lr, 0.0, 1.0, low_open=True)
        check_number("weight_decay", self.weight_decay, 0.0, 1.0)
        check_seed("seed", self.seed)


class EndToEndTouch:
    """--touch e2e: a fresh trainable encoder of ``encoder``'s structure and the demonstrations' windows, rendered
    per batch (rotation.il.data.touch_rows)."""

    def __init__(self, paths: list[Path], encoder: str, seed: int) -> None:
        from rotation.il.data import touch_rows
        from rotation.il.touch import TouchEmbedder

        self.embedder = TouchEmbedder(encoder, "e2e", seed=seed)
        self.windows, self.rows = touch_rows(paths)

    def embed(self, steps: np.ndarray) -> torch.Tensor:
        """(B, 4, D) fingertip embeddings of demonstration steps ``steps``, with gradients to the encoder."""
        from rotation.il.data import window_batch

        x = window_batch(self.windows, self.rows[steps])
        return self.embedder.tokens_mean(x).reshape(len(steps), self.rows.shape[1], self.embedder.width)


def _hand_grip_wrist(paths: list[Path], touch: str) -> tuple[str, str, str]:
    """The demonstrations' hand, grip of the plug and wrist (one of each for all of them), the hand checked against
    the touch the policy reads."""
    from envs.insertion import InsertionConfig
    from envs.plug_grip import FIRST_GRIP
    from envs.wrist_compliance import FIRST_WRIST
    from rotation.data.session_reader import SessionReader

    hands, grips, wrists = set(), set(), set()
    for path in paths:
        with SessionReader(path) as r:
            hands.add(str(r.meta.extra.get("sim_hand", InsertionConfig.hand)))
            grips.add(str((r.meta.extra.get("demos") or {}).get("grip", FIRST_GRIP)))
            wrists.add(str((r.meta.extra.get("demos") or {}).get("wrist", FIRST_WRIST)))
    if len(hands) > 1:
        raise RequestRefused(f"demos: the demonstrations come from different hands ({', '.join(sorted(hands))}); "
                             "train on one hand's")
    if len(grips) > 1:
        raise RequestRefused(f"demos: the demonstrations hold the plug in different grips ({', '.join(sorted(grips))}"
                             "); train on one grip's")
    if len(wrists) > 1:
        raise RequestRefused(f"demos: the demonstrations move the wrist in different ways ({', '.join(sorted(wrists))}"
                             "); train on one wrist's")
    hand = hands.pop()
    if (touch == "skin") != (hand == "xela_v4") and touch != "none":
        need = "the Xela hand's (`rotate demos --hand xela_v4`)" if touch == "skin" else "a Digit 360 hand's"
        raise RequestRefused(f"touch: --touch {touch} needs {need} demonstrations; these are the {hand} hand's")
    return hand, grips.pop(), wrists.pop()


def _paths(demos: tuple[Path, ...]) -> list[Path]:
    """Every session of the folders, each file once (a folder may hold another that is also given)."""
    from rotation.data.dataset import find_sessions

    paths: dict[Path, None] = {}
    for folder in demos:
        found = find_sessions(folder) if Path(folder).exists() else []
        if not found:
            raise RequestRefused(f"demos: no demonstration sessions in {folder} (record them with `rotate demos`)")
        paths.update((Path(p).resolve(), None) for p in found)
    return sorted(paths)


def run(cfg: Config) -> dict:
    torch.set_num_threads(cfg.torch_threads)
    paths = _paths(cfg.demos)
    out = Path(cfg.out)
    ckpt = out / "checkpoint.pt"
    if cfg.resume and not ckpt.is_file():
        raise RequestRefused(f"resume: no checkpoint in {out}")
    if not cfg.resume and ckpt.is_file():
        raise RequestRefused(f"out: {out} holds a run; continue it with --resume or choose another --out")
    hand, grip, wrist = _hand_grip_wrist(paths, cfg.touch)  # before anything is written: a refusal leaves OUT as it was
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.json")
    touch, touch_dim, fingers, e2e = None, 0, 4, None
    if cfg.touch == "e2e":
        e2e = EndToEndTouch(paths, cfg.encoder, cfg.seed)
        touch_dim = e2e.embedder.width
    elif cfg.touch != "none":
        touch = touch_embeddings(paths, cfg.encoder, cfg.touch, out, cfg.progress)
        touch_dim, fingers = touch.shape[-1], touch.shape[1]
    data = Demos(paths, cfg.chunk, touch)
    h, w = data.images.shape[1:3]
    torch.manual_seed(cfg.seed)  # the initial weights
    model = ChunkPolicy(PolicyConfig(image_size=(w, h), chunk=cfg.chunk, width=cfg.width, touch_dim=touch_dim,
                                     fingers=fingers))
    model.set_stats(torch.from_numpy(data.proprio), torch.from_numpy(data.actions),
                    None if touch is None else torch.from_numpy(touch))
    params = [*model.parameters(), *([] if e2e is None else e2e.embedder.encoder.parameters())]
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    start, wall_before, history = 0, 0.0, []
    if cfg.resume:
        state = torch.load(ckpt, weights_only=False)
        model.load_state_dict(state["model"])
        if e2e is not None:
            e2e.embedder.encoder.load_state_dict(state["touch_encoder"])
        opt.load_state_dict(state["opt"])
        start, wall_before, history = state["step"], state["wall_s"], state["history"]
    t0 = time.perf_counter()
    model.train()
    bar = tqdm(total=cfg.steps, initial=start, desc="train-il", unit="step", disable=not cfg.progress,
               dynamic_ncols=True)
    loss_sum, n_sum = 0.0, 0
    for step in range(start, cfg.steps):
        g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)  # a resumed run draws the same batches
        idx = torch.randint(0, len(data), (min(cfg.batch_size, len(data)),), generator=g)
        batch = [data[int(i)] for i in idx]
        b = {k: torch.stack([s[k] for s in batch]) for k in batch[0]}
        torch.manual_seed(cfg.seed * 1_000_003 + step)  # dropout
        touch_in = b.get("touch") if e2e is None else e2e.embed(idx.numpy())
        pred = model(b["image"], b["proprio"], touch_in)
        target = (b["actions"] - model.action_mean) / model.action_std
        err = (pred - target).abs().mean(-1)
        loss = (err * b["mask"]).sum() / b["mask"].sum().clamp_min(1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 10.0)
        opt.step()
        loss_sum, n_sum = loss_sum + loss.item(), n_sum + 1
        bar.update(1)
        if (step + 1) % 50 == 0 or step + 1 == cfg.steps:
            history.append({"step": step + 1, "loss": loss_sum / n_sum})
            bar.set_postfix(loss=f"{loss_sum / n_sum:.3f}")
            loss_sum, n_sum = 0.0, 0
        if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == cfg.steps:
            wall = wall_before + time.perf_counter() - t0
            tmp = ckpt.with_suffix(".tmp")
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "step": step + 1, "wall_s": wall,
                        "history": history, **({} if e2e is None else
                                               {"touch_encoder": e2e.embedder.encoder.state_dict()})}, tmp)
            tmp.replace(ckpt)
    bar.close()
    wall = wall_before + time.perf_counter() - t0
    (out / "curves.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))
    model.eval()
    card = {"trained_by": "rotate train-il", "config": to_jsonable(cfg), "demonstrations": len(paths),
            "samples": len(data), "steps": cfg.steps, "wall_time_s": round(wall, 1),
            "final_loss": history[-1]["loss"] if history else math.nan}
    bundle = save_il(out / "bundle", model, {"task": "insertion", "hand": hand, "grip": grip, "wrist": wrist,
                                             "touch": cfg.touch,
                                             "encoder": None if cfg.touch == "none" else cfg.encoder, "card": card},
                     touch_encoder=None if e2e is None else e2e.embedder.encoder)
    print(f"train-il: {cfg.steps} steps on {len(paths)} demonstrations ({len(data)} samples) in {wall:.0f} s, "
          f"final loss {card['final_loss']:.3f}; bundle at {bundle}")
    return {"bundle": str(bundle), "history": history, "final_loss": float(np.nan_to_num(card["final_loss"]))}
