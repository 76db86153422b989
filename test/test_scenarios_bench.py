"""The scenarios benchmark's record of where its kept rows come from (no fits run here)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import scenarios_bench  # noqa: E402


def test_kept_rows_name_each_run_they_come_from():
    full = {"command": "python bench/scenarios_bench.py ", "date": "2026-12-01", "total_seconds": 1955.3}
    noisy = {"command": "python bench/scenarios_bench.py --noise 40 --keep-other-noise", "date": "2026-12-01",
             "total_seconds": 1590.4}
    rows = [{"kept": True, "source": full}, {"kept": True, "source": noisy}, {"kept": True, "source": noisy},
            {"scenario": "20 kHz"}]
    sources = scenarios_bench.kept_sources(rows)
    assert sources == [{"run": full, "rows": 1}, {"run": noisy, "rows": 2}]
    text = scenarios_bench.kept_text({"kept_from": sources})
    assert text == (": `python bench/scenarios_bench.py` (2026-12-01, 1955 s; 1 row); `python bench/scenarios_bench.py "
                    "--noise 40 --keep-other-noise` (2026-12-01, 1590 s; 2 rows)")
    assert scenarios_bench.kept_text({"kept_from": None}) == ""
