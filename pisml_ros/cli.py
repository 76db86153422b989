"""The ``pisml`` command: simulate, inspect data, analyse, run the demo.

User errors (bad files, parameters, values) print one line ``pisml: error: ...``
on stderr and exit with status 2; no traceback.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from .data import DataError
from .model import ModelFormatError
from .plant.effects import EFFECTS
from .plant.parameters import ParameterError

EXIT_USAGE = 2


class UserError(Exception):
    """An error of the user's input: reported in one line, exit status 2."""


def _load_plant(args):
    from .plant import InverterPlant, PlantParameters, load_parameters
    from .plant.effects import parse_effect_assignments

    params = load_parameters(args.params) if args.params else PlantParameters()
    effects = parse_effect_assignments(args.effect or [], args.effect_param or [])
    return InverterPlant(params, effects)


def _add_plant_options(parser):
    parser.add_argument("--params", metavar="FILE", help="plant parameters (YAML or JSON; keys as in DESIGN.md)")
    parser.add_argument("--effect", action="append", metavar="NAME", choices=list(EFFECTS),
                        help="switch on a named effect (repeatable): " + ", ".join(EFFECTS))
    parser.add_argument("--effect-param", action="append", metavar="NAME.KEY=VALUE",
                        help="set an effect parameter (repeatable; switches the effect on)")


# ---------------------------------------------------------------------------- commands
def cmd_simulate(args) -> int:
    if args.model:
        return _simulate_model(args)
    if not args.scenario:
        raise UserError("give --scenario (simulate the virtual HIL) or --model MODEL.json --data PATH (replay)")
    from .data import write_dataset
    from .plant.noise import add_measurement_noise
    from .plant.scenarios import generate, schedules_for

    plant = _load_plant(args)
    if args.n_traj is not None and args.n_traj < 1:
        raise UserError(f"--n-traj must be >= 1, got {args.n_traj}")
    if args.duration is not None and not (0 < args.duration <= 600):
        raise UserError(f"--duration must be in (0, 600] s, got {args.duration}")
    schedules, duration = schedules_for(args.scenario, seed=args.seed, n_traj=args.n_traj, duration=args.duration)
    dataset = generate(plant, schedules, duration, method=args.solver,
                       metadata={"scenario": args.scenario, "seed": args.seed,
                                 "command": "pisml " + " ".join(sys.argv[1:])})
    if args.noisy_inputs and args.snr_db is None:
        raise UserError("--noisy-inputs needs --snr-db (the noise level)")
    if args.snr_db is not None:
        dataset = add_measurement_noise(dataset, args.snr_db, seed=args.seed + 1_000_003,
                                        include_inputs=args.noisy_inputs)
    out = write_dataset(dataset, args.out)
    noise = "clean" if args.snr_db is None else f"{args.snr_db:g} dB SNR{' on inputs too' if args.noisy_inputs else ''}"
    print(f"wrote {out}: {len(dataset)} trajectories x {len(dataset.trajectories[0])} samples "
          f"({args.scenario}, {noise}"
          f"{', effects ' + ','.join(plant.effects) if plant.effects else ''})")
    return 0


def _simulate_model(args) -> int:
    from .analysis.metrics import relative_error, vector_relative_error
    from .data import concat_datasets, read_dataset, write_dataset
    from .model import ExplicitModel
    from .signals import SCORED_STATES

    if not args.data:
        raise UserError("--model needs --data PATH (the trajectories whose inputs and initial states are replayed)")
    if args.scenario:
        raise UserError("--scenario and --model exclude each other")
    model = ExplicitModel.load(args.model)
    data = concat_datasets([read_dataset(p) for p in args.data])
    missing = [n for n in model.state_names + model.input_names if n not in data.state_names + data.input_names]
    if missing:
        raise UserError(f"--data {' '.join(args.data)}: lacks the model's signals {missing}")
    pred = model.simulate(data, method=args.solver)
    cols = data.state_index(model.state_names)
    # the paper's scored states, where the model has them: ε per state and with the four taken together
    # (analysis.metrics: the anchors are on the second scale)
    scored = [model.state_names.index(n) for n in SCORED_STATES] if set(SCORED_STATES) <= set(model.state_names) else []
    for tr, pr in zip(data, pred):
        truth = tr.x[:, cols]
        err = relative_error(pr.x, truth)
        line = f"trajectory {tr.traj_id}: relative error {err:.4g} % (all states)"
        if scored:
            pair = pr.x[:, scored], truth[:, scored]
            line += (f"; {', '.join(SCORED_STATES)}: {relative_error(*pair):.4g} % per state, "
                     f"{vector_relative_error(*pair):.4g} % taken together")
        print(line)
    pred.metadata.update({"model": str(args.model), "command": "pisml " + " ".join(sys.argv[1:])})
    out = write_dataset(pred, args.out)
    print(f"wrote {out}: {len(pred)} predicted trajectories")
    return 0


def cmd_identify(args) -> int:
    import time as _time

    from .analysis.operating_point import identified_input_range
    from .data import concat_datasets, read_dataset
    from .ident import METHODS, ConfigError, IdentConfig, make_estimator, selection_warnings, settings_from_assignments
    from .ident.limiter import limit_in_use, limit_note, readable_equations
    from .ident.noise import noise_note

    if args.method not in METHODS:
        raise UserError(f"--method {args.method}: choose one of {', '.join(METHODS)}")
    try:
        config = IdentConfig.load(args.config, settings_from_assignments(args.set or [], "--set"))
    except ConfigError as err:
        raise UserError(str(err)) from None
    train = concat_datasets([read_dataset(p) for p in args.data])
    smallsignal = concat_datasets([read_dataset(p) for p in args.smallsignal]) if args.smallsignal else None
    if smallsignal is not None and tuple(smallsignal.state_names) != tuple(train.state_names):
        raise UserError(f"--smallsignal: states {list(smallsignal.state_names)} differ from the training data's "
                        f"{list(train.state_names)}")
    out = Path(args.out)
    if out.suffix != ".json":
        raise UserError(f"--out {out}: expected a .json path for the explicit model")
    started = _time.monotonic()
    show = sys.stderr.isatty() and not args.quiet
    last = [0.0]

    def progress(update):
        now = _time.monotonic()
        if args.quiet:
            return
        if update.model is not None or update.stage in ("distillation",) or now - last[0] > (0.5 if show else 5):
            last[0] = now
            losses = " ".join(f"{k}={v:.4g}" for k, v in update.losses.items())
            line = f"[{now - started:6.1f} s] {update.stage:<12} {100 * update.progress:5.1f} % {losses}"
            if show and update.model is None:
                print("\r" + line[:150].ljust(150), end="", file=sys.stderr, flush=True)
            else:
                print(("\r" if show else "") + line[:150].ljust(150 if show else 0), file=sys.stderr, flush=True)

    try:
        est = make_estimator(args.method, config).fit(train, smallsignal, callback=progress)
    except (ConfigError, ValueError) as err:
        raise UserError(str(err)) from None
    if est.explicit_model_ is None:
        print(f"{args.method}: no explicit model (a neural vector field with {est.model_.n_parameters} parameters); "
              f"nothing written", file=sys.stderr)
        return 0
    model = est.explicit_model_
    model.metadata.setdefault("identification", {}).update(
        {"data": [str(p) for p in args.data], "smallsignal": [str(p) for p in args.smallsignal or []],
         "metrics": {k: float(v) for k, v in est.metrics_.items()}})
    model.save(out)
    nonzero = int((model.coefficients != 0).sum())
    inside = model.n_parameters - nonzero
    print(f"{args.method}: {nonzero} nonzero coefficients over {len(model.terms)} terms"
          + (f" and {inside} numbers inside its terms" if inside else "")
          + f", {est.metrics_['seconds']:.1f} s; wrote {out}")
    covered = ", ".join(f"{name} {low:.4g}-{high:.4g}" for name, (low, high) in
                        (identified_input_range(model) or {}).items())
    selection = model.metadata.get("selection") or {}
    if covered:
        # analyses outside this range extrapolate (pisml analyse says so)
        print(f"  identified on {covered}" + (
            f"; chosen: {selection['chosen']} (free-run error on the records "
            f"{selection['training_error_pct'][selection['chosen']]:.3g} %)" if selection.get("chosen") else ""))
    training = model.metadata.get("training") or {}
    if "records_at_rest" in training:
        resting, records = training["records_at_rest"], training["trajectories"]
        print(f"  training records starting at rest: {resting} of {records}" + (
            "" if resting else " (constant inputs and still states before the first input change): the "
            "selection's equilibrium check and the stability prior rest on the small-signal records alone"))
    noise = noise_note(model)
    if noise:
        print(f"  {noise}")
    note = limit_note(model)
    if note:
        print(f"  {'caution: ' if limit_in_use(model) is False else ''}{note}")
    for warning in selection_warnings(model):
        print(f"  caution: {warning}")
    if args.equations:
        for line in readable_equations(model, digits=5):
            print("  " + line)
    return 0


def cmd_data_info(args) -> int:
    from .data import read_dataset

    summary = read_dataset(args.path).summary()
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return 0
    print(f"{args.path}: {summary['trajectories']} trajectories, {summary['samples']} samples, "
          f"dt = {summary['dt']:.6g} s ({1 / summary['dt']:.6g} Hz)")
    durations = summary["durations"]
    print(f"  durations: {min(durations):.4g}-{max(durations):.4g} s; ids {summary['trajectory_ids']}")
    print(f"  states ({len(summary['states'])}): {', '.join(summary['states'])}")
    print(f"  inputs ({len(summary['inputs'])}): {', '.join(summary['inputs'])}")
    width = max(len(n) for n in summary["ranges"])
    for name, (lo, hi) in summary["ranges"].items():
        print(f"  {name:<{width}}  [{lo: .5g}, {hi: .5g}]")
    meta = summary["metadata"]
    for key in ("scenario", "snr_db", "effects", "generator"):
        if meta.get(key) not in (None, {}, ""):
            print(f"  {key}: {meta[key]}")
    return 0


def _print_uncertainty(report: dict, whose: str) -> None:
    """The lines on how far the data pin a report's verdict: its ``uncertainty`` (noise alone) and
    its ``alternatives`` (the fit's other candidates that reproduced the records about as well)."""
    from .analysis.operating_point import alternatives_note

    uncertainty = report.get("uncertainty")
    if uncertainty:
        low, high = uncertainty["max_real_interval"]
        print(f"  {whose} pin the largest real part to {low:.4g} .. {high:.4g} 1/s (2 std, noise alone): "
              + ("stability undetermined by the data" if uncertainty["verdict"] == "undetermined"
                 else f"{uncertainty['verdict']} either way"))
    alternatives = report.get("alternatives")
    if alternatives:
        note = alternatives_note(alternatives)
        print(f"  caution: {note}" if note else
              f"  the {len(alternatives['candidates'])} other candidate(s) that fit the records about as well "
              f"give the same verdict")


def cmd_analyse(args) -> int:
    from .analysis.operating_point import (coverage_note, operating_point_report, other_equilibria_note,
                                           ug_stability_margin)
    from .plant import EquilibriumError

    from .model import EquilibriumNotFound, ExplicitModel

    if args.model == "plant":
        system = _load_plant(args)
    else:
        if args.params or args.effect or args.effect_param:
            raise UserError("--params/--effect/--effect-param apply to --model plant only")
        system = ExplicitModel.load(args.model)
        if tuple(system.input_names) != ("ug", "theta_g") and len(system.input_names) != 2:
            raise UserError(f"--model {args.model}: analysis needs two inputs (grid magnitude, phase), "
                            f"the model has {list(system.input_names)}")
    for name, value in (("--ug", args.ug), ("--theta-g", args.theta_g)):
        if not math.isfinite(value):
            raise UserError(f"{name} must be finite, got {value}")
    if args.ug <= 0:
        raise UserError(f"--ug must be > 0, got {args.ug}")
    try:
        report = operating_point_report(system, args.ug, args.theta_g)
    except (EquilibriumError, EquilibriumNotFound) as err:
        raise UserError(str(err)) from None
    if args.margin:
        report.update(ug_stability_margin(system, args.ug, args.theta_g))
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    op = report["operating_point"]
    print(f"operating point ug = {op['ug']:g} p.u., theta_g = {op['theta_g']:g} rad: "
          f"{'STABLE' if report['stable'] else 'UNSTABLE'} (max real part {report['max_real']:.4g} 1/s, "
          f"min damping {report['min_damping']:.3f})")
    _print_uncertainty(report, "the data")
    print(f"  {'eigenvalue (1/s)':>28}  {'damping':>8}  {'freq (Hz)':>10}  dominant states")
    for (re, im), zeta, freq, dom in zip(report["eigenvalues"], report["damping"], report["frequencies_hz"],
                                          report["dominant_states"]):
        print(f"  {re:12.4f} {im:+13.4f}j  {zeta:8.4f}  {freq:10.3f}  {', '.join(dom)}")
    if args.margin:
        coverage = report.get("data_coverage")
        low, high = coverage["input_range"].get(system.input_names[0], (-math.inf, math.inf)) if coverage else (
            -math.inf, math.inf)
        bounds = [f"{b:.4g}" + ("" if low <= b <= high else " (extrapolated)") for b in report["boundaries"]]
        print(f"  stability boundaries in ug: [{', '.join(bounds)}]; margin {report['ug_margin']:.4f} p.u.")
        if report.get("undetermined_ug"):
            stretches = ", ".join(f"{low:.3g}-{high:.3g}" if high > low else f"{low:.3g}"
                                  for low, high in report["undetermined_ug"])
            print(f"  stability not decided by the data (largest real part within 2 std of 0) at ug {stretches}")
    note = coverage_note(report.get("data_coverage"))
    if note:
        print(f"  note: {note}")
    for line in other_equilibria_note(report):
        print(f"  caution: {line}")
    if args.model != "plant":
        from .ident import selection_warnings

        for warning in selection_warnings(system):  # what the identification found wrong with the model
            print(f"  caution: {warning}")
    return 0


def _vary_values(text: str) -> tuple[str, list[float]]:
    """``PATH=v1,v2,...`` or ``PATH=start:stop:points`` -> (PATH, values)."""
    import numpy as np

    path, sep, spec = text.partition("=")
    if not sep or not path or not spec:
        raise UserError(f"--vary {text!r}: expected PATH=v1,v2,... or PATH=start:stop:points")
    try:
        if ":" in spec:
            start, stop, points = spec.split(":")
            if int(points) < 2:
                raise ValueError("points must be >= 2")
            values = [float(v) for v in np.linspace(float(start), float(stop), int(points))]
        else:
            values = [float(v) for v in spec.split(",")]
    except ValueError as err:
        raise UserError(f"--vary {text!r}: {err}") from None
    if not all(math.isfinite(v) for v in values):
        raise UserError(f"--vary {text!r}: values must be finite")
    return path, values


def _microgrid_transient(args, config, build, microgrid, inputs) -> dict:
    """``pisml microgrid --step/--duration/--out``: the time response from the operating point
    through the steps (each a network with one setting changed from then on)."""
    import numpy as np

    from .analysis.microgrid import simulate_stages, with_setting
    from .fileio import atomic_write_text

    steps = []
    for item in args.step or []:
        setting, sep, when = item.rpartition("@")
        path, eq, value = setting.partition("=")
        try:
            steps.append((float(when), path, float(value)))
        except ValueError:
            raise UserError(f"--step {item!r}: expected PATH=VALUE@SECONDS, e.g. buses.pcc.load.r=0.6@0.02") from None
        if not sep or not eq or not path or not (math.isfinite(steps[-1][0]) and steps[-1][0] > 0):
            raise UserError(f"--step {item!r}: expected PATH=VALUE@SECONDS with SECONDS > 0")
    steps.sort()
    duration = args.duration if args.duration is not None else max([0.06] + [t + 0.04 for t, _, _ in steps])
    if not (math.isfinite(duration) and duration > 0) or any(t >= duration for t, _, _ in steps):
        raise UserError(f"--duration {duration:g}: must be > 0 s and after every --step")
    stages, cfg, start = [], config, 0.0
    grid = microgrid
    for when, path, value in steps:
        stages.append((grid, when - start))
        cfg = with_setting(cfg, path, value)
        grid, start = build(cfg)[0], when
    stages.append((grid, duration - start))
    t, x = simulate_stages(stages, microgrid.equilibrium(*inputs), inputs)
    currents = microgrid.injected_currents(x)
    if args.out:
        names = ["t"] + [f"{u.name}.i_{ax}" for u in microgrid.units for ax in "DQ"] + list(microgrid.state_names)
        table = np.column_stack([t, currents.reshape(len(t), -1), x])
        lines = [",".join(names)] + [",".join(f"{v:.10g}" for v in row) for row in table]
        atomic_write_text(Path(args.out), "\n".join(lines) + "\n")
    magnitude = np.linalg.norm(currents, axis=-1)
    return {"duration": duration, "steps": [{"t": t_, "path": p_, "value": v_} for t_, p_, v_ in steps],
            "out": args.out or "", "samples": int(len(t)),
            "current_range": {u.name: [float(magnitude[:, k].min()), float(magnitude[:, k].max())]
                              for k, u in enumerate(microgrid.units)}}


def cmd_microgrid(args) -> int:
    from .analysis.microgrid import (MicrogridError, microgrid_from_config, microgrid_report, parameter_sweep,
                                     read_microgrid_config, unit_other_equilibria_note)
    from .model import EquilibriumNotFound
    from .plant import EquilibriumError

    path = Path(args.config)
    try:
        config = read_microgrid_config(path)
    except MicrogridError as err:
        raise UserError(f"--config {err}") from None
    source = str(path)
    if args.ug is not None or args.theta_g is not None:
        grid = dict(config.get("grid") or {}) if isinstance(config, dict) else {}
        grid.update({k: v for k, v in (("ug", args.ug), ("theta_g", args.theta_g)) if v is not None})
        config = dict(config, grid=grid) if isinstance(config, dict) else config
    for item in args.model or []:
        name, sep, model_path = item.partition("=")
        units = config.get("units") if isinstance(config, dict) else None
        matches = [k for k, entry in enumerate(units or [])
                   if isinstance(entry, dict) and str(entry.get("name")) == name]
        if not sep or not model_path or not matches:
            known = [str(entry.get("name")) for entry in units or [] if isinstance(entry, dict)]
            raise UserError(f"--model {item!r}: expected UNIT=PATH with UNIT one of the configuration's units {known}")
        units = list(units)
        entry = {k: v for k, v in units[matches[0]].items() if k != "plant"}
        entry["model"] = str(Path(model_path).resolve())
        units[matches[0]] = entry
        config = dict(config, units=units)
    loaded: dict = {}

    def build(cfg):
        return microgrid_from_config(cfg, base_dir=path.parent, source=source, loaded=loaded)

    try:
        microgrid, inputs = build(config)
        report = microgrid_report(microgrid, *inputs, modes=args.modes)
        if args.vary:
            vary_path, values = _vary_values(args.vary)
            report["sweep"] = parameter_sweep(config, vary_path, values, base_dir=path.parent, loaded=loaded,
                                              source=source)
        if args.step or args.out:
            report["simulation"] = _microgrid_transient(args, config, build, microgrid, inputs)
    except (MicrogridError, ModelFormatError, EquilibriumError, EquilibriumNotFound) as err:
        raise UserError(str(err)) from None
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    op = report["operating_point"]
    where = (f"islanded, frequency {report['frequency_pu']:.5f} p.u. (the network's frame turns with unit "
             f"{microgrid.units[0].name})" if microgrid.islanded
             else f"grid source {op['ug']:g} p.u., {op['theta_g']:g} rad")
    print(f"microgrid: {len(microgrid.units)} units, {len(microgrid.buses)} buses, {len(microgrid.lines)} lines, "
          f"{microgrid.n_states} states; {where}: "
          f"{'STABLE' if report['stable'] else 'UNSTABLE'} (max real part {report['max_real']:.4g} 1/s, "
          f"min damping {report['min_damping']:.3f})")
    _print_uncertainty(report, "the identified units' data")
    for unit in report["units"]:
        line = (f"  unit {unit['name']} ({unit['kind']}) at bus {unit['bus']}: sees {unit['ug']:.4f} p.u., "
                f"{unit['theta_g']:.4f} rad; delivers P {unit['p']:.4f}, Q {unit['q']:.4f} p.u.")
        print(line + (f"; {unit['note']}" if unit.get("note") else ""))
        for note in unit_other_equilibria_note(unit):
            print(f"    caution: {note}")
    print("  least-damped modes (share of each unit in the mode):")
    for mode in report["weakest_modes"]:
        re, im = mode["eigenvalue"]
        shares = ", ".join(f"{name} {share:.0%}" for name, share in mode["unit_shares"].items() if share >= 0.005)
        print(f"  {re:12.4f} {im:+13.4f}j  damping {mode['damping']:.4f}, {mode['frequency_hz']:.3f} Hz: {shares}"
              + (f"\n      caution: {mode['note']}" if mode.get("note") and im >= 0 else ""))  # once per pair
    if "sweep" in report:
        sweep = report["sweep"]
        print(f"  sweep of {sweep['parameter']}:")
        for row in sweep["points"]:
            verdict = "no equilibrium" if row["max_real"] is None else (
                f"max real part {row['max_real']:.4g} 1/s, " + ("stable" if row["max_real"] < 0 else "UNSTABLE"))
            print(f"    {row['value']:.6g}: {verdict}")
        bounds = ", ".join(f"{b:.6g}" for b in sweep["boundaries"]) or "none in the range"
        print(f"  stability boundaries in {sweep['parameter']}: {bounds}")
    if "simulation" in report:
        sim = report["simulation"]
        steps = "; ".join(f"{step['path']} = {step['value']:g} at {step['t']:g} s" for step in sim["steps"]) or "none"
        print(f"  simulated {sim['duration']:g} s (steps: {steps}) -> {sim['out'] or 'not written (--out)'}")
        for name, (low, high) in sim["current_range"].items():
            print(f"    unit {name}: injected current magnitude {low:.4f} .. {high:.4f} p.u.")
    for unit in microgrid.units:
        from .ident import selection_warnings

        for warning in selection_warnings(unit.system):
            print(f"  caution ({unit.name}): {warning}")
    return 0


def cmd_gap(args) -> int:
    from .data import concat_datasets, read_dataset
    from .gap import GapSettings, GapWorkflow, ModelReference, PlantReference
    from .gap.output import summary_lines, write_gap_outputs
    from .model import ExplicitModel
    from .plant import PlantParameters, load_parameters

    data = concat_datasets([read_dataset(p) for p in args.data])
    if args.model:
        model = ExplicitModel.load(args.model)
        missing = [n for n in model.state_names + model.input_names if n not in data.state_names + data.input_names]
        if missing:
            raise UserError(f"--model {args.model}: the data lacks the model's signals {missing}")
        reference = ModelReference(model)
    else:
        reference = PlantReference(load_parameters(args.params) if args.params else PlantParameters())
        if tuple(data.state_names) != reference.state_names:
            raise UserError(f"the plant reference needs the states {list(reference.state_names)} in this order; "
                            f"the data has {list(data.state_names)}")
    if args.max_effects < 0:
        raise UserError(f"--max-effects must be >= 0, got {args.max_effects}")
    log = (lambda text: None) if args.quiet else (lambda text: print(f"[gap] {text}", flush=True))
    flow = GapWorkflow(reference, GapSettings(max_effects=args.max_effects), log=log)
    report = flow.run(data)
    paths = write_gap_outputs(flow, report, data, args.out)
    for line in summary_lines(report):
        print(line)
    print(f"wrote {paths['report']}, {paths['figure']}, {paths['augmented']}")
    return 0


def cmd_effects(args) -> int:
    for spec in EFFECTS.values():
        print(f"{spec.name}: {spec.description}")
        for key, meaning in spec.meanings.items():
            default = spec.defaults.get(key)
            print(f"    {spec.name}.{key}  {meaning}" + (f" [default {default:g}]" if default is not None else ""))
    return 0


def cmd_demo(args) -> int:
    from .ros.demo import run_demo

    if not args.timeout > 0:
        raise UserError(f"--timeout must be > 0 s, got {args.timeout}")
    if args.method is not None:
        from .ident import METHODS

        if args.method not in METHODS:
            raise UserError(f"--method {args.method!r} is not one of {', '.join(METHODS)}")
    return run_demo(Path(args.out), quiet=args.quiet, method=args.method, timeout=args.timeout)


def cmd_record(args) -> int:
    from .ros.recording import record

    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if Path(args.out).exists():
        raise UserError(f"--out {args.out}: exists (choose a new directory)")
    print(f"recording {', '.join(args.topics)} into {args.out}"
          f"{f' for {args.duration:g} s' if args.duration else ' until Ctrl-C'}", flush=True)
    counts = record(args.topics, args.out, duration=args.duration, storage=args.storage,
                    log=lambda text: print(text, flush=True))
    print(f"wrote {args.out}: " + ", ".join(f"{topic} {n} messages" for topic, n in counts.items()), flush=True)
    return 0


def cmd_play(args) -> int:
    from .ros.recording import play

    if not args.rate >= 0:
        raise UserError(f"--rate must be >= 0, got {args.rate}")
    if args.wait_for_subscribers < 0:
        raise UserError(f"--wait-for-subscribers must be >= 0, got {args.wait_for_subscribers}")
    n = play(args.bag, rate=args.rate, loop=args.loop, topics=args.topics,
             wait_for_subscribers=args.wait_for_subscribers, log=lambda text: print(text, flush=True))
    print(f"published {n} messages", flush=True)
    return 0


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pisml", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("simulate", help="simulate the virtual HIL on a scenario of the paper's protocol, "
                                        "or replay measured inputs through an explicit model")
    p.add_argument("--scenario", choices=["train", "test", "smallsignal"])
    p.add_argument("--model", metavar="MODEL.json", help="replay --data through this explicit model instead")
    p.add_argument("--data", action="append", metavar="PATH", help="with --model: CSV or bag (repeatable)")
    _add_plant_options(p)
    p.add_argument("--snr-db", type=float, help="add per-channel measurement noise at this SNR (dB)")
    p.add_argument("--noisy-inputs", action="store_true",
                   help="with --snr-db: the noise on the grid inputs (ug, theta_g) too, not on the states only")
    p.add_argument("--seed", type=int, default=0, help="random seed (scenario and noise)")
    p.add_argument("--n-traj", type=int, help="number of trajectories (default: the protocol's)")
    p.add_argument("--duration", type=float, help="seconds per trajectory (default: 0.04, smallsignal 0.1)")
    p.add_argument("--solver", default="rk4", choices=["rk4", "LSODA", "Radau", "BDF"])
    p.add_argument("--out", required=True, help="PATH.csv (plus PATH.json sidecar) or a bag directory")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("identify", help="identify explicit governing equations from measured trajectories")
    p.add_argument("--data", action="append", required=True, metavar="PATH", help="CSV or bag (repeatable)")
    p.add_argument("--smallsignal", action="append", metavar="PATH",
                   help="small-signal records (CSV or bag, repeatable) for the Jacobian-consistency loss")
    p.add_argument("--method", default="pisml", help="pisml | pisml-nojac | std-sindy | mod-sindy | node")
    p.add_argument("--config", metavar="FILE", help="identification settings (YAML/JSON)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one setting (repeatable)")
    p.add_argument("--out", required=True, metavar="MODEL.json")
    p.add_argument("--equations", action="store_true", help="print the identified equations")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("data", help="inspect datasets")
    data_sub = p.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    q = data_sub.add_parser("info", help="summarise a CSV or bag dataset")
    q.add_argument("path")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_data_info)

    p = sub.add_parser("analyse", aliases=["analyze"], help="equilibrium, eigenvalues and damping at an operating point")
    p.add_argument("--model", default="plant", help="'plant' (the virtual HIL) or an explicit model JSON file")
    _add_plant_options(p)
    p.add_argument("--ug", type=float, required=True, help="grid voltage magnitude (p.u.)")
    p.add_argument("--theta-g", type=float, default=0.0, help="grid voltage phase (rad)")
    p.add_argument("--margin", action="store_true", help="also scan ug for stability boundaries")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_analyse)

    p = sub.add_parser("microgrid", help="assemble inverter models (identified or known) with buses, lines, loads and "
                                         "a grid source; equilibrium, modes, a parameter sweep")
    p.add_argument("--config", required=True, metavar="FILE",
                   help="microgrid description (YAML or JSON; README, 'Microgrid')")
    p.add_argument("--ug", type=float, help="grid source voltage (p.u.; default: the configuration's, else 1.0)")
    p.add_argument("--theta-g", type=float, help="grid source phase (rad; default: the configuration's, else 0)")
    p.add_argument("--model", action="append", metavar="UNIT=PATH",
                   help="take this unit's equations from an explicit model JSON (e.g. target=model.json from "
                        "`pisml identify`) instead of the configuration's (repeatable)")
    p.add_argument("--modes", type=int, default=3, help="least-damped modes to list with each unit's share (default 3)")
    p.add_argument("--vary", metavar="PATH=VALUES", help="sweep one setting, e.g. units.aux.plant.KpV=0.5:3:11 or "
                   "lines.3.x=0.1,0.2,0.4 (list entries by name or index): the largest real part at each value and "
                   "the stability boundaries between them")
    p.add_argument("--step", action="append", metavar="PATH=VALUE@T",
                   help="simulate from the operating point with this setting changed at T seconds, e.g. "
                        "buses.pcc.load.r=0.6@0.02 (a load step; repeatable)")
    p.add_argument("--duration", type=float,
                   help="simulated time (s; default: 40 ms after the last step, at least 60 ms)")
    p.add_argument("--out", help="CSV of the simulation: t, each unit's injected current (network frame), every state")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_microgrid)

    p = sub.add_parser("gap", help="find where a reference model and measurements disagree and name the missing effect")
    p.add_argument("--data", action="append", required=True, metavar="PATH", help="CSV or bag (repeatable)")
    ref = p.add_mutually_exclusive_group(required=True)
    ref.add_argument("--params", metavar="NOMINAL.yaml", help="reference: the virtual HIL with these nameplate values")
    ref.add_argument("--model", metavar="MODEL.json", help="reference: an explicit model")
    p.add_argument("--max-effects", type=int, default=3, help="effects to name at most (greedy)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_gap)

    p = sub.add_parser("effects", help="list the virtual HIL's named effects and their parameters")
    p.set_defaults(func=cmd_effects)

    p = sub.add_parser("demo", help="the main job on the bundled defaults (what `make demo` runs)")
    p.add_argument("--out", default="out/demo", help="report folder")
    p.add_argument("--method", help="identification method (default: the demo's, pisml)")
    p.add_argument("--timeout", type=float, default=1200.0, help="give up after this many seconds")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("record", help="record live topics into a rosbag2 (mcap)")
    p.add_argument("--topics", nargs="+", default=["/pisml/measurement"], metavar="TOPIC",
                   help="topics to record (default /pisml/measurement)")
    p.add_argument("--out", required=True, metavar="DIR", help="bag directory to create")
    p.add_argument("--duration", type=float, help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"])
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("play", help="publish the messages of a rosbag2 on the live graph")
    p.add_argument("bag", metavar="BAG")
    p.add_argument("--rate", type=float, default=1.0, help="x the recorded pace (0 = as fast as possible)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics (default: all)")
    p.add_argument("--wait-for-subscribers", type=int, default=1, metavar="N",
                   help="hold the data until N subscribers of the measurement topic are matched (0 = don't)")
    p.set_defaults(func=cmd_play)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (UserError, DataError, ParameterError, ModelFormatError) as err:
        print(f"pisml: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("pisml: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
