"""`make bench`'s runner: a partial run keeps the other benchmarks' results in the summary."""

import json
import sys
import types


def _fake(results, name, text, fail=False):
    def main():
        if fail:
            raise RuntimeError("broken")
        (results / f"{name}.md").write_text(text)

    module = types.ModuleType(f"benchmarks.{name}")
    module.main = main
    return module


def test_partial_run_updates_its_entries_and_keeps_the_others(tmp_path, monkeypatch):
    from benchmarks import run

    monkeypatch.setattr(run, "RESULTS", tmp_path)
    monkeypatch.setattr(run, "discover", lambda: ["alpha", "beta", "gamma"])
    for name, text in (("alpha", "| a | 1 |"), ("beta", "| b | 1 |"), ("gamma", "| c | 1 |")):
        monkeypatch.setitem(sys.modules, f"benchmarks.{name}", _fake(tmp_path, name, text))
    assert run.main([]) == 0
    monkeypatch.setitem(sys.modules, "benchmarks.beta", _fake(tmp_path, "beta", "| b | 2 |"))
    monkeypatch.setitem(sys.modules, "benchmarks.gamma", _fake(tmp_path, "gamma", "", fail=True))
    assert run.main(["beta", "gamma"]) == 1  # gamma failed
    status = json.loads((tmp_path / "run.json").read_text())
    assert list(status) == ["alpha", "beta", "gamma"]
    assert status["alpha"]["status"] == "ok" and status["beta"]["status"] == "ok"
    assert status["gamma"]["status"] == "failed" and "broken" in status["gamma"]["error"]
    summary = (tmp_path / "SUMMARY.md").read_text()
    assert "| a | 1 |" in summary and "| b | 2 |" in summary and "| b | 1 |" not in summary
    assert "| gamma | failed |" in summary


def test_a_time_bound_scales_with_the_reference_operation_and_never_shrinks(monkeypatch, capsys):
    from benchmarks import calibrate, common, run

    base = calibrate.TARGET_REFERENCE_SECONDS
    assert calibrate.scaled_bound(60, base) == 60.0
    assert calibrate.scaled_bound(60, 3 * base) == 180.0  # a machine three times slower
    assert calibrate.scaled_bound(60, base / 2) == 60.0  # a faster one keeps the bound
    monkeypatch.setattr(common, "reference_operation", lambda repeats: {"seconds": 2.5 * base})
    assert calibrate.main(["60"]) == 0 and capsys.readouterr().out.strip() == "150"

    def missing(repeats):
        raise FileNotFoundError("no Horse")

    monkeypatch.setattr(common, "reference_operation", missing)
    assert calibrate.main(["60"]) == 0 and capsys.readouterr().out.strip() == "60"
    assert calibrate.main(["soon"]) == 2
    assert "calibrate" not in run.discover()  # a helper, not a benchmark
