"""Write the gap workflow's results: report.json, the figure, the augmented model."""
from __future__ import annotations

import json
from pathlib import Path

from ..fileio import atomic_write_text


def write_gap_outputs(flow, report: dict, data, out_dir: str | Path) -> dict:
    """``report.json``, ``gap.png`` and ``augmented_model.json`` in ``out_dir``; returns their paths."""
    from ..report.figures import plot_gap

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"report": out / "report.json", "figure": out / "gap.png", "augmented": out / "augmented_model.json"}
    atomic_write_text(paths["report"], json.dumps(report, indent=2, default=float) + "\n")
    atomic_write_text(paths["augmented"], json.dumps(flow.augmented.describe(), indent=2, default=float) + "\n")
    plot_gap(data, flow.preds_before, flow.preds_after, flow.windows, paths["figure"])
    return paths


def summary_lines(report: dict) -> list[str]:
    """Human-readable summary of a report."""
    lines = [f"noise level: {report['noise_level']['relative_median']:.2e} of the signal RMS (median over states)",
             f"disagreement windows: {len(report['windows'])}"]
    for w in report["windows"][:8]:
        lines.append(f"  traj {w['traj']}: {w['t0'] * 1e3:.1f}-{w['t1'] * 1e3:.1f} ms, first {', '.join(w['states'][:3])}; "
                     f"gap {w['gap_before']:.2f} % -> {w['gap_after']:.2f} %")
    if not report["effects"]:
        lines.append("no effect is missing: model and data agree to the noise floor"
                     if not report["windows"] else "no catalogue effect explains the gap")
    for e in report["effects"]:
        if e["name"] == "unnamed":
            terms = ", ".join(f"{t['coefficient']:+.4g}·{t['term']} in d{t['state']}/dt" for t in e["params"]["terms"][:6])
            lines.append(f"effect: unnamed (learned residual): {terms}")
        else:
            params = ", ".join(f"{k} = {v:.5g}" if isinstance(v, float) else f"{k} = {v}" for k, v in e["params"].items())
            unc = ", ".join(f"±{v:.2g}" for v in e["uncertainty"].values())
            lines.append(f"effect: {e['name']} ({params}; {unc}), SSE -{e['evidence']['sse_reduction_pct']:.1f} %")
    lines.append(f"gap overall: {report['gap_before']['overall']:.3f} % -> {report['gap_after']['overall']:.3f} %")
    return lines
