"""bench/independent_score.py: an outsider's scoring of a model JSON agrees with the package's."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    from independent_score import write_reference

    directory = tmp_path_factory.mktemp("reference")
    write_reference(directory)
    return directory


def perturbed_truth(scale: float) -> dict:
    """The plant's equations as an explicit model, the active-power filter's p term scaled."""
    from oracle_bench import true_equations

    from pisml_ros.model import ExplicitModel
    from pisml_ros.plant import InverterPlant
    from pisml_ros.signals import INPUT_NAMES, STATE_NAMES

    plant = InverterPlant()
    basis, coef = true_equations(plant)
    pf = STATE_NAMES.index("Pf")
    k = int(np.argmax(np.abs(coef[:, pf]) * (np.array(["*" in t for t in basis]))))
    coef[k, pf] *= scale
    refs = {"reference_points": [{"inputs": [1.0, 0.0], "state": plant.equilibrium(1.0).tolist()}]}
    return ExplicitModel(STATE_NAMES, INPUT_NAMES, basis, coef, refs).to_dict()


def test_the_outsiders_figures_match_the_packages_and_see_an_error(reference):
    from independent_score import comparison_row

    truth = json.loads((reference / "truth.json").read_text())
    rows = {}
    for scale in (1.0, 1.05):
        data = json.loads(json.dumps(perturbed_truth(scale)))  # as a file would give it
        rows[scale] = comparison_row(Path(f"x{scale}.json"), data, reference, truth, compare=True)
    exact, off = rows[1.0], rows[1.05]
    # the plant's own equations: what is left is the integrators' error, far below any target
    assert exact["iod"] < 0.005 and exact["ood"] < 0.005 and exact["w_ug08"] < 1e-6
    assert exact["spurious"] == [] and exact["equilibria_differ"] == []
    # 5 % off in one coefficient: both scorings see the same error
    assert off["iod"] > 10 * exact["iod"] and off["ood"] > 10 * exact["ood"]
    for key in ("iod", "ood"):
        assert off[key] == pytest.approx(off["package"][key], rel=0.05)
    assert off["spectra"]["0.8"]["w"] == pytest.approx(off["package"]["spectra"]["0.8"]["w"], rel=1e-6)


def test_a_file_that_is_not_an_explicit_model_is_refused():
    from independent_score import RebuiltModel

    with pytest.raises(ValueError, match="format 'other'"):
        RebuiltModel({"format": "other"})
