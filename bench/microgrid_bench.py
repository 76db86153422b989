"""The identified inverter inside a microgrid: does it stand in for the real one?

The paper's system-level check (section 4, the 3-bus microgrid): the target inverter, identified
from its own terminal records, is assembled with two known auxiliary inverters, lines, a load and
the grid (``config/microgrid.yaml``), and the whole system's operating point, modes and stability
boundary are compared with the same microgrid built around the true plant. For each recording
and method (PISML and the Mod-SINDy baseline) it prints and writes:

- the target's operating point in the microgrid (P, Q delivered; truth 0.497 / 0.073 p.u.);
- the microgrid's largest real part and the Wasserstein distance of its spectrum to the truth's,
  with the grid source at 0.8, 1.0 and 1.2 p.u.;
- the stability boundary in the droop gain mp of auxiliary inverter 1 (the truth: 0.1326), the
  paper's "tuning the known units to accommodate the black box";
- a load step (the load bus's resistance 0.9 -> 0.6 p.u.): each unit's injected current against
  the true microgrid's, the paper's large-signal check of the 3-bus system;
- the same microgrid islanded (its line to the grid removed): frequency, the target's power and
  voltage, the largest real part and the boundary in aux1's mp;
- grid strength: the target alone behind a line to the grid (``config/weak_grid.yaml``), the
  largest real part as the line's reactance grows (short-circuit ratio from 100 to 0.67) at 1.0 and
  1.2 p.u., the boundary in x, and where the model's verdict is not the plant's.

    .venv/bin/python bench/microgrid_bench.py [--seeds 0-9] [--noise 40] [--clean] \
        [--methods pisml,mod-sindy] [--out bench/microgrid_results.json] [--markdown bench/MICROGRID_RESULTS.md] \
        [--figure bench/figures/microgrid_load_step.png] [--strength-figure bench/figures/microgrid_grid_strength.png] \
        [--set KEY=VALUE ...]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]

CONFIG = BENCH.parent / "config" / "microgrid.yaml"
GRID_VOLTAGES = (0.8, 1.0, 1.2)
VARY = "units.aux1.plant.mp"
VARY_GRID = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3)
STEP = ("buses.pcc.load.r", 0.6, 0.02, 0.06)  # the load bus's resistance 0.9 -> 0.6 p.u. at 20 ms, 60 ms in all
# grid strength: the target alone behind a line to the grid (config/weak_grid.yaml), the line's x
# (SCR about 1/x) swept at these grid voltages
WEAK_GRID = BENCH.parent / "config" / "weak_grid.yaml"
WEAK_X = (0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 1.0, 1.5)
WEAK_UG = (1.0, 1.2)


def assess(config: dict, target, reference: dict | None = None) -> dict:
    """The microgrid around ``target`` (a system, or None for the plant of the configuration)."""
    from pisml_ros.analysis.metrics import spectrum_wasserstein
    from pisml_ros.analysis.microgrid import (microgrid_from_config, microgrid_report, parameter_sweep, simulate_stages,
                                              with_setting, with_unit_model)

    loaded = {}
    if target is not None:
        config, loaded = with_unit_model(config, "target", target, CONFIG.parent)

    def build(cfg):
        return microgrid_from_config(cfg, CONFIG.parent, loaded=loaded)[0]

    row = {"grid": {}}
    for ug in GRID_VOLTAGES:
        entry = {}
        try:
            grid = build(config)
            report = microgrid_report(grid, ug, 0.0)
            eigs = np.array([complex(re, im) for re, im in report["eigenvalues"]])
            entry.update(max_real=report["max_real"], p=report["units"][0]["p"], q=report["units"][0]["q"],
                         eigenvalues=[[z.real, z.imag] for z in eigs])
            if report.get("alternatives"):  # the target's candidates that fitted its records about as well
                found = report["alternatives"]
                entry["alternatives"] = {"max_real": [item["max_real"] for item in found["candidates"]],
                                         "agree": found["agree"]}
            if reference is not None and reference["grid"][str(ug)].get("eigenvalues"):
                truth = np.array([complex(re, im) for re, im in reference["grid"][str(ug)]["eigenvalues"]])
                entry["wasserstein"] = spectrum_wasserstein(eigs, truth)
        except Exception as err:  # no equilibrium of this microgrid: recorded
            entry["error"] = f"{type(err).__name__}: {err}"
        row["grid"][str(ug)] = entry

    row["boundaries"] = parameter_sweep(config, VARY, VARY_GRID, CONFIG.parent, loaded=loaded)["boundaries"]
    # the paper's large-signal check: a load step, each unit's injected current against the truth's
    path, value, at, end = STEP
    try:
        before, after = build(config), build(with_setting(config, path, value))
        t, x = simulate_stages([(before, at), (after, end - at)], before.equilibrium(1.0, 0.0), [1.0, 0.0])
        currents = before.injected_currents(x)  # (samples, units, 2)
        row["transient"] = {"t": t.tolist(), "currents": currents.tolist()}
        if reference is not None and reference.get("transient"):
            truth = np.array(reference["transient"]["currents"])
            if truth.shape == currents.shape:
                row["transient_error"] = {
                    unit.name: float(100 * np.linalg.norm(currents[:, k] - truth[:, k]) / np.linalg.norm(truth[:, k]))
                    for k, unit in enumerate(before.units)}
    except Exception as err:  # no operating point, or a run that blew up: recorded
        row["transient_error_text"] = f"{type(err).__name__}: {err}"
    # islanded: the same microgrid without its line to the grid (the droops share the load)
    islanded = dict(config, lines=[line for line in config["lines"] if line["to"] != "grid"])
    try:
        report = microgrid_report(build(islanded))
        row["islanded"] = {"frequency": report["frequency_pu"], "max_real": report["max_real"],
                           "p": report["units"][0]["p"], "q": report["units"][0]["q"],
                           "ug_seen": report["units"][0]["ug"], "note": report["units"][0].get("note", ""),
                           "boundaries": parameter_sweep(islanded, VARY, VARY_GRID, CONFIG.parent,
                                                         loaded=loaded)["boundaries"]}
    except Exception as err:  # no operating point: recorded
        row["islanded"] = {"error": f"{type(err).__name__}: {err}"}
    return row


def grid_strength(target) -> dict:
    """The target (a system, or None for the plant) behind a line of growing reactance: the largest
    real part at each x of WEAK_X and the stability boundaries in x, at each grid voltage of WEAK_UG."""
    from pisml_ros.analysis.microgrid import parameter_sweep, read_microgrid_config, with_setting, with_unit_model

    config, loaded = read_microgrid_config(WEAK_GRID), {}
    if target is not None:
        config, loaded = with_unit_model(config, "target", target, WEAK_GRID.parent)
    out = {}
    for ug in WEAK_UG:
        sweep = parameter_sweep(with_setting(config, "grid.ug", ug), "lines.0.x", WEAK_X, WEAK_GRID.parent,
                                loaded=loaded)
        out[str(ug)] = {"max_real": [p["max_real"] for p in sweep["points"]], "boundaries": sweep["boundaries"]}
    return out


def quick_verdicts(target) -> dict:
    """The stability verdicts of ``target`` (a system, or None for the plant) that
    ``bench/setting_sweep.py run`` keeps per recording, without the boundary sweeps and the load
    step of :func:`assess`: the 3-bus microgrid's largest real part with the grid source at 1.0 p.u.
    (None: no operating point), the weak-grid sweep's at 1.0 p.u. (at each x of WEAK_X), and the
    same of each of the target's alternatives (the fit's candidates that reproduced its records
    about as well: ``grid_tied_alternatives``, a list; ``weak_alternatives``, a list per x)."""
    from pisml_ros.analysis.microgrid import microgrid_from_config, read_microgrid_config, with_setting, with_unit_model

    def verdicts(config, base):
        try:
            grid, inputs = microgrid_from_config(config, base, loaded=loaded)
            x = grid.equilibrium(*inputs)
            own = float(np.max(np.linalg.eigvals(grid.jacobian(x, inputs)).real))
        except Exception:  # no operating point of this microgrid: a verdict of its own
            return None, []
        return own, [item["max_real"] for item in grid.alternative_max_reals(x, inputs)]

    loaded = {}
    config = read_microgrid_config(CONFIG)
    if target is not None:
        config, loaded = with_unit_model(config, "target", target, CONFIG.parent)
    grid_tied, grid_tied_alternatives = verdicts(config, CONFIG.parent)
    weak = with_setting(read_microgrid_config(WEAK_GRID), "grid.ug", 1.0)
    if target is not None:
        weak, more = with_unit_model(weak, "target", target, WEAK_GRID.parent)
        loaded.update(more)
    found = [verdicts(with_setting(weak, "lines.0.x", x), WEAK_GRID.parent) for x in WEAK_X]
    return {"grid_tied_max_real": grid_tied, "weak_max_real": [own for own, _ in found],
            "grid_tied_alternatives": grid_tied_alternatives, "weak_alternatives": [others for _, others in found]}


def wrong_verdicts(row: dict, truth: dict, ug: float) -> list:
    """The (x, what the model says) at the x of WEAK_X where the model's stability verdict differs
    from the plant's ("stable", "unstable", or "no eq.": no operating point)."""
    mine, theirs = row["grid_strength"][str(ug)]["max_real"], truth["grid_strength"][str(ug)]["max_real"]
    wrong = []
    for x, m, t in zip(WEAK_X, mine, theirs):
        if m is None:
            wrong.append((x, "no eq."))
        elif (m > 0) != (t > 0):
            wrong.append((x, "unstable" if m > 0 else "stable"))
    return wrong


def verdicts_text(wrong: list) -> str:
    """:func:`wrong_verdicts` for a table cell: "none", or runs of neighbouring x of WEAK_X with the
    same wrong verdict, e.g. "0.02-1.5 unstable"."""
    runs = []  # [first x, last x, what the model says]
    for x, said in wrong:
        if runs and runs[-1][2] == said and WEAK_X.index(runs[-1][1]) == WEAK_X.index(x) - 1:
            runs[-1][1] = x
        else:
            runs.append([x, x, said])
    return ", ".join(f"{a:g}{'' if a == b else f'-{b:g}'} {said}" for a, b, said in runs) or "none"


def cell(value, digits=3):
    return "—" if value is None else f"{value:.{digits}g}"


def write_markdown(results: dict, path: Path) -> None:
    truth = results["truth"]
    lines = ["# The identified inverter inside a microgrid", "",
             f"Generated by `python bench/microgrid_bench.py {results['args']}` on {results['machine']} "
             f"({results['date']}); {results['seconds']:.0f} s.", "",
             "The target inverter of `config/microgrid.yaml` (the paper's 3-bus system: the target and two known "
             "auxiliary inverters, lines, a load bus, the grid) as identified from its own records (the protocol's, "
             "recording = scenario and noise seed), against the same microgrid around the true plant. P, Q: what "
             "the target delivers with the grid source at 1.0 p.u.; max Re: the microgrid's largest real part "
             "(1/s); W: Wasserstein distance of the microgrid's spectrum to the truth's; boundary: the droop gain "
             f"mp of auxiliary inverter 1 where the microgrid turns unstable (`--vary {VARY}`).", "",
             f"Load step: the load bus's resistance {STEP[0].split('.')[-1]} from 0.9 to {STEP[1]} p.u. at "
             f"{STEP[2] * 1e3:g} ms, {STEP[3] * 1e3:g} ms in all, from each microgrid's own operating point; the "
             "relative L2 error (%) of each unit's injected current (network frame) against the true "
             "microgrid's, target / aux1 / aux2 (the paper's figures of the 3-bus transient).", "",
             "Alternatives: the max Re at 1.0 p.u. of the microgrid with each of the target's alternatives in its "
             "place (the fit's other candidates within the selection's tolerance of the best training error, kept "
             "in the model's metadata); \"open\": one of them gives the other verdict, and `pisml microgrid` says "
             "the records do not decide.", "",
             "| target | P | Q | max Re at 0.8 / 1.0 / 1.2 | W at 0.8 / 1.0 / 1.2 | alternatives at 1.0 | "
             "boundary in aux1 mp | load step, current error % |",
             "|---|---|---|---|---|---|---|---|"]

    def row_text(name, row):
        at = row["grid"]
        one = at["1.0"]
        res = " / ".join(cell(at[str(g)].get("max_real"), 4) if "error" not in at[str(g)] else "no eq."
                         for g in GRID_VOLTAGES)
        ws = " / ".join(cell(at[str(g)].get("wasserstein")) if "error" not in at[str(g)] else "—"
                        for g in GRID_VOLTAGES)
        bounds = ", ".join(f"{b:.4g}" for b in row["boundaries"]) or "none"
        errors = row.get("transient_error")
        step = " / ".join(cell(v) for v in errors.values()) if errors else (
            "failed" if "transient_error_text" in row else "—")
        others = one.get("alternatives")
        rivals = "—" if not others else (", ".join("no eq." if v is None else f"{v:.3g}" for v in others["max_real"])
                                         + ("" if others["agree"] else " (open)"))
        return (f"| {name} | {cell(one.get('p'), 4)} | {cell(one.get('q'), 4)} | {res} | {ws} | {rivals} | "
                f"{bounds} | {step} |")

    lines.append(row_text("true plant", truth))
    for row in results["rows"]:
        name = f"{row['method']}, recording {row['seed']}, {row['data']} ({row['coefficients']} coefficients)"
        lines.append(row_text(name, row))
    lines += ["", "Islanded: the same microgrid without its line to the grid (the droops share the load; the "
              "network's frame turns with the target's). Frequency (p.u.), what the target delivers and the voltage "
              "it sees, the largest real part, and the boundary in aux1's mp.", "",
              "| target | frequency | P | Q | target's bus voltage | max Re | boundary in aux1 mp |",
              "|---|---|---|---|---|---|---|"]

    def islanded_text(name, row):
        entry = row.get("islanded") or {}
        if "error" in entry or not entry:
            return f"| {name} | no operating point | | | | | |"
        bounds = ", ".join(f"{b:.4g}" for b in entry["boundaries"]) or "none"
        note = " (outside its records)" if entry.get("note") else ""
        return (f"| {name} | {entry['frequency']:.5f} | {cell(entry['p'], 4)} | {cell(entry['q'], 4)} | "
                f"{entry['ug_seen']:.4f}{note} | {cell(entry['max_real'], 4)} | {bounds} |")

    lines.append(islanded_text("true plant", truth))
    for row in results["rows"]:
        lines.append(islanded_text(f"{row['method']}, recording {row['seed']}, {row['data']}", row))
    if truth.get("grid_strength"):
        low, high = WEAK_UG
        lines += ["", "Grid strength: the target alone behind a line to the grid (`config/weak_grid.yaml`, bus "
                  f"capacitance 0.01, line r 0.01), the line's x swept over {', '.join(f'{x:g}' for x in WEAK_X)} "
                  "p.u. (short-circuit ratio about 1/x: 100 to 0.67). At "
                  f"{high:g} p.u. the plant is unstable on a stiff grid and stable from the boundary on; at {low:g} "
                  "p.u. it is stable at every x. Wrong verdicts: the x where the model's stability verdict is not "
                  "the plant's (what the model says there).", "",
                  f"| target | max Re at {low:g} p.u., x {WEAK_X[0]:g} / {WEAK_X[3]:g} / {WEAK_X[-1]:g} | wrong "
                  f"verdicts at {low:g} p.u. | boundary in x at {high:g} p.u. | wrong verdicts at {high:g} p.u. |",
                  "|---|---|---|---|---|"]

        def strength_text(name, row):
            entry = row.get("grid_strength")
            if not entry:
                return f"| {name} | failed | | | |"
            res = " / ".join(cell(entry[str(low)]["max_real"][k], 4) for k in (0, 3, -1))
            bounds = ", ".join(f"{b:.4g}" for b in entry[str(high)]["boundaries"]) or "none"
            if row is truth:
                return f"| {name} | {res} | | {bounds} | |"
            return (f"| {name} | {res} | {verdicts_text(wrong_verdicts(row, truth, low))} | {bounds} | "
                    f"{verdicts_text(wrong_verdicts(row, truth, high))} |")

        lines.append(strength_text("true plant", truth))
        for row in results["rows"]:
            lines.append(strength_text(f"{row['method']}, recording {row['seed']}, {row['data']}", row))
    path.write_text("\n".join(lines) + "\n")


def _save_figure(fig, axes, ylabel: str, legend_size: int, path: Path) -> None:
    """The y label and the legend on the first of ``axes``, then ``fig`` written to ``path`` and closed."""
    import matplotlib.pyplot as plt

    first = np.atleast_1d(axes)[0]
    first.set_ylabel(ylabel)
    first.legend(fontsize=legend_size)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def strength_figure(truth: dict, rows: list, path: Path) -> None:
    """The largest real part against the line's x (grid strength) at each grid voltage of WEAK_UG:
    the plant and every PISML model of noisy data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not truth.get("grid_strength"):
        return
    fig, axes = plt.subplots(1, len(WEAK_UG), figsize=(11, 3.6))
    for ax, ug in zip(np.atleast_1d(axes), WEAK_UG):
        for row in rows:
            if row["method"] == "pisml" and row["data"] != "clean" and row.get("grid_strength"):
                values = [np.nan if m is None else m for m in row["grid_strength"][str(ug)]["max_real"]]
                ax.plot(WEAK_X, values, "-", color="tab:blue", alpha=0.45, lw=1)
        ax.plot(WEAK_X, truth["grid_strength"][str(ug)]["max_real"], "k-o", lw=2.2, ms=4, label="true plant")
        ax.plot([], [], "-", color="tab:blue", alpha=0.6, label="PISML, one per noisy recording")
        ax.axhline(0.0, color="r", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("symlog", linthresh=1.0)  # a model's spurious mode can sit at +50 1/s, the plant's near -1
        ax.set_xlabel("line reactance x (p.u.; SCR about 1/x)")
        ax.set_title(f"grid at {ug:g} p.u.")
    _save_figure(fig, axes, "largest real part (1/s)", 8, path)


def figure(truth: dict, rows: list, path: Path) -> None:
    """Each unit's injected current (D axis) through the load step: the true microgrid, and the
    first recording's models of each method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not truth.get("transient"):
        return
    t = np.array(truth["transient"]["t"]) * 1e3
    currents = np.array(truth["transient"]["currents"])
    names = ["target", "aux1", "aux2"]
    fig, axes = plt.subplots(1, currents.shape[1], figsize=(12, 3.4), sharey=True)
    shown = {}
    for row in rows:  # one model per method and data: the first recording's
        shown.setdefault((row["method"], row["data"]), row)
    for k, ax in enumerate(np.atleast_1d(axes)):
        ax.plot(t, currents[:, k, 0], "k-", lw=2.2, label="true plant")
        for (method, data), row in shown.items():
            if row.get("transient"):
                model = np.array(row["transient"]["currents"])
                ax.plot(np.array(row["transient"]["t"]) * 1e3, model[:, k, 0], "--", lw=1.2,
                        label=f"{method}, {data}, recording {row['seed']}")
        ax.set_title(f"{names[k] if k < len(names) else k}: injected current, D axis")
        ax.set_xlabel("t (ms)")
    _save_figure(fig, axes, "p.u.", 7, path)


def main(argv=None) -> int:
    from bench import add_settings_option, datasets, machine, settings_or_exit

    from pisml_ros.analysis.microgrid import read_microgrid_config

    from pisml_ros.ident import IdentConfig, make_estimator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-9", help="recordings (scenario and noise seeds), e.g. 0-9 or 0,2,5")
    parser.add_argument("--noise", type=float, default=40.0, help="SNR (dB) of the noisy recordings")
    parser.add_argument("--clean", action="store_true", help="also the clean recording of the first seed")
    parser.add_argument("--methods", default="pisml,mod-sindy")
    parser.add_argument("--out", default=str(BENCH / "microgrid_results.json"))
    parser.add_argument("--markdown", default=str(BENCH / "MICROGRID_RESULTS.md"))
    parser.add_argument("--figure", default=str(BENCH / "figures" / "microgrid_load_step.png"))
    parser.add_argument("--strength-figure", default=str(BENCH / "figures" / "microgrid_grid_strength.png"))
    add_settings_option(parser)
    args = parser.parse_args(argv)
    settings = settings_or_exit(args.set, parser)
    seeds = []
    for part in (p.strip() for p in args.seeds.split(",") if p.strip()):
        low, _, high = part.partition("-")
        seeds += list(range(int(low), int(high or low) + 1))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    config = read_microgrid_config(CONFIG)
    started = time.monotonic()
    truth = assess(config, None)
    truth["grid_strength"] = grid_strength(None)
    print(f"truth: max Re at 1.0 {truth['grid']['1.0']['max_real']:.4g} 1/s, boundary in {VARY} {truth['boundaries']}",
          flush=True)
    runs = [(seed, None) for seed in seeds[:1]] if args.clean else []
    runs += [(seed, args.noise) for seed in seeds]
    rows = []
    for seed, snr in runs:
        _, train, small, _ = datasets(None, snr, seed=seed)
        for method in methods:
            fit_started = time.monotonic()
            est = make_estimator(method, IdentConfig.load(None, settings)).fit(train, small)
            model = est.explicit_model_
            row = {"seed": seed, "data": "clean" if snr is None else f"{snr:g} dB", "method": method,
                   "coefficients": int(model.n_parameters), "fit_s": round(time.monotonic() - fit_started, 1)}
            row.update(assess(config, model, truth))
            try:
                row["grid_strength"] = grid_strength(model)
            except Exception as err:  # a sweep that cannot start (no operating point at all): recorded
                row["grid_strength_error"] = f"{type(err).__name__}: {err}"
            rows.append(row)
            one = row["grid"]["1.0"]
            step = row.get("transient_error", row.get("transient_error_text"))
            print(f"{method} {row['data']} recording {seed}: P {cell(one.get('p'), 4)} Q {cell(one.get('q'), 4)} "
                  f"max Re {cell(one.get('max_real'), 4)} W {cell(one.get('wasserstein'))} "
                  f"boundary {row['boundaries']} load step {step} "
                  f"({row['fit_s']} s fit){' ' + one['error'] if 'error' in one else ''}",
                  flush=True)
            if row.get("grid_strength"):
                print("  grid strength: wrong verdicts " + "; ".join(
                    f"at {ug:g} p.u.: {verdicts_text(wrong_verdicts(row, truth, ug))}" for ug in WEAK_UG) +
                    f"; boundary at {WEAK_UG[-1]:g} p.u. {row['grid_strength'][str(WEAK_UG[-1])]['boundaries']}",
                    flush=True)
    figure(truth, rows, Path(args.figure))
    strength_figure(truth, rows, Path(args.strength_figure))
    for row in [truth, *rows]:  # the waveforms are in the figure; the results file keeps the errors
        row.pop("transient", None)
    for row in rows:  # and the truth's spectra, the models' distances to them (W)
        for entry in row["grid"].values():
            entry.pop("eigenvalues", None)
    results = {"args": " ".join(argv if argv is not None else sys.argv[1:]), "machine": machine(),
               "date": time.strftime("%Y-%m-%d"), "seconds": time.monotonic() - started,
               "config": str(CONFIG.relative_to(BENCH.parent)), "vary": VARY, "truth": truth, "rows": rows}
    Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    write_markdown(results, Path(args.markdown))
    print(f"wrote {args.out} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
