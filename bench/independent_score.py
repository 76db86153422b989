"""Score explicit model JSON files as an outsider would, with none of pisml_ros's code.

The issue's check: "score the explicit model JSON with my own code — rebuilding f(x, u) from the
JSON alone — on trajectories you have not seen, including spectra at several ug". The scoring
functions here use json, numpy, scipy and sympy only: the model's terms are parsed by sympy and
compiled by ``lambdify``, trajectories are integrated by scipy's LSODA (tolerances far below the
errors scored) with each measured input held over its sample period, the equilibrium is found by
``scipy.optimize.root`` from the plant's, and the Jacobian is sympy's derivative of the rebuilt
field. So this is a second implementation of what ``pisml_ros.analysis`` measures (RK4 with four
substeps per sample; equilibria followed from the records' rest states): trajectories that
disagree mean one of them is wrong; spectra that disagree mean the two found different equilibria
of the model (both valid: a model can have more than one near the plant's).

    make bench-independent
    .venv/bin/python bench/independent_score.py [MODEL.json ...] [--reference DIR] [--write-reference] \
        [--compare] [--out bench/independent_results.json] [--markdown bench/INDEPENDENT_RESULTS.md]

The models default to ``bench/models/*.json`` (written by ``make bench``: the standard plant's
clean and 40 dB models of every method with an explicit model, and the ten 40 dB recordings').
DIR (default ``bench/models/reference``) holds what the truth side provides (``--write-reference``
writes it from the virtual HIL, the only step besides ``--compare`` that uses the package):
``test.csv`` (the protocol's test records: the sag to 0.4 p.u. first, the phase jump last) and
``truth.json`` (the plant's equilibrium and eigenvalues at each ug of the grid). ``--compare``
also scores each model with pisml_ros (the benchmark's figures) and sets the two side by side.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.integrate
import scipy.optimize
import sympy

BENCH = Path(__file__).resolve().parent
MODELS = BENCH / "models"  # written by bench/bench.py
SCORED = ("ig_d", "ig_q", "vc_d", "vc_q")  # DESIGN.md: ε averaged over these
T_SPLIT = 0.02  # IOD window [0, T_SPLIT) of the phase-jump record, OOD [T_SPLIT, end] of the sag
STABLE_UG = (0.2, 0.4, 0.6, 0.8, 1.0, 1.1)  # where the plant is stable (spurious modes counted there)
FUNCTIONS = {"sin": sympy.sin, "cos": sympy.cos, "exp": sympy.exp, "tanh": sympy.tanh, "sqrt": sympy.sqrt,
             "Abs": sympy.Abs, "Min": sympy.Min, "Max": sympy.Max, "sign": sympy.sign}


class RebuiltModel:
    """f(x, u) and its state Jacobian rebuilt from an explicit model JSON (DESIGN.md's contract)."""

    def __init__(self, data: dict):
        if data.get("format") != "pisml-explicit-model/1":
            raise ValueError(f"not an explicit model: format {data.get('format')!r}")
        self.states, self.inputs = list(data["states"]), list(data["inputs"])
        symbols = sympy.symbols(self.states + self.inputs, real=True)
        names = dict(zip(self.states + self.inputs, symbols), **FUNCTIONS)
        terms = [sympy.sympify(t, locals=names) for t in data["terms"]]
        coef = np.asarray(data["coefficients"], dtype=float)
        if coef.shape != (len(terms), len(self.states)):
            raise ValueError(f"coefficients {coef.shape}, expected {(len(terms), len(self.states))}")
        rhs = [sum((sympy.Float(coef[k, j]) * terms[k] for k in range(len(terms)) if coef[k, j] != 0),
                   sympy.Integer(0)) for j in range(len(self.states))]
        x = symbols[:len(self.states)]
        self._f = sympy.lambdify(symbols, rhs, "numpy")
        self._jac = sympy.lambdify(symbols, sympy.Matrix(rhs).jacobian(x), "numpy")
        self.n_parameters = int(np.count_nonzero(coef))

    def f(self, x, u) -> np.ndarray:
        return np.asarray(self._f(*x, *u), dtype=float)

    def jacobian(self, x, u) -> np.ndarray:
        return np.asarray(self._jac(*x, *u), dtype=float)


def read_records(path: Path, states: list[str], inputs: list[str]) -> list[dict]:
    """The CSV's trajectories (header ``traj,t,<states>,<inputs>``) as dicts of t, x, u."""
    table = np.genfromtxt(path, delimiter=",", names=True)
    columns = table.dtype.names
    missing = [c for c in ["traj", "t", *states, *inputs] if c not in columns]
    if missing:
        raise ValueError(f"{path}: columns {missing} missing (has {list(columns)})")
    out = []
    for traj in np.unique(table["traj"]):
        rows = table[table["traj"] == traj]
        out.append({"t": rows["t"], "x": np.column_stack([rows[s] for s in states]),
                    "u": np.column_stack([rows[s] for s in inputs])})
    return out


def replay(model: RebuiltModel, record: dict, rtol: float = 1e-9, atol: float = 1e-10) -> np.ndarray:
    """The model's states at the record's sample times, from its first measured state, each
    measured input held from its sample to the next (stretches of equal inputs integrated at once)."""
    t, u = record["t"], record["u"]
    pred = np.full(record["x"].shape, np.nan)
    pred[0] = record["x"][0]
    changes = [0] + [k for k in range(1, len(t)) if np.any(u[k] != u[k - 1])] + [len(t) - 1]
    state = pred[0]
    for start, stop in zip(changes[:-1], changes[1:]):
        if stop <= start:
            continue
        sol = scipy.integrate.solve_ivp(lambda _, x, uk=u[start]: model.f(x, uk), (t[start], t[stop]), state,
                                        method="LSODA", t_eval=t[start:stop + 1], rtol=rtol, atol=atol)
        if not sol.success or sol.y.shape[1] != stop - start + 1 or not np.all(np.isfinite(sol.y)):
            return pred  # diverged: the rest stays NaN and the error is infinite
        pred[start:stop + 1] = sol.y.T
        state = sol.y[:, -1]
    return pred


def relative_error(pred: np.ndarray, true: np.ndarray) -> float:
    """DESIGN.md's ε: ‖ŷ − y‖ / ‖y‖ · 100 per state, averaged over the states (inf after a divergence)."""
    if not np.all(np.isfinite(pred)):
        return float("inf")
    return float(np.mean(np.linalg.norm(pred - true, axis=0) / np.linalg.norm(true, axis=0)) * 100.0)


def equilibrium(model: RebuiltModel, u, start) -> np.ndarray | None:
    """A root of f(·, u) near ``start`` (the plant's equilibrium), or None."""
    sol = scipy.optimize.root(lambda x: model.f(x, u), np.asarray(start, dtype=float),
                              jac=lambda x: model.jacobian(x, u), method="hybr", tol=1e-12)
    scale = np.maximum(np.abs(model.jacobian(sol.x, u)).sum(axis=1), 1.0)
    if not np.all(np.isfinite(sol.x)) or np.max(np.abs(model.f(sol.x, u)) / scale) > 1e-8:
        return None
    return sol.x


def wasserstein(a, b) -> float:
    """1-Wasserstein distance of two spectra as uniform point masses in the complex plane (an
    assignment for equal counts, a transport linear programme otherwise): a second implementation,
    on purpose, of pisml_ros.analysis.metrics.spectrum_wasserstein."""
    a, b = np.asarray(a, dtype=complex), np.asarray(b, dtype=complex)
    cost = np.abs(a[:, None] - b[None, :])
    if len(a) == len(b):
        rows, cols = scipy.optimize.linear_sum_assignment(cost)
        return float(cost[rows, cols].mean())
    n, m = len(a), len(b)
    eq = np.vstack([np.kron(np.eye(n), np.ones(m)), np.kron(np.ones(n), np.eye(m))])
    res = scipy.optimize.linprog(cost.ravel(), A_eq=eq, b_eq=np.r_[np.full(n, 1 / n), np.full(m, 1 / m)],
                                 bounds=(0, None), method="highs")
    return float(res.fun)


def score(data: dict, records: list[dict], truth: dict) -> dict:
    """IOD / OOD ε (%), and at each ug of ``truth``: the equilibrium, the largest real part and W."""
    with np.errstate(all="ignore"):  # a diverging model (Std SINDy) scores inf, without a warning per step
        return _score(RebuiltModel(data), records, truth)


def _score(model: RebuiltModel, records: list[dict], truth: dict) -> dict:
    cols = [model.states.index(s) for s in SCORED]
    jump, sag = records[-1], records[0]
    pred_jump, pred_sag = replay(model, jump), replay(model, sag)
    iod, ood = jump["t"] < T_SPLIT - 1e-12, sag["t"] >= T_SPLIT - 1e-12
    out = {"n_parameters": model.n_parameters,
           "iod": relative_error(pred_jump[iod][:, cols], jump["x"][iod][:, cols]),
           "ood": relative_error(pred_sag[ood][:, cols], sag["x"][ood][:, cols]), "spectra": {}}
    for point in truth["points"]:
        u = [point["ug"], 0.0]
        x = equilibrium(model, u, point["state"])
        if x is None:
            out["spectra"][f"{point['ug']:g}"] = None
            continue
        eig = np.linalg.eigvals(model.jacobian(x, u))
        true_eig = np.array([complex(*z) for z in point["eigenvalues"]])
        out["spectra"][f"{point['ug']:g}"] = {"max_real": float(eig.real.max()), "w": wasserstein(eig, true_eig)}
    found = [v for v in out["spectra"].values() if v is not None]
    out["w_ug08"] = (out["spectra"].get("0.8") or {}).get("w")
    out["w_mean"] = float(np.mean([v["w"] for v in found])) if len(found) == len(out["spectra"]) else None
    out["spurious"] = [ug for ug, v in out["spectra"].items() if float(ug) in STABLE_UG and v and v["max_real"] > 0]
    out["no_equilibrium"] = [ug for ug, v in out["spectra"].items() if v is None]
    return out


def write_reference(directory: Path) -> None:
    """The truth side, from the virtual HIL: the protocol's test records and the plant's spectra."""
    sys.path[:0] = [str(BENCH), str(BENCH.parent)]
    from bench import UG_GRID, datasets, plant_grid
    from pisml_ros.data import write_dataset

    plant, _, _, test = datasets({}, None)
    directory.mkdir(parents=True, exist_ok=True)
    write_dataset(test, directory / "test.csv")
    points = [{"ug": g, "state": plant.equilibrium(g, 0.0).tolist(),
               "eigenvalues": [[z.real, z.imag] for z in plant.eigenvalues(g, 0.0)]} for g in plant_grid(plant)]
    (directory / "truth.json").write_text(json.dumps({"plant": "standard", "grid": list(UG_GRID), "points": points},
                                                     indent=1))


def package_score(data: dict, truth: dict, test_csv: Path) -> dict:
    """The same figures as pisml_ros computes them (the benchmark's code) on the same test records,
    for --compare."""
    from pisml_ros.analysis.metrics import protocol_errors, spectrum_wasserstein
    from pisml_ros.data import read_dataset
    from pisml_ros.model import ExplicitModel

    model = ExplicitModel.from_dict(data)
    out = dict(protocol_errors(model, read_dataset(test_csv)))
    out["spectra"] = {}
    for point in truth["points"]:
        try:
            eig = np.asarray(model.eigenvalues(point["ug"], 0.0))
        except Exception:  # no equilibrium: as the benchmark counts it
            out["spectra"][f"{point['ug']:g}"] = None
            continue
        true_eig = np.array([complex(*z) for z in point["eigenvalues"]])
        out["spectra"][f"{point['ug']:g}"] = {"max_real": float(eig.real.max()),
                                              "w": spectrum_wasserstein(eig, true_eig)}
    return out


def comparison_row(path: Path, data: dict, reference: Path, truth: dict, compare: bool) -> dict:
    """One model's independent figures on ``reference``'s test records and, with ``compare``, the
    package's and where they differ."""
    started = time.monotonic()
    records = read_records(reference / "test.csv", data["states"], data["inputs"])
    row = {"model": path.name, **score(data, records, truth)}
    if compare:
        with np.errstate(all="ignore"):
            ours = package_score(data, truth, reference / "test.csv")
        row["package"] = {k: ours[k] for k in ("iod", "ood", "spectra")}
        # grid voltages where the two found different equilibria (the largest real parts differ)
        row["equilibria_differ"] = [g for g, v in row["spectra"].items()
                                    if (v is None) != (ours["spectra"].get(g) is None)
                                    or v and abs(v["max_real"] - ours["spectra"][g]["max_real"]) > 1e-6]
    row["seconds"] = time.monotonic() - started
    return row


def write_markdown(rows: list[dict], path: Path, command: str) -> None:
    """The comparison table (bench/INDEPENDENT_RESULTS.md)."""
    def pct(v):
        return "diverged" if v is None or not np.isfinite(v) else f"{v:.4g}"

    def w(v):
        return "—" if v is None else f"{v:.4g}"

    lines = ["# Explicit models scored without pisml_ros", "",
             f"Generated by `{command}` ({time.strftime('%Y-%m-%d')}).", "",
             "Each model JSON of `bench/models/` rebuilt from the file alone (sympy), its test records integrated by "
             "scipy's LSODA (rtol 1e-9) with each input held over its sample, equilibria by scipy's root from the "
             "plant's, Jacobians by sympy (`bench/independent_score.py`), against the same figures from pisml_ros "
             "(RK4 with four substeps per sample, equilibria followed from the records' rest states). IOD / OOD: "
             "ε % as in RESULTS.md. Equilibria differ: grid voltages where the two analyses found different "
             "equilibria of the model (the largest real part differs by more than 1e-6 1/s), with both values.", "",
             "| model | coefficients | IOD % independent / package | OOD % independent / package | "
             "W(ug 0.8) independent / package | spurious unstable (0.2-1.1) | no equilibrium | equilibria differ |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r.get("package") or {}
        pw = ((p.get("spectra") or {}).get("0.8") or {}).get("w")
        differ = "; ".join(f"ug {g}: max Re {w((r['spectra'][g] or {}).get('max_real'))} / "
                           f"{w((p['spectra'].get(g) or {}).get('max_real'))}"
                           for g in r.get("equilibria_differ", [])) or "none"
        lines.append(f"| {r['model']} | {r['n_parameters']} | {pct(r['iod'])} / {pct(p.get('iod'))} | "
                     f"{pct(r['ood'])} / {pct(p.get('ood'))} | {w(r['w_ug08'])} / {w(pw)} | "
                     f"{', '.join(r['spurious']) or 'none'} | {', '.join(r['no_equilibrium']) or 'none'} | {differ} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="*", type=Path, help="explicit model JSON files (default: bench/models/*.json)")
    parser.add_argument("--reference", type=Path, default=MODELS / "reference",
                        help="folder with test.csv and truth.json (default bench/models/reference)")
    parser.add_argument("--write-reference", action="store_true",
                        help="write test.csv and truth.json into --reference from the virtual HIL first")
    parser.add_argument("--compare", action="store_true", help="also score with pisml_ros and print the difference")
    parser.add_argument("--out", type=Path, help="results JSON (e.g. bench/independent_results.json)")
    parser.add_argument("--markdown", type=Path, help="comparison table (needs --compare)")
    args = parser.parse_args(argv)
    if args.write_reference:
        write_reference(args.reference)
    truth = json.loads((args.reference / "truth.json").read_text())
    paths = args.models or sorted(MODELS.glob("*.json"))
    rows = []
    for path in paths:
        row = comparison_row(path, json.loads(path.read_text()), args.reference, truth, args.compare)
        line = (f"{path.name:34s} IOD {row['iod']:8.4g} % OOD {row['ood']:8.4g} % W0.8 "
                f"{row['w_ug08'] if row['w_ug08'] is None else round(row['w_ug08'], 3)!s:>8} "
                f"spurious {','.join(row['spurious']) or 'none'} no eq. {','.join(row['no_equilibrium']) or 'none'}")
        if args.compare:
            line += (f" | package IOD {row['package']['iod']:8.4g} OOD {row['package']['ood']:8.4g}; "
                     f"equilibria differ at {','.join(row['equilibria_differ']) or 'none'}")
        print(line, flush=True)
        rows.append(row)
    command = "python bench/independent_score.py" + (" --compare" if args.compare else "")
    if args.out:
        args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": command, "rows": rows},
                                       indent=1, default=float))
    if args.markdown and args.compare:
        write_markdown(rows, args.markdown, command)
    return 0


if __name__ == "__main__":
    sys.exit(main())
