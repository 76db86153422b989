"""Figures of an identification run: model vs measurement, coefficients, training curves."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..signals import SCORED_STATES  # noqa: E402
from .figures import _save  # noqa: E402


def plot_model_vs_data(data, pred, path: str | Path, t_split: float = 0.02, states: Sequence[str] = SCORED_STATES,
                       titles: Sequence[str] | None = None, title: str = "") -> Path:
    """Measured vs simulated trajectories, one column per trajectory, one row per state; the
    in-distribution window (t < t_split) shaded."""
    cols = data.state_index(states)
    n = len(data)
    fig, axes = plt.subplots(len(states), n, figsize=(5.5 * n, 1.9 * len(states)), sharex=True, squeeze=False)
    for k, (tr, pr) in enumerate(zip(data, pred)):
        for row, (col, name) in enumerate(zip(cols, states)):
            ax = axes[row, k]
            ax.axvspan(0, t_split * 1e3, color="0.92", zorder=0)
            ax.plot(tr.t * 1e3, tr.x[:, col], color="0.35", lw=1.6, label="measured")
            y = np.where(np.isfinite(pr.x[:, col]), pr.x[:, col], np.nan)
            ax.plot(pr.t * 1e3, y, "C3--", lw=1.0, label="identified model")
            lo, hi = np.min(tr.x[:, col]), np.max(tr.x[:, col])
            pad = 0.5 * (hi - lo) + 1e-3
            ax.set_ylim(lo - pad, hi + pad)  # a diverging model must not hide the measurement
            if k == 0:
                ax.set_ylabel(f"{name} (p.u.)")
        axes[0, k].set_title(titles[k] if titles else f"trajectory {tr.traj_id}", fontsize=9)
        axes[-1, k].set_xlabel("t (ms)   [shaded: IOD window]")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_coefficients(model, path: str | Path, title: str = "") -> Path:
    """Heatmap of the explicit model's coefficients (terms × states) on a symmetric log scale; zeros blank."""
    from matplotlib.colors import SymLogNorm

    coef = np.asarray(model.coefficients, dtype=float)
    rows = np.flatnonzero(np.any(coef != 0, axis=1))
    coef = coef[rows]
    terms = [model.terms[k] for k in rows]
    nonzero = np.abs(coef[coef != 0])
    top = float(nonzero.max()) if nonzero.size else 1.0
    linthresh = max(float(np.percentile(nonzero, 10)) if nonzero.size else 1e-3, top * 1e-6)
    fig, ax = plt.subplots(figsize=(1.0 + 0.55 * coef.shape[1], 1.2 + 0.22 * max(len(terms), 1)))
    image = ax.imshow(np.where(coef != 0, coef, np.nan), aspect="auto", cmap="coolwarm", interpolation="nearest",
                      norm=SymLogNorm(linthresh=linthresh, vmin=-top, vmax=top, base=10))
    ax.set_xticks(range(len(model.state_names)), [f"d{n}" for n in model.state_names], rotation=60, fontsize=7)
    ax.set_yticks(range(len(terms)), [t if len(t) < 40 else t[:37] + "..." for t in terms], fontsize=6)
    cbar = fig.colorbar(image, ax=ax, fraction=0.05)
    cbar.set_label("coefficient (1/s, symmetric log scale)")
    ax.set_title(title or f"{np.count_nonzero(coef)} nonzero coefficients over {len(terms)} terms", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def plot_training_curves(history: dict, path: str | Path, title: str = "") -> Path:
    """Losses against epochs (the engine's training history) and the updates' losses over time."""
    training = history.get("training") or {}
    curves = training.get("training", training) if isinstance(training, dict) else {}
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.8))
    epochs = curves.get("epochs") or []
    drawn = False
    for key, value in curves.items():
        if key == "epochs" or not isinstance(value, list) or not value or len(value) != len(epochs):
            continue
        y = np.asarray(value, dtype=float)
        if np.all(y <= 0):
            continue
        left.semilogy(epochs, np.where(y > 0, y, np.nan), label=key.replace("_", " "))
        drawn = True
    left.set_xlabel("epoch")
    left.set_ylabel("loss")
    left.set_title("hybrid training" if drawn else "no training stage in this method", fontsize=9)
    if drawn:
        left.legend(fontsize=8)
    left.grid(alpha=0.3)
    updates = history.get("updates") or []
    counts = {"terms", "nonzero", "n_terms", "n_nonzero"}  # sizes, not losses
    names = sorted({k for u in updates for k in u.get("losses", {}) if k not in counts})
    for name in names:
        pts = [(u["t"], u["losses"][name]) for u in updates if name in u.get("losses", {})]
        t, y = np.array(pts, dtype=float).T
        if np.all(y > 0):
            right.semilogy(t, y, "o-", ms=2, label=name)
    stages = []
    for u in updates:
        if not stages or stages[-1][1] != u["stage"]:
            stages.append((u["t"], u["stage"]))
    for t, stage in stages:
        right.axvline(t, color="0.7", lw=0.7)
        right.annotate(stage, (t, 1), xycoords=("data", "axes fraction"), rotation=90, va="top", fontsize=7)
    right.set_xlabel("wall time (s)")
    right.set_title("engine updates (losses as reported)", fontsize=9)
    if names:
        right.legend(fontsize=7)
    right.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)
