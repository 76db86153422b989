"""Figures of datasets and spectra (matplotlib with the Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_trajectories(dataset, path: str | Path, states: Sequence[str] = ("ig_d", "ig_q", "vc_d", "vc_q"),
                      traj_ids: Sequence[int] | None = None, title: str = "") -> Path:
    """One panel per state, one line per trajectory; grid voltage on a twin axis of the first panel."""
    ids = list(traj_ids) if traj_ids is not None else [tr.traj_id for tr in dataset][:4]
    cols = dataset.state_index(states)
    fig, axes = plt.subplots(len(states), 1, figsize=(8, 2.0 * len(states)), sharex=True)
    for tr in dataset:
        if tr.traj_id not in ids:
            continue
        for ax, col, name in zip(axes, cols, states):
            ax.plot(tr.t * 1e3, tr.x[:, col], lw=1.0, label=f"traj {tr.traj_id}")
            ax.set_ylabel(f"{name} (p.u.)")
    if "ug" in dataset.input_names:
        twin = axes[0].twinx()
        k = dataset.input_names.index("ug")
        for tr in dataset:
            if tr.traj_id in ids:
                twin.plot(tr.t * 1e3, tr.u[:, k], "k:", lw=0.8)
        twin.set_ylabel("ug (dotted)")
    axes[0].legend(loc="lower left", fontsize=7)
    axes[-1].set_xlabel("t (ms)")
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_spectra(spectra: Mapping[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """Eigenvalues in the complex plane: full view and a zoom on the slow modes."""
    fig, (full, zoom) = plt.subplots(1, 2, figsize=(10, 4))
    markers = "os^vDp"
    for k, (label, eig) in enumerate(spectra.items()):
        eig = np.asarray(eig)
        for ax in (full, zoom):
            ax.scatter(eig.real, eig.imag, marker=markers[k % len(markers)], s=28, label=label,
                       facecolors="none", edgecolors=f"C{k}")
    for ax in (full, zoom):
        ax.axvline(0, color="r", lw=0.8)
        ax.set_xlabel("Re λ (1/s)")
        ax.set_ylabel("Im λ (1/s)")
        ax.grid(alpha=0.3)
    zoom.set_xlim(-40, 5)
    zoom.set_ylim(-80, 80)
    zoom.set_title("slow modes")
    full.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_stability_scan(ug: np.ndarray, max_real: np.ndarray, path: str | Path, boundaries=()) -> Path:
    """Largest real part of the eigenvalues against the grid voltage, boundaries marked."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(ug, max_real, "o-", ms=3)
    ax.axhline(0, color="r", lw=0.8)
    for b in boundaries:
        ax.axvline(b, color="k", ls="--", lw=0.8)
        ax.annotate(f"boundary ug = {b:.3f}", (b, 0), textcoords="offset points", xytext=(-120, 20))
    ax.set_xlabel("ug (p.u.)")
    ax.set_ylabel("max Re λ (1/s)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_gap(data, before, after, windows, path, states=("ig_d", "ig_q", "vc_d", "vc_q"), traj_index=None) -> Path:
    """Measured vs reference vs augmented simulation of one trajectory, disagreement windows shaded."""
    if traj_index is None:
        traj_index = windows[0]["traj_index"] if windows else 0
    tr = data.trajectories[traj_index]
    cols = data.state_index(states)
    fig, axes = plt.subplots(len(states), 1, figsize=(8, 2.0 * len(states)), sharex=True)
    for ax, col, name in zip(axes, cols, states):
        ax.plot(tr.t * 1e3, tr.x[:, col], color="0.5", lw=1.5, label="measured")
        ax.plot(tr.t * 1e3, before[traj_index][:, col], "r--", lw=1.0, label="reference")
        ax.plot(tr.t * 1e3, after[traj_index][:, col], "b-", lw=0.9, label="augmented")
        for w in windows:
            if w["traj_index"] == traj_index:
                ax.axvspan(w["t0"] * 1e3, w["t1"] * 1e3, color="orange", alpha=0.15)
        ax.set_ylabel(f"{name} (p.u.)")
    axes[0].legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("t (ms)")
    fig.suptitle(f"gap workflow, trajectory {tr.traj_id} (disagreement windows shaded)")
    fig.tight_layout()
    return _save(fig, path)
