"""bench/fit_time.py: a fit's refinement stages grouped by family from the candidates' metadata (no fitting here)."""
import sys
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import fit_time  # noqa: E402


def _stage(window, seconds):
    return {"window": window, "support": 200, "evaluations": 20, "accepted": 15, "seconds": seconds, "cost": 1.0}


def test_stages_are_grouped_by_refinement_family_in_the_order_they_ran():
    growing = {"refinement": {"stages": [_stage(10, 5.0), _stage(25, 4.0)]}}

    def pruned(round_, seconds):
        return SimpleNamespace(metadata={"refinement": {"stages": [_stage(10, 99.0)]},  # copied from the refined model
                                         "pruning": {"round": round_, "polish_stages": [_stage(100, seconds)]}})

    candidates = {
        "backbone": SimpleNamespace(metadata={}),
        "refined": SimpleNamespace(metadata=growing),
        "pruned +0.1 % x2": pruned(2, 2.0),
        "pruned +0.1 %": pruned(1, 1.0),
        "refined from noise-compensated backbone": SimpleNamespace(metadata=growing),
        "pruned +0.1 % from noise-compensated backbone": pruned(1, 3.0),
        "pruned +0.1 % x3 with growing prior": pruned(3, 6.0),
    }
    families = fit_time.family_stages(candidates)
    assert set(families) == {"first start", "from noise-compensated backbone", "with growing prior"}
    first = families["first start"]
    # growing stages first, then the rounds' polish by round, not by the candidates' order
    assert [(s["part"], s["seconds"]) for s in first] == [("growing", 5.0), ("growing", 4.0), ("polish 1", 1.0),
                                                          ("polish 2", 2.0)]
    assert [s["seconds"] for s in families["from noise-compensated backbone"]] == [5.0, 4.0, 3.0]
    assert [(s["part"], s["seconds"]) for s in families["with growing prior"]] == [("polish 3", 6.0)]
    assert "window  100  support" in fit_time.format_stage(first[-1]) and "accepted  15" in fit_time.format_stage(first[-1])
    assert "window   10 x  48  support" in fit_time.format_stage({**first[0], "windows": 48})


def test_the_extra_refinements_say_why_they_ran():
    meta = {"refinement_rescue": {"run": True, "selected_before": "pruned +0.1 %", "ratio": 2.61,
                                  "inconsistent_rest_points": 0},
            "refinement_unrestricted": {"run": False, "selected_before": "pruned +0.1 % x3", "ratio": None,
                                        "inconsistent_rest_points": 1, "refinement_lost": True}}
    rescue, fallback = fit_time.extra_runs(meta)
    assert rescue == "rescue: ran (before it: 'pruned +0.1 %', 2.61x the noise floor, inconsistent at 0 rest points)"
    assert fallback.startswith("unrestricted fallback: not run")
    assert "inconsistent at 1 rest points, refinement lost" in fallback
    assert fit_time.extra_runs({}) == []
