"""Training pictures: renders beside their ground truth, and the loss curves (matplotlib, Agg)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from common.files import atomic_path


def _to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def save_samples(path: Path, renders: list[torch.Tensor], truths: list[torch.Tensor]) -> None:
    """One row per sample: render | ground truth."""
    rows = [np.concatenate([_to_uint8(r), _to_uint8(t)], axis=1) for r, t in zip(renders, truths)]
    grid = np.concatenate(rows, axis=0)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(0, "PNG encoding failed")
    with atomic_path(path, make_parents=True) as tmp:
        Path(tmp).write_bytes(buf.tobytes())


def save_loss_curve(metrics_path: Path, out_path: Path) -> None:
    # The Figure API without pyplot: no GUI backend and no global figure state, and a second less to import.
    from matplotlib.figure import Figure

    train: dict[int, list] = {1: [], 2: []}
    evals: dict[int, list] = {1: [], 2: []}
    for line in Path(metrics_path).read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        (evals if rec.get("eval") else train).setdefault(rec.get("stage", 1), []).append(rec)
    fig = Figure(figsize=(10, 3.6))
    axes = fig.subplots(1, 2)
    for stage, ax in zip((1, 2), axes):
        rows = train.get(stage, [])
        if rows:
            steps = np.array([r["step"] for r in rows])
            loss = np.array([r["loss"] for r in rows])
            ax.plot(steps, loss, lw=0.6, alpha=0.4, color="tab:blue", label="loss (step)")
            k = max(1, len(loss) // 50)
            if len(loss) >= k:
                smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
                ax.plot(steps[k - 1:], smooth, color="tab:blue", label=f"loss (mean of {k})")
                # The rendering term alone: the total jumps where a schedule adds a term (the Chamfer ramp).
                if all("render" in r for r in rows) and len(rows) >= k:
                    part = np.convolve(np.array([r["render"] for r in rows]), np.ones(k) / k, mode="valid")
                    ax.plot(steps[k - 1:], part, color="tab:green", label="rendering term")
        ev = evals.get(stage, [])
        if ev:
            ax2 = ax.twinx()
            ax2.plot([r["step"] for r in ev], [r["psnr"] for r in ev], "o-", color="tab:red", label="held-out PSNR")
            ax2.set_ylabel("PSNR (dB)")
        ax.set_title(f"stage {stage}")
        ax.set_xlabel("step")
        ax.set_ylabel("loss")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    with atomic_path(out_path, make_parents=True) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
