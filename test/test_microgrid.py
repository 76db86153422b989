"""Multi-inverter assembly (pisml_ros.analysis.microgrid) and `pisml microgrid`."""
import json
from pathlib import Path

import numpy as np
import pytest

from pisml_ros.analysis.microgrid import (Bus, Line, Microgrid, MicrogridError, Unit, microgrid_from_config,
                                          microgrid_report, parameter_sweep, read_microgrid_config, simulate_stages,
                                          with_setting)
from pisml_ros.ident.library import extended_library, monomial_basis, physics_library
from pisml_ros.ident.roles import SignalRoles
from pisml_ros.model import ExplicitModel
from pisml_ros.plant import InverterPlant, PlantParameters
from pisml_ros.signals import INPUT_NAMES, STATE_NAMES

from cli_helpers import pisml

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "microgrid.yaml"


def three_bus(target, aux_gain=2.0):
    aux1 = InverterPlant(PlantParameters(mp=0.06, KpV=aux_gain, KiV=4.0, KpC=0.3))
    aux2 = InverterPlant(PlantParameters(KpV=1.4, KiV=2.0, KpC=0.4))
    units = [Unit("target", target, "b1"), Unit("aux1", aux1, "b2"), Unit("aux2", aux2, "b3")]
    buses = [Bus("b1", 0.02), Bus("b2", 0.02, load_r=4.0), Bus("b3", 0.02), Bus("pcc", 0.05, load_r=0.9, load_x=0.4358)]
    lines = [Line("b1", "pcc", 0.01, 0.05), Line("b2", "pcc", 0.01, 0.05), Line("b3", "b2", 0.01, 0.05),
             Line("pcc", "grid", 0.02, 0.2)]
    return Microgrid(units, buses, lines)


def plant_as_explicit_model(plant):
    """The plant's vector field over the engine's monomial basis, fitted exactly by least squares
    (the plant lies in the basis' span) around its equilibria."""
    roles = SignalRoles()
    basis, _ = monomial_basis(physics_library(roles, STATE_NAMES) + extended_library(roles, STATE_NAMES),
                              STATE_NAMES + INPUT_NAMES)
    rng = np.random.default_rng(0)
    points = []
    for ug in (0.8, 0.9, 1.0, 1.1, 1.2):
        x0 = plant.equilibrium(ug)
        for _ in range(40):
            points.append((x0 + 0.05 * rng.standard_normal(x0.size) * (1 + np.abs(x0)),
                           [ug * (1 + 0.05 * rng.standard_normal()), 0.1 * rng.standard_normal()]))
    x = np.array([p for p, _ in points])
    u = np.array([q for _, q in points])
    empty = ExplicitModel(STATE_NAMES, INPUT_NAMES, basis, np.zeros((len(basis), len(STATE_NAMES))))
    coef = np.linalg.lstsq(empty.features(x, u), plant.vector_field(x, u), rcond=None)[0]
    coef[np.abs(coef) < 1e-8] = 0.0
    refs = [{"inputs": [1.0, 0.0], "state": plant.equilibrium(1.0).tolist()}]
    return ExplicitModel(STATE_NAMES, INPUT_NAMES, basis, coef, metadata={"reference_points": refs})


def test_jacobian_is_exact():
    grid = three_bus(InverterPlant())
    u = np.array([1.0, 0.05])
    x = grid.equilibrium(*u)
    assert np.abs(grid.vector_field(x, u)).max() < 1e-6
    rng = np.random.default_rng(1)
    x = x + 1e-2 * rng.standard_normal(x.size)  # off the equilibrium too
    step = 1e-6
    numeric = np.stack([(grid.vector_field(x + step * e, u) - grid.vector_field(x - step * e, u)) / (2 * step)
                        for e in np.eye(grid.n_states)], axis=1)
    exact = grid.jacobian(x, u)
    assert np.abs(exact - numeric).max() < 1e-7 * np.abs(exact).max()
    numeric_u = np.stack([(grid.vector_field(x, u + step * e) - grid.vector_field(x, u - step * e)) / (2 * step)
                          for e in np.eye(2)], axis=1)
    assert np.allclose(grid.jacobian(x, u, wrt="u"), numeric_u, rtol=1e-6, atol=1e-4)


def test_one_unit_on_a_stiff_bus_has_the_plant_modes():
    plant = InverterPlant()
    grid = Microgrid([Unit("inv", plant, "pcc")], [Bus("pcc", capacitance=1e-4)], [Line("pcc", "grid", r=0.0, x=1e-4)])
    eigs = grid.eigenvalues(1.0, 0.0)
    for reference in plant.eigenvalues(1.0, 0.0):  # the plant's own, on its ideal grid
        assert np.min(np.abs(eigs - reference)) < 1e-3 * max(1.0, abs(reference))
    # the network adds its own (stiff) modes only
    assert len(eigs) == plant.n_states + 4


def test_a_line_in_series_is_the_plant_with_a_larger_grid_inductance():
    """An independent check of the network's frames and rotations: a unit behind a line (bus
    capacitance → 0) is the plant with the line's r and x added to its own Rg and Lg."""
    merged = InverterPlant(PlantParameters(Lg=0.15, Rg=0.03))
    grid = Microgrid([Unit("inv", InverterPlant(), "b")], [Bus("b", capacitance=1e-5)], [Line("b", "grid", 0.02, 0.1)])
    eigs = grid.eigenvalues(1.0, 0.0)
    for reference in merged.eigenvalues(1.0, 0.0):
        assert np.min(np.abs(eigs - reference)) < 2e-4 * max(1.0, abs(reference))


def test_weak_grid_configuration_finds_the_stiff_grid_boundary():
    """config/weak_grid.yaml (one inverter behind a line): at 1.2 p.u. the plant is unstable on a
    stiff grid and stable once the line adds enough impedance; the boundary in the line's x is the
    one of the plant with x added to its own Lg (the connection point's capacitance aside)."""
    from scipy.optimize import brentq

    config = read_microgrid_config(ROOT / "config" / "weak_grid.yaml")
    sweep = parameter_sweep(with_setting(config, "grid.ug", 1.2), "lines.0.x", [0.005, 0.02, 0.1, 1.0],
                            ROOT / "config")
    assert [p["max_real"] > 0 for p in sweep["points"]] == [True, False, False, False]
    merged = brentq(lambda x: InverterPlant(PlantParameters(Lg=0.05 + x, Rg=0.02)).eigenvalues(1.2).real.max(),
                    0.0, 0.05)
    assert len(sweep["boundaries"]) == 1 and abs(sweep["boundaries"][0] - merged) < 0.01 * merged
    at_one = parameter_sweep(config, "lines.0.x", [0.01, 0.1, 1.0], ROOT / "config")
    assert all(p["max_real"] < 0 for p in at_one["points"]) and not at_one["boundaries"]


def test_two_units_of_half_the_rating_are_one_of_the_full_rating():
    plant = InverterPlant()
    network = ([Bus("b", 0.02, load_r=2.0, load_x=0.5)], [Line("b", "grid", 0.01, 0.1)])
    one = Microgrid([Unit("one", plant, "b")], *network)
    two = Microgrid([Unit("a", plant, "b", rating=0.5), Unit("b", plant, "b", rating=0.5)], *network)
    x1, x2 = one.equilibrium(), two.equilibrium()
    assert np.allclose(one.injected_currents(x1)[0], two.injected_currents(x2).sum(axis=0), atol=1e-8)
    assert np.allclose(x1[one.n_unit_states:], x2[two.n_unit_states:], atol=1e-8)  # the same network state
    eigs = two.eigenvalues()
    for reference in one.eigenvalues():  # the pair's common mode is the single unit's
        assert np.min(np.abs(eigs - reference)) < 1e-6 * max(1.0, abs(reference))
    with pytest.raises(MicrogridError, match="rating must be > 0"):
        Unit("c", plant, "b", rating=0.0)


def test_identified_equations_stand_in_for_the_plant():
    """The target as explicit model equations (here: the plant's exact ones, over the engine's
    monomials) gives the same microgrid: operating point, modes, stability boundary."""
    plant = InverterPlant()
    model = plant_as_explicit_model(plant)
    truth, assembled = three_bus(plant), three_bus(model)
    x_truth, x_model = truth.equilibrium(1.0, 0.0), assembled.equilibrium(1.0, 0.0)
    assert np.allclose(x_truth, x_model, atol=1e-6)
    a, b = np.sort_complex(truth.eigenvalues(1.0, 0.0)), np.sort_complex(assembled.eigenvalues(1.0, 0.0))
    assert np.abs(a - b).max() < 1e-5 * np.abs(a).max()
    report = microgrid_report(assembled, 1.0, 0.0, modes=2)
    assert report["stable"] and [u["name"] for u in report["units"]] == ["target", "aux1", "aux2"]
    for mode in report["weakest_modes"]:
        assert sum(mode["unit_shares"].values()) == pytest.approx(1.0)
    # grid-connected droop inverters deliver their set point
    assert all(u["p"] == pytest.approx(0.5, abs=0.02) for u in report["units"])


def test_an_identified_unit_with_a_second_equilibrium_at_its_bus_voltage_is_cautioned(tmp_path):
    """A unit whose angle equation has two roots (δ = 0 stable, δ = 0.3 unstable, in its bus
    voltage's frame) reports the other one, held at its bus voltage; a plant and the plant's exact
    equations (one root there) report none."""
    from pisml_ros.analysis.microgrid import unit_other_equilibria

    states, inputs = ("delta", "ig_d", "ig_q"), ("ug", "theta_g")
    terms = ["1", "delta", "delta**2", "ig_d", "ig_q"]
    coefficients = np.array([[0.0, 5.0, 0.0],  # ig_d rests at 0.5
                             [-10.0, 0.0, 0.0], [100.0 / 3.0, 0.0, 0.0],  # d(delta)/dt: roots 0 and 0.3
                             [0.0, -10.0, 0.0], [0.0, 0.0, -10.0]])
    toy = ExplicitModel(states, inputs, terms, coefficients,
                        metadata={"reference_points": [{"inputs": [1.0, 0.0], "state": [0.0, 0.5, 0.0]},
                                                       {"inputs": [1.0, 0.0], "state": [0.2, 0.5, 0.0]}]})
    grid = Microgrid([Unit("toy", toy, "poc")], [Bus("poc", 0.01)], [Line("poc", "grid", 0.01, 0.05)])
    x = grid.equilibrium(1.0, 0.0)
    local, _ = grid._local(x, 0)
    assert local[0] == pytest.approx(0.0, abs=1e-9)  # the stable root, in the bus frame
    (other,) = unit_other_equilibria(grid, x, 0)
    assert other["state"]["delta"] == pytest.approx(0.3, abs=1e-9) and other["distance"] == pytest.approx(0.3)
    assert not other["stable"] and other["max_real"] == pytest.approx(10.0) and other["differs_most"][0] == "delta"
    report = microgrid_report(grid, 1.0, 0.0)
    assert report["units"][0]["other_equilibria"][0]["state"]["delta"] == pytest.approx(0.3)
    path = toy.save(tmp_path / "toy.json")
    config = tmp_path / "toy.yaml"
    config.write_text(f"buses: [{{name: poc, capacitance: 0.01}}]\nlines: [{{from: poc, to: grid, r: 0.01, x: 0.05}}]\n"
                      f"units: [{{name: toy, bus: poc, model: {path}}}]\n")
    text = pisml("microgrid", "--config", config).stdout
    assert ("caution: held at the voltage of its bus, the unit has another equilibrium 0.3 away in state (most in "
            "delta") in text and "unstable (largest real part +10 1/s)" in text
    plant = InverterPlant()
    for system in (plant, plant_as_explicit_model(plant)):
        grid = Microgrid([Unit("target", system, "poc")], [Bus("poc", 0.01)], [Line("poc", "grid", 0.01, 0.05)])
        assert "other_equilibria" not in microgrid_report(grid, 1.0, 0.0)["units"][0]
        assert unit_other_equilibria(grid, grid.equilibrium(1.0, 0.0), 0) == (None if system is plant else [])


def test_modes_faster_than_an_identified_units_records_are_noted():
    """A network resonance above a quarter of an identified unit's sample rate, with the unit's
    share in it, carries a caution; slower modes and units without a recorded sample period
    (the plant) do not."""
    plant = InverterPlant()
    model = plant_as_explicit_model(plant)
    model.metadata["training"] = {"sample_period": 1e-4}  # records at 10 kHz
    grid = Microgrid([Unit("target", model, "poc")], [Bus("poc", 0.01)], [Line("poc", "grid", 0.01, 0.05)])
    report = microgrid_report(grid, 1.0, 0.0, modes=grid.n_states)
    noted = [m for m in report["weakest_modes"] if m.get("note")]
    assert noted and all(m["frequency_hz"] > 2500.0 and m["unit_shares"]["target"] >= 0.1 for m in noted)
    assert "target's records (10000 Hz)" in noted[0]["note"]
    assert all(m["frequency_hz"] <= 2500.0 or m["unit_shares"]["target"] < 0.1
               for m in report["weakest_modes"] if not m.get("note"))
    assert any(m["frequency_hz"] > 3000.0 for m in noted)  # the capacitor-line resonance near 3.9 kHz
    bare = Microgrid([Unit("target", plant, "poc")], [Bus("poc", 0.01)], [Line("poc", "grid", 0.01, 0.05)])
    assert not any(m.get("note") for m in microgrid_report(bare, 1.0, 0.0, modes=bare.n_states)["weakest_modes"])


def test_load_step_transient_is_the_same_with_the_equations():
    """A load step simulated through the microgrid: at rest before it, and the plant's exact
    equations as the target reproduce the plant's currents."""
    plant = InverterPlant()
    model = plant_as_explicit_model(plant)
    runs = []
    for target in (plant, model):
        before = three_bus(target)
        after = Microgrid(before.units, [*before.buses[:3], Bus("pcc", 0.05, load_r=0.6, load_x=0.4358)], before.lines)
        x0 = before.equilibrium(1.0, 0.0)
        t, x = simulate_stages([(before, 0.01), (after, 0.01)], x0, [1.0, 0.0])
        currents = before.injected_currents(x)
        assert np.abs(currents[t < 0.01] - currents[0]).max() < 1e-7  # nothing moves before the step
        assert np.abs(currents[-1] - currents[0]).max() > 0.02  # the step moves every unit
        runs.append(currents)
    assert len(t) == 201 and np.abs(runs[0] - runs[1]).max() < 1e-6
    with pytest.raises(MicrogridError, match="share their states"):
        resistive = Microgrid(before.units, [*before.buses[:3], Bus("pcc", 0.05, load_r=0.6)], before.lines)
        simulate_stages([(before, 0.01), (resistive, 0.01)], x0, [1.0, 0.0])


def islanded(target):
    grid = three_bus(target)
    return Microgrid(grid.units, grid.buses, grid.lines[:3])  # no line to the grid


def test_islanded_microgrid_shares_the_load_by_droop():
    grid = islanded(InverterPlant())
    assert grid.islanded and "target.delta" not in grid.state_names and "aux1.delta" in grid.state_names
    x = grid.equilibrium()
    u = np.array([1.0, 0.0])
    assert np.abs(grid.vector_field(x, u)).max() < 1e-6
    # one frequency for all: each unit's droop w = 1 + mp (P* - Pf) at its own filtered power
    w = grid.frequency(x)
    for k, unit in enumerate(grid.units):
        own = grid.unit_state(x, k)
        assert 1.0 + unit.system.params.mp * (0.5 - own[1]) == pytest.approx(w, abs=1e-9)
    # the units supply the loads and the lines' losses
    report = microgrid_report(grid, modes=1)
    supplied = sum(entry["p"] for entry in report["units"])
    v = {b.name: x[grid.v_offset[b.name]:grid.v_offset[b.name] + 2] for b in grid.buses}
    consumed = np.sum(v["b2"] ** 2) / 4.0  # resistive load at b2
    o = grid.load_offset["pcc"]
    consumed += 0.9 * np.sum(x[o:o + 2] ** 2)
    consumed += sum(line.r * np.sum(x[grid.line_offset[k]:grid.line_offset[k] + 2] ** 2)
                    for k, line in enumerate(grid.lines))
    # less load than the set points (3 x 0.5 p.u.): the droops settle above the nominal frequency
    assert supplied == pytest.approx(consumed, rel=1e-6) and supplied < 1.5 and w > 1.0
    assert report["islanded"] and report["frequency_pu"] == pytest.approx(w)
    # no structural zero mode (the reference angle is not a state), and the exact Jacobian
    eigs = np.linalg.eigvals(grid.jacobian(x, u))
    assert np.abs(eigs).min() > 1e-3
    rng = np.random.default_rng(2)
    x = x + 1e-2 * rng.standard_normal(x.size)
    step = 1e-6
    numeric = np.stack([(grid.vector_field(x + step * e, u) - grid.vector_field(x - step * e, u)) / (2 * step)
                        for e in np.eye(grid.n_states)], axis=1)
    exact = grid.jacobian(x, u)
    assert np.abs(exact - numeric).max() < 1e-7 * np.abs(exact).max()
    # the equations of the plant as the reference unit give the same modes
    other = np.sort_complex(islanded(plant_as_explicit_model(InverterPlant())).eigenvalues())
    assert np.abs(np.sort_complex(eigs) - other).max() < 1e-5 * np.abs(eigs).max()


def test_the_identified_units_covariance_carries_to_the_microgrid_verdict():
    """One identified unit on a stiff bus: the microgrid's largest real part is the unit's own, and
    so is its standard deviation (analysis.uncertainty, the single-model computation)."""
    from pisml_ros.analysis.uncertainty import covariance_metadata, max_real_std

    model = plant_as_explicit_model(InverterPlant())
    support = np.flatnonzero(model.coefficients.ravel())
    cov = np.diag((0.002 * model.coefficients.ravel()[support]) ** 2)
    model.metadata["coefficient_covariance"] = covariance_metadata(model.coefficients.shape, support, cov)
    # (the line resistive enough that the network's own fast modes are damped well below the unit's slowest)
    grid = Microgrid([Unit("inv", model, "pcc")], [Bus("pcc", capacitance=1e-5)], [Line("pcc", "grid", 1e-5, 1e-5)])
    x = grid.equilibrium(1.0, 0.0)
    alone = max_real_std(model, model.equilibrium(1.0, 0.0), np.array([1.0, 0.0]))
    assert alone > 0 and grid.max_real_std(x) == pytest.approx(alone, rel=1e-3)
    report = microgrid_report(three_bus(model), 1.0, 0.0)
    assert report["uncertainty"]["max_real_std"] > 0 and report["uncertainty"]["verdict"] in ("stable", "undetermined")
    assert "uncertainty" not in microgrid_report(three_bus(InverterPlant()), 1.0, 0.0)  # nothing identified


def test_descriptions_that_cannot_be_assembled_say_what_is_wrong():
    plant = InverterPlant()
    with pytest.raises(MicrogridError, match="bus 'nowhere'"):
        Microgrid([Unit("a", plant, "nowhere")], [Bus("b")], [Line("b", "grid")])
    with pytest.raises(MicrogridError, match="capacitance"):
        Microgrid([Unit("a", plant, "b")], [Bus("b", capacitance=0.0)], [Line("b", "grid")])
    with pytest.raises(MicrogridError, match=r"state\(s\) \['i_out'\]"):
        Unit("a", plant, "b", current=("ig_d", "i_out"))
    config = read_microgrid_config(CONFIG)
    broken = with_setting(config, "lines.1.x", -0.1)
    with pytest.raises(MicrogridError, match=r"lines\[1\]\.x: must be > 0"):
        microgrid_from_config(broken, CONFIG.parent, source="cfg")
    with pytest.raises(MicrogridError, match=r"units\[1\]: unknown key\(s\) \['gain'\]"):
        microgrid_from_config(with_setting(config, "units.aux1.gain", 2.0), CONFIG.parent, source="cfg")
    with pytest.raises(MicrogridError, match=r"units\[1\]\.plant: unknown parameter"):
        microgrid_from_config(with_setting(config, "units.aux1.plant.Kp", 2.0), CONFIG.parent, source="cfg")
    with pytest.raises(MicrogridError, match="no entry 'nine'"):
        with_setting(config, "lines.nine.x", 1.0)


def test_setting_by_name_or_index():
    config = read_microgrid_config(CONFIG)
    changed = with_setting(with_setting(config, "units.aux2.plant.KpV", 3.0), "lines.3.x", 0.4)
    assert changed["units"][2]["plant"]["KpV"] == 3.0 and changed["lines"][3]["x"] == 0.4
    assert config["units"][2]["plant"]["KpV"] == 1.4  # a copy


def test_cli_microgrid_with_an_identified_unit_and_a_sweep(tmp_path):
    model = plant_as_explicit_model(InverterPlant())
    path = model.save(tmp_path / "target.json")
    out = json.loads(pisml("microgrid", "--config", CONFIG, "--model", f"target={path}", "--json",
                           "--vary", "grid.ug=0.15:0.35:3").stdout)
    assert out["stable"] and out["units"][0]["kind"] == "ExplicitModel"
    sweep = out["sweep"]
    assert sweep["parameter"] == "grid.ug" and len(sweep["points"]) == 3
    assert all(len(point["eigenvalues"]) == 57 for point in sweep["points"])  # the root locus
    # the same boundary as with the plant itself as the target
    plain = json.loads(pisml("microgrid", "--config", CONFIG, "--json", "--vary", "grid.ug=0.15:0.35:3").stdout)
    assert len(sweep["boundaries"]) == len(plain["sweep"]["boundaries"]) == 1
    assert sweep["boundaries"][0] == pytest.approx(plain["sweep"]["boundaries"][0], abs=1e-3)
    text = pisml("microgrid", "--config", CONFIG, "--step", "buses.pcc.load.r=0.6@0.01", "--duration", "0.02",
                 "--out", tmp_path / "step.csv").stdout
    assert "STABLE" in text and "unit aux1 (InverterPlant) at bus b2" in text
    assert "simulated 0.02 s (steps: buses.pcc.load.r = 0.6 at 0.01 s)" in text
    table = np.genfromtxt(tmp_path / "step.csv", delimiter=",", names=True)
    assert len(table) == 201 and table["targeti_D"][-1] > table["targeti_D"][0] + 0.02
    bad = pisml("microgrid", "--config", CONFIG, "--model", f"nobody={path}", check=False)
    assert bad.returncode == 2 and "UNIT one of the configuration's units ['target', 'aux1', 'aux2']" in bad.stderr
    missing = pisml("microgrid", "--config", tmp_path / "none.yaml", check=False)
    assert missing.returncode == 2 and "none.yaml" in missing.stderr


def test_the_alternatives_of_an_identified_unit_each_take_its_place():
    """A unit whose alternative (a candidate that fitted its records as well) has a larger droop
    gain: the 3-bus microgrid with the alternative in the unit's place is unstable where the unit's
    own is stable, and the report says the verdict is open (analysis.operating_point.alternative_verdicts)."""
    from pisml_ros.ident.selection import alternative_entry

    model = plant_as_explicit_model(InverterPlant())
    rival = plant_as_explicit_model(InverterPlant(PlantParameters(mp=0.2)))
    model.metadata["alternatives"] = [alternative_entry("rival", rival, 1.0)]
    grid = three_bus(model)
    x = grid.equilibrium(1.0, 0.0)
    found = grid.alternative_max_reals(x, (1.0, 0.0))
    assert [(item["unit"], item["name"]) for item in found] == [("target", "rival")]
    assert found[0]["max_real"] == pytest.approx(float(three_bus(rival).eigenvalues(1.0).real.max()), abs=1e-6)
    assert grid.units[0].system is model  # put back
    report = microgrid_report(grid, 1.0, 0.0)
    assert report["stable"] and found[0]["max_real"] > 0
    assert report["alternatives"]["agree"] is False and report["alternatives"]["max_real_range"][1] > 0
    assert "alternatives" not in microgrid_report(three_bus(InverterPlant()), 1.0, 0.0)  # nothing identified
