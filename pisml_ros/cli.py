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
    if args.snr_db is not None:
        dataset = add_measurement_noise(dataset, args.snr_db, seed=args.seed + 1_000_003)
    out = write_dataset(dataset, args.out)
    print(f"wrote {out}: {len(dataset)} trajectories x {len(dataset.trajectories[0])} samples "
          f"({args.scenario}, {'clean' if args.snr_db is None else f'{args.snr_db:g} dB SNR'}"
          f"{', effects ' + ','.join(plant.effects) if plant.effects else ''})")
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


def cmd_analyse(args) -> int:
    from .analysis.operating_point import operating_point_report, ug_stability_margin
    from .plant import EquilibriumError

    if args.model != "plant":
        raise UserError(f"--model {args.model}: only 'plant' (the virtual HIL) is available in this version")
    system = _load_plant(args)
    for name, value in (("--ug", args.ug), ("--theta-g", args.theta_g)):
        if not math.isfinite(value):
            raise UserError(f"{name} must be finite, got {value}")
    if args.ug <= 0:
        raise UserError(f"--ug must be > 0, got {args.ug}")
    try:
        report = operating_point_report(system, args.ug, args.theta_g)
    except EquilibriumError as err:
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
    print(f"  {'eigenvalue (1/s)':>28}  {'damping':>8}  {'freq (Hz)':>10}  dominant states")
    for (re, im), zeta, freq, dom in zip(report["eigenvalues"], report["damping"], report["frequencies_hz"],
                                          report["dominant_states"]):
        print(f"  {re:12.4f} {im:+13.4f}j  {zeta:8.4f}  {freq:10.3f}  {', '.join(dom)}")
    if args.margin:
        print(f"  stability boundaries in ug: {[round(b, 4) for b in report['boundaries']]}; "
              f"margin {report['ug_margin']:.4f} p.u.")
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
    from .demo import run_demo

    return run_demo(Path(args.out), quiet=args.quiet)


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pisml", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("simulate", help="simulate the virtual HIL on a scenario of the paper's protocol")
    p.add_argument("--scenario", required=True, choices=["train", "test", "smallsignal"])
    _add_plant_options(p)
    p.add_argument("--snr-db", type=float, help="add per-channel measurement noise at this SNR (dB)")
    p.add_argument("--seed", type=int, default=0, help="random seed (scenario and noise)")
    p.add_argument("--n-traj", type=int, help="number of trajectories (default: the protocol's)")
    p.add_argument("--duration", type=float, help="seconds per trajectory (default: 0.04, smallsignal 0.1)")
    p.add_argument("--solver", default="rk4", choices=["rk4", "LSODA", "Radau", "BDF"])
    p.add_argument("--out", required=True, help="PATH.csv (plus PATH.json sidecar) or a bag directory")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("data", help="inspect datasets")
    data_sub = p.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    q = data_sub.add_parser("info", help="summarise a CSV or bag dataset")
    q.add_argument("path")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_data_info)

    p = sub.add_parser("analyse", aliases=["analyze"], help="equilibrium, eigenvalues and damping at an operating point")
    p.add_argument("--model", default="plant", help="'plant' (the virtual HIL)")
    _add_plant_options(p)
    p.add_argument("--ug", type=float, required=True, help="grid voltage magnitude (p.u.)")
    p.add_argument("--theta-g", type=float, default=0.0, help="grid voltage phase (rad)")
    p.add_argument("--margin", action="store_true", help="also scan ug for stability boundaries")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_analyse)

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
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)
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
