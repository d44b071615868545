"""Training plots as PNG: validation MAE per epoch, and predicted vs expert control over a
validation sequence (the paper's Figure 4)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

STEP_S = 0.1  # simulation step


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_metrics(history: list[dict[str, Any]], path: Path) -> None:
    """MAE of steer and accel on validation per epoch, with the best constant's MAE dashed."""
    plt = _pyplot()
    epochs = [r["epoch"] for r in history]
    fig, (ax_mae, ax_loss) = plt.subplots(1, 2, figsize=(10, 3.6))
    for key, colour in (("steer", "tab:blue"), ("accel", "tab:orange")):
        ax_mae.plot(epochs, [r[f"val_mae_{key}"] for r in history], "o-", color=colour,
                    label=f"{key}")
        ax_mae.axhline(history[-1][f"const_mae_{key}"], color=colour, ls="--", lw=1,
                       label=f"{key}, best constant")
    ax_mae.set(xlabel="epoch", ylabel="validation MAE", title="MAE per epoch")
    ax_mae.legend(fontsize=8)
    ax_loss.plot(epochs, [r["train_loss"] for r in history], "o-", label="train")
    ax_loss.plot(epochs, [r["val_loss"] for r in history], "o-", label="validation")
    ax_loss.set(xlabel="epoch", ylabel="L1 loss", title="loss")
    ax_loss.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_sequence(steps: np.ndarray, predicted: np.ndarray, expert: np.ndarray, episode: int,
                  path: Path) -> None:
    """Predicted vs expert steer (top) and accel (bottom) over one validation episode.

    predicted, expert: (N, 2) = (steer, accel) at `steps` (simulation steps of 0.1 s).
    """
    plt = _pyplot()
    t = np.asarray(steps) * STEP_S
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    for ax, i, name in ((axes[0], 0, "steer"), (axes[1], 1, "accel")):
        ax.plot(t, expert[:, i], color="black", lw=1.2, label="expert")
        ax.plot(t, predicted[:, i], color="tab:red", lw=1.0, label="BID")
        ax.set(ylabel=name, ylim=(-1.05, 1.05))
        ax.legend(fontsize=8, loc="upper right")
    axes[0].set_title(f"predicted vs expert, validation episode {episode}")
    axes[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
