"""``pisml demo``: the main job on the bundled defaults, end to end, with a report folder.

In this version the job is the foundation: the virtual HIL generates the
paper's datasets (training at 40 dB, test, small-signal) as CSV and rosbag2,
the two formats are checked to carry the same values, and the plant's
small-signal stability is mapped over the grid voltage (eigenvalues, damping,
the stability boundary), with figures.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np


def run_demo(out: Path, quiet: bool = False) -> int:
    from .analysis.operating_point import max_real_part, operating_point_report
    from .analysis.margins import stability_boundaries
    from .data import read_bag, read_csv, write_bag, write_csv
    from .plant import InverterPlant
    from .plant.noise import add_measurement_noise
    from .plant.scenarios import generate, schedules_for
    from .report.figures import plot_spectra, plot_stability_scan, plot_trajectories

    started = time.monotonic()

    def say(text):
        if not quiet:
            print(f"[demo {time.monotonic() - started:5.1f} s] {text}", flush=True)

    out.mkdir(parents=True, exist_ok=True)
    plant = InverterPlant()
    files = {}
    for scenario, snr in (("train", 40.0), ("test", None), ("smallsignal", 40.0)):
        schedules, duration = schedules_for(scenario, seed=0)
        data = generate(plant, schedules, duration, metadata={"scenario": scenario, "seed": 0})
        if snr:
            data = add_measurement_noise(data, snr, seed=1_000_003)
        stem = f"{scenario}_{'clean' if snr is None else f'{snr:g}dB'}"
        csv_path = write_csv(data, out / "data" / f"{stem}.csv")
        bag_path = write_bag(data, out / "data" / f"{stem}_bag")
        a, b = read_csv(csv_path), read_bag(bag_path)
        same = all(np.array_equal(ta.x, tb.x) and np.array_equal(ta.u, tb.u) for ta, tb in zip(a, b))
        if not same:
            print(f"demo: CSV and bag of {stem} disagree", flush=True)
            return 1
        files[scenario] = (csv_path, data)
        say(f"{scenario}: {len(data)} trajectories x {len(data.trajectories[0])} samples -> {csv_path.name} "
            f"and {bag_path.name}/ (identical values)")

    plot_trajectories(files["test"][1], out / "test_trajectories.png",
                      title="virtual HIL, test set: sag to 0.4 p.u. at 20 ms (second: 8° jump at 8 ms)")
    plot_trajectories(files["train"][1], out / "train_trajectories.png", traj_ids=[0, 1, 2],
                      title="virtual HIL, training set at 40 dB SNR (first three)")

    reports = {f"{ug:g}": operating_point_report(plant, ug) for ug in (0.2, 0.8, 1.0, 1.2)}
    grid = np.round(np.arange(0.2, 1.3001, 0.05), 3)
    scan = np.array([max_real_part(plant, ug) for ug in grid])
    boundaries = stability_boundaries(lambda g: max_real_part(plant, g), grid)
    (out / "stability.json").write_text(json.dumps(
        {"model_id": "plant", "operating_points": reports, "scan": {"ug": grid.tolist(), "max_real": scan.tolist()},
         "ug_boundaries": boundaries}, indent=2) + "\n")
    plot_spectra({f"ug = {k}": np.array([complex(*z) for z in r["eigenvalues"]]) for k, r in reports.items()},
                 out / "eigenvalues.png", title="virtual HIL eigenvalues")
    plot_stability_scan(grid, scan, out / "stability_scan.png", boundaries)

    r = reports["0.8"]
    say("plant at ug = 0.8 p.u.: eigenvalues (1/s), damping, dominant states")
    if not quiet:
        for (re, im), zeta, dom in zip(r["eigenvalues"], r["damping"], r["dominant_states"]):
            if im >= 0:
                print(f"    {re:10.2f} {'±' if im else ' '} {abs(im):9.2f}j   ζ = {zeta:6.3f}   {', '.join(dom)}")
    for key, rep in reports.items():
        say(f"ug = {key}: {'stable' if rep['stable'] else 'UNSTABLE'}, max Re λ = {rep['max_real']:+.3f} 1/s, "
            f"min ζ = {rep['min_damping']:.3f}")
    say(f"stability boundary in grid voltage: ug = {', '.join(f'{b:.4f}' for b in boundaries)} p.u.")
    say(f"report folder: {out}/ (stability.json, eigenvalues.png, stability_scan.png, *_trajectories.png, data/)")
    return 0
