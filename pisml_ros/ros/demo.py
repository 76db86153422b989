"""``pisml demo``: the main job on the bundled defaults, on the live ROS 2 graph.

Three nodes run as separate processes on loopback DDS: the measurement node
plays the bundled training recording (``bags/train_40dB``, 12 trajectories at
40 dB SNR), the identifier learns the equations from it (with the small-signal
records ``bags/smallsignal_40dB``), the analyser publishes the stability of
every model it receives. The demo watches the graph as a plain subscriber,
prints progress, then the discovered equations, eigenvalues and margins, and
writes the report folder: ``model.json``, ``equations.txt``, ``stability.json``,
figures (model vs measurement on the test recording ``bags/test_clean``,
eigenvalues of model vs plant, coefficients, training curves, the plant's
stability map) and ``logs/`` of the nodes.

Node parameters come from ``config/pisml.yaml`` (identification settings in the
identifier's ``method``/``overrides``), with the demo's sources and folders.
"""
from __future__ import annotations

import itertools
import json
import math
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
NODES = ("analyser", "identifier", "measurement")
MICROGRID_CONFIG = "config/microgrid.yaml"
MICROGRID_VARY = ("units.aux1.plant.mp", (0.05, 0.1, 0.15, 0.2, 0.25, 0.3))  # the boundary the demo reports
UG_POINTS = [0.4, 0.8, 1.0, 1.2]


class DemoError(RuntimeError):
    """The demo cannot go on; the message says why (and where the logs are)."""


def _find(relative: str) -> Path | None:
    for base in (ROOT, Path.cwd(), Path(sys.prefix) / "share" / "pisml_ros"):
        if (base / relative).exists():
            return (base / relative).resolve()
    return None


def _bags(out: Path, say) -> dict:
    """The bundled recordings; simulated into ``out/data`` when this install has none."""
    names = {"train": "train_40dB", "smallsignal": "smallsignal_40dB", "test": "test_clean"}
    found = {key: _find(f"bags/{name}") for key, name in names.items()}
    if all(found.values()):
        return found
    from ..data import write_bag
    from ..plant import InverterPlant
    from ..plant.noise import add_measurement_noise
    from ..plant.scenarios import generate, schedules_for

    say("bundled recordings not found: simulating them with the virtual HIL")
    for key, snr in (("train", 40.0), ("smallsignal", 40.0), ("test", None)):
        if found[key] is None:
            schedules, duration = schedules_for(key, seed=0)
            data = generate(InverterPlant(), schedules, duration, metadata={"scenario": key, "seed": 0})
            if snr:
                data = add_measurement_noise(data, snr, seed=1_000_003)
            found[key] = write_bag(data, out / "data" / names[key])
    return found


def _params(out: Path, bags: dict, method: str | None) -> tuple[Path, dict]:
    """The node parameter file of the demo: config/pisml.yaml with the demo's sources and folders."""
    import yaml

    base = _find("config/pisml.yaml")
    params = yaml.safe_load(base.read_text()) if base else {}
    section = {name: dict((params.get(name) or {}).get("ros__parameters") or {}) for name in NODES}
    section["measurement"].update(source="bag", path=str(bags["train"]), rate=1.0, loop=False,
                                  wait_for_subscribers=1, start_delay=0.5)
    section["identifier"].update(min_trajectories=12, retrain_policy="once", smallsignal_path=str(bags["smallsignal"]),
                                 output_dir=str(out / "identifier"), initial_model="")
    if method:
        section["identifier"]["method"] = method
    section["identifier"].setdefault("method", "pisml")
    section["analyser"].update(ug_points=UG_POINTS, analyse_plant=False, output_dir=str(out / "analyser"))
    microgrid = _find(MICROGRID_CONFIG)
    # the identified inverter also as the target of the paper's 3-bus microgrid (/pisml/microgrid)
    section["analyser"].update(microgrid_config=str(microgrid) if microgrid else "", microgrid_unit="target")
    path = out / "params.yaml"
    path.write_text(yaml.safe_dump({name: {"ros__parameters": values} for name, values in section.items()},
                                   sort_keys=False))
    return path, section


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join("    " + line for line in path.read_text().splitlines()[-lines:])
    except OSError:
        return "    (no log)"


class Graph:
    """The three node processes and the demo's own subscriber node."""

    def __init__(self, out: Path, params: Path, say):
        self.out, self.params, self.say = out, params, say
        self.logs = out / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}
        self.models, self.reports, self.loci, self.microgrids, self.diags = [], [], [], [], {}

    def start(self, env):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from pisml_msgs.msg import IdentifiedModel, StabilityReport
        from std_msgs.msg import String

        from .common import latched_qos

        rclpy.init(args=[sys.argv[0]])
        self.node = rclpy.create_node("pisml_demo")
        self.node.create_subscription(IdentifiedModel, "/pisml/model", self.models.append, latched_qos())
        # reports and loci in one arrival order: a model's root locus follows its reports
        arrival = itertools.count()
        self.node.create_subscription(StabilityReport, "/pisml/stability",
                                      lambda msg: self.reports.append((next(arrival), msg)), latched_qos(32))
        self.node.create_subscription(String, "/pisml/root_locus",
                                      lambda msg: self.loci.append((next(arrival), msg)), latched_qos())
        self.node.create_subscription(String, "/pisml/microgrid",
                                      lambda msg: self.microgrids.append((next(arrival), msg)), latched_qos())
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)
        for name in NODES:
            log = open(self.logs / f"{name}.log", "w")
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", f"pisml_ros.ros.{name}", "--ros-args", "--params-file", str(self.params)],
                stdout=log, stderr=subprocess.STDOUT, env=env)
            if name == "identifier":
                self.wait_for_nodes(("analyser", "identifier"), 90.0)  # the data starts once they listen
        self.wait_for_nodes(NODES, 60.0)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            self.diags[status.name] = (status, {kv.key: kv.value for kv in status.values})

    def check_alive(self):
        for name, proc in self.procs.items():
            if proc.poll() is not None and not (name == "measurement" and proc.returncode == 0):
                raise DemoError(f"the {name} node stopped (exit status {proc.returncode}); the end of "
                                f"{self.logs / (name + '.log')}:\n{_tail(self.logs / (name + '.log'))}")

    def spin(self, seconds: float):
        import rclpy

        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=min(0.05, max(deadline - time.monotonic(), 0.0)))

    def wait_for_nodes(self, names, timeout: float):
        deadline = time.monotonic() + timeout
        while True:
            self.check_alive()
            up = set(self.node.get_node_names())
            missing = [n for n in names if n not in up]
            if not missing:
                return
            if time.monotonic() > deadline:
                raise DemoError(f"node(s) {missing} did not come up within {timeout:g} s; logs in {self.logs}:\n" +
                                "\n".join(f"  {n}:\n{_tail(self.logs / (n + '.log'))}" for n in missing))
            self.spin(0.2)

    def stop(self):
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in self.procs.values():
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if getattr(self, "node", None) is not None:
            import rclpy

            self.node.destroy_node()
            rclpy.try_shutdown()


def _progress_line(values: dict) -> str:
    stage, progress = values.get("stage", "?"), float(values.get("progress", 0) or 0)
    losses = ", ".join(f"{k[5:]} {float(v):.3g}" for k, v in values.items() if k.startswith("loss."))
    epoch = f", epoch {values['epoch']}" if values.get("epoch", "0") not in ("0", "") else ""
    return f"identifier: {stage} {progress * 100:3.0f} %{epoch}{'; ' + losses if losses else ''}"


def _watch(graph: Graph, ug_points, timeout: float, say, microgrid: bool = False):
    """Wait for the final model and its reports at every operating point (and its root locus)."""
    from .conversions import message_metrics

    deadline = time.monotonic() + timeout
    seen_models, last_line, last_stage, last_time, announced = set(), "", None, 0.0, False
    while True:
        graph.spin(0.25)
        graph.check_alive()
        for msg in graph.models:
            key = (msg.model_id, msg.stage, message_metrics(msg).get("final"))
            if key not in seen_models:
                seen_models.add(key)
                kind = "explicit equations" if msg.model_json else "no explicit form"
                say(f"model {msg.model_id} on /pisml/model: stage {msg.stage}, {msg.n_parameters} parameters "
                    f"({kind})")
        meas = graph.diags.get("pisml: measurement")
        if meas and meas[0].message == "done" and not announced:
            announced = True
            say(f"measurement: {meas[1].get('published_samples')} samples published")
        ident = graph.diags.get("pisml: identifier")
        if ident:
            line, stage = _progress_line(ident[1]), ident[1].get("stage")
            if line != last_line and (stage != last_stage or time.monotonic() - last_time > 3.0):
                say(line)
                last_line, last_stage, last_time = line, stage, time.monotonic()
            if ident[1].get("stage") == "failed":
                raise DemoError(f"identification failed: {ident[1].get('last_error')}")
        finals = [m for m in graph.models if message_metrics(m).get("final") == 1.0]
        if finals:
            final = finals[-1]
            reports, locus = final_analysis(final, graph.reports, graph.loci)
            if not final.model_json:
                return final, {}, None, None
            grid = final_analysis(final, graph.reports, graph.microgrids)[1] if microgrid else None
            if all(round(ug, 6) in reports for ug in ug_points) and locus is not None and (grid or not microgrid):
                return final, reports, locus, grid
        if time.monotonic() > deadline:
            raise DemoError(f"no final model and stability reports within {timeout:g} s (last: {last_line}); "
                            f"logs in {graph.logs}")


def final_analysis(final, reports: list, loci: list) -> tuple[dict, dict | None]:
    """The analyser's StabilityReports on the final model by ug, and its root locus (None until it came).

    ``reports`` and ``loci`` are ``(arrival order, message)`` pairs (``loci`` may be another
    JSON topic the analyser publishes after the reports, such as /pisml/microgrid). Every stage of an identifier
    run shares its model_id: the final model's reports are the ones stamped after the final model
    was published, its locus the first one with its model_id after them (the analyser publishes a
    model's locus after its reports). Before, the demo could print the reports on a run's first
    explicit model as the final model's (stop 18: "UNSTABLE, +15 1/s" at every ug for a final model
    stable at all four).
    """
    published = _nanoseconds(final.header.stamp)
    by_ug, newest = {}, None
    for order, msg in reports:
        if msg.model_id == final.model_id and _nanoseconds(msg.header.stamp) >= published:
            by_ug[round(float(msg.input_values[0]), 6)] = msg
            newest = order
    if newest is None:
        return by_ug, None
    for order, msg in loci:
        locus = json.loads(msg.data)
        if order > newest and locus.get("model_id") == final.model_id:
            return by_ug, locus
    return by_ug, None


def _nanoseconds(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _plant_part(plant):
    from ..analysis.margins import stability_boundaries
    from ..analysis.operating_point import max_real_part, operating_point_report

    reports = {f"{ug:g}": operating_point_report(plant, ug) for ug in (0.2, 0.4, 0.8, 1.0, 1.2)}
    grid = np.round(np.arange(0.2, 1.3001, 0.05), 3)
    scan = np.array([max_real_part(plant, ug) for ug in grid])
    boundaries = stability_boundaries(lambda g: max_real_part(plant, g), grid)
    return {"model_id": "plant", "operating_points": reports, "scan": {"ug": grid.tolist(), "max_real": scan.tolist()},
            "ug_boundaries": boundaries}


def _clean(obj):
    """JSON-ready: NaN/inf as null."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def run_demo(out: Path, quiet: bool = False, method: str | None = None, timeout: float = 1200.0) -> int:
    from .dds_env import configure_loopback_dds

    started = time.monotonic()

    def say(text):
        if not quiet:
            print(f"[demo {time.monotonic() - started:5.1f} s] {text}", flush=True)

    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    # the demo's graph: loopback DDS, a domain of its own unless the user chose one
    configure_loopback_dds()
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    env = dict(os.environ)
    bags = _bags(out, say)
    params, section = _params(out, bags, method)
    say(f"nodes measurement (bag {bags['train'].name}), identifier (method {section['identifier']['method']}, "
        f"small-signal {bags['smallsignal'].name}), analyser (ug {UG_POINTS}) on loopback DDS, "
        f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}; parameters {params}")
    graph = Graph(out, params, say)
    try:
        graph.start(env)
        say("all three nodes are up; measurements flowing")
        final, reports, locus, grid = _watch(graph, UG_POINTS, timeout - (time.monotonic() - started), say,
                                             microgrid=bool(section["analyser"]["microgrid_config"]))
    except DemoError as err:
        print(f"demo: {err}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        print("demo: interrupted", file=sys.stderr, flush=True)
        return 130
    finally:
        graph.stop()
    say(f"final model {final.model_id} received after {time.monotonic() - started:.0f} s; nodes stopped")
    code = _report(out, final, reports, locus, bags, say, quiet)
    if code == 0 and grid is not None:
        try:
            _microgrid_part(out, final, grid, Path(section["analyser"]["microgrid_config"]), say)
        except Exception as err:  # the microgrid is an extra: its failure is reported, the demo's result stands
            say(f"microgrid analysis failed: {type(err).__name__}: {err}")
    return code


def _microgrid_part(out: Path, final, grid: dict, config_path: Path, say) -> None:
    """The analyser's report on the identified inverter inside the microgrid of ``config_path``,
    beside the same microgrid around the plant, and the boundary in an auxiliary unit's droop
    gain for both (``microgrid.json``)."""
    from ..analysis.microgrid import (microgrid_from_config, microgrid_report, parameter_sweep, read_microgrid_config,
                                      with_unit_model)
    from ..analysis.operating_point import alternatives_note
    from .conversions import model_from_message

    config = read_microgrid_config(config_path)
    with_model, loaded = with_unit_model(config, str(grid.get("unit", "target")), model_from_message(final),
                                         config_path.parent)
    path, values = MICROGRID_VARY

    def boundary(cfg):
        return parameter_sweep(cfg, path, values, config_path.parent, loaded=loaded)["boundaries"]

    plant_grid, inputs = microgrid_from_config(config, config_path.parent)
    truth = microgrid_report(plant_grid, *inputs)
    part = {"config": str(config_path), "model": json.loads(json.dumps(grid)), "plant": truth,
            "vary": path, "boundaries": {"model": boundary(with_model), "plant": boundary(config)}}
    (out / "microgrid.json").write_text(json.dumps(_clean(part), indent=1) + "\n")
    names = ", ".join(u["name"] for u in truth["units"])
    say(f"in the microgrid of {config_path.name} (units {names}; the identified model as unit {grid.get('unit')}, "
        f"against the plant there):")
    if "error" in grid:
        say(f"  model: no operating point ({grid['error']}) | plant: "
            f"{'stable' if truth['stable'] else 'UNSTABLE'}, max Re λ = {truth['max_real']:+.3f} 1/s")
    else:
        mode = grid["weakest_modes"][0]
        shares = ", ".join(f"{k} {v:.0%}" for k, v in mode["unit_shares"].items() if v >= 0.01)
        say(f"  model {'stable' if grid['stable'] else 'UNSTABLE'}, max Re λ = {grid['max_real']:+.3f} 1/s (weakest "
            f"mode {mode['eigenvalue'][0]:+.3f} {mode['eigenvalue'][1]:+.3f}j: {shares}) | plant "
            f"{'stable' if truth['stable'] else 'UNSTABLE'}, max Re λ = {truth['max_real']:+.3f} 1/s")
        rivals = alternatives_note(grid.get("alternatives"))
        if rivals:  # the identification's other candidates, as good on the records, say otherwise
            say(f"  caution: {rivals}")
    bounds = part["boundaries"]
    fmt = lambda values_: ", ".join(f"{b:.4f}" for b in values_) or "none"  # noqa: E731
    say(f"  stability boundary in {path} ({values[0]:g}-{values[-1]:g}): model {fmt(bounds['model'])} | plant "
        f"{fmt(bounds['plant'])}")


def _report(out: Path, final, reports: dict, locus, bags: dict, say, quiet: bool) -> int:
    from ..analysis.metrics import protocol_errors, spectrum_wasserstein
    from ..analysis.operating_point import undetermined_ug_ranges
    from ..data import read_dataset
    from ..ident.limiter import readable_equations
    from ..plant import InverterPlant
    from ..report.figures import plot_spectra, plot_stability_scan, plot_trajectories
    from ..report.identification import plot_coefficients, plot_model_vs_data, plot_training_curves
    from .conversions import message_metrics, model_from_message, stability_dict

    show = (lambda text: None) if quiet else (lambda text: print(text, flush=True))
    plant = InverterPlant()
    plant_part = _plant_part(plant)
    test = read_dataset(bags["test"])
    plot_trajectories(test, out / "test_trajectories.png",
                      title="test recording: sag to 0.4 p.u. at 20 ms (second: 8° jump at 8 ms)")
    plot_stability_scan(np.array(plant_part["scan"]["ug"]), np.array(plant_part["scan"]["max_real"]),
                        out / "stability_scan.png", plant_part["ug_boundaries"])
    metrics = message_metrics(final)
    history_path = out / "identifier" / "history.json"
    history = json.loads(history_path.read_text()) if history_path.is_file() else {}
    plot_training_curves(history, out / "training_curves.png", title=f"{final.model_id}: training")
    if not final.model_json:
        say(f"method gave no explicit model ({final.equations[0] if final.equations else final.stage}); "
            "nothing to analyse")
        return 0
    model = model_from_message(final)
    model.save(out / "model.json")
    (out / "equations.txt").write_text("\n".join(readable_equations(model, digits=6)) + "\n")
    stability = {"model_id": final.model_id,
                 "operating_points": {f"{ug:g}": stability_dict(r) for ug, r in sorted(reports.items())},
                 "root_locus": locus, "ug_boundaries": locus["boundaries"] if locus else [],
                 "metrics": metrics, "plant": plant_part}
    spectra = {}
    for ug in sorted(reports):
        r = reports[ug]
        eig = np.array(r.eigenvalues_real) + 1j * np.array(r.eigenvalues_imag)
        truth = plant.eigenvalues(ug)
        spectra[ug] = (eig, truth)
        stability["operating_points"][f"{ug:g}"]["wasserstein_to_plant"] = \
            spectrum_wasserstein(eig, truth) if len(eig) else math.inf
    errors = {}
    try:
        pred = model.simulate(test)
        errors = protocol_errors(model, test)
        plot_model_vs_data(test, pred, out / "model_vs_measured.png",
                           titles=[f"sag to 0.4 p.u. (OOD after 20 ms): ε_OOD = {errors['ood']:.2f} %",
                                   f"8° jump at 8 ms (IOD before 20 ms): ε_IOD = {errors['iod']:.2f} %"],
                           title=f"{final.model_id} vs measurement (test recording, clean)")
    except Exception as err:  # a model that cannot simulate the test set is reported, not fatal
        say(f"model simulation on the test recording failed: {err}")
    stability["errors_pct"] = errors
    if locus:
        stability["undetermined_ug"] = undetermined_ug_ranges(model, locus["ug"])
    (out / "stability.json").write_text(json.dumps(_clean(stability), indent=1) + "\n")
    if 0.8 in spectra:
        plot_spectra({"plant ug = 0.8": spectra[0.8][1], "model ug = 0.8": spectra[0.8][0]},
                     out / "eigenvalues.png", title=f"eigenvalues at ug = 0.8: plant vs {final.model_id}")
    plot_spectra({f"model ug = {ug:g}": s[0] for ug, s in spectra.items()}, out / "eigenvalues_model.png",
                 title=f"{final.model_id}: eigenvalues at the analysed operating points")
    plot_coefficients(model, out / "coefficients.png", title=f"{final.model_id}: {model.n_parameters} parameters")
    if locus:
        grid = np.array(locus["ug"])
        max_real = np.array([np.nan if v is None else v for v in locus["max_real"]])
        plot_stability_scan(grid, max_real, out / "stability_scan_model.png", locus["boundaries"])

    # ------------------------------------------------------------------ what the user reads
    say(f"identified model {final.model_id}: {model.n_parameters} parameters over {len(model.terms)} terms"
        f" (full equations in {out / 'equations.txt'})")
    for line in readable_equations(model, digits=4):
        n_terms = line.count(" + ") + line.count(" - ") + 1
        show("    " + (line if len(line) <= 160 else line[:150] + f" ... ({n_terms} terms)"))
    if 0.8 in spectra and len(spectra[0.8][0]) == len(spectra[0.8][1]):
        import scipy.optimize

        eig, truth = spectra[0.8]
        rows, cols = scipy.optimize.linear_sum_assignment(np.abs(truth[:, None] - eig[None, :]))
        say("eigenvalues at ug = 0.8 p.u. (1/s), matched: plant | identified model")
        for k in sorted(rows, key=lambda k: (-truth[k].real, -truth[k].imag)):
            a, b = truth[k], eig[cols[list(rows).index(k)]]
            show(f"    {a.real:10.2f} {a.imag:+10.2f}j  |  {b.real:10.2f} {b.imag:+10.2f}j")
    for ug in sorted(reports):
        r = reports[ug]
        truth = plant_part["operating_points"].get(f"{ug:g}")
        plant_text = (f" | plant {'stable' if truth['stable'] else 'UNSTABLE'}, max Re λ = {truth['max_real']:+.3f}"
                      if truth else "")
        if not r.equilibrium_found:
            say(f"ug = {ug:g}: model: {r.message}{plant_text}")
            continue
        open_verdict = " (not decided by the data)" if "not decided by the data" in r.message else ""
        say(f"ug = {ug:g}: model {'stable' if r.stable else 'UNSTABLE'}{open_verdict}, max Re λ = "
            f"{r.max_real_part:+.3f} 1/s, min ζ = {r.min_damping_ratio:.3f}, ug margin {r.ug_margin:.3f} p.u., "
            f"W1 to plant {stability['operating_points'][f'{ug:g}']['wasserstein_to_plant']:.1f}{plant_text}")
    if locus:
        bounds = ", ".join(f"{b:.4f}" for b in locus["boundaries"])
        low, high = locus["ug"][0], locus["ug"][-1]
        say(f"stability boundary in grid voltage (model): ug = {bounds or f'none in [{low:g}, {high:g}]'}")
        open_ranges = stability.get("undetermined_ug")
        if open_ranges:
            stretches = ", ".join(f"{a:.3g}-{b:.3g}" if b > a else f"{a:.3g}" for a, b in open_ranges)
            say(f"  the data do not decide stability at ug {stretches} (the model's largest real part within two "
                f"standard deviations of 0): a boundary there is the model's guess")
    say(f"stability boundary in grid voltage: ug = {', '.join(f'{b:.4f}' for b in plant_part['ug_boundaries'])} p.u. "
        f"(plant)")
    if errors:
        say(f"test recording: ε_IOD = {errors['iod']:.2f} %, ε_OOD = {errors['ood']:.2f} % (per scored state; "
            f"the four states taken together: {errors['iod_vector']:.2f} %, {errors['ood_vector']:.2f} %)")
    say(f"report folder: {out}/ (model.json, equations.txt, stability.json, model_vs_measured.png, eigenvalues.png, "
        f"coefficients.png, training_curves.png, stability_scan*.png, microgrid.json, logs/)")
    return 0
