"""The scripts in benchmarks/ still run, at tiny sizes (the README's figures come from full runs)."""

import json
import runpy
from pathlib import Path

from geodepth_lite import sdf

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load(script: str) -> dict:
    """The script's globals, as ``python benchmarks/<script>`` would define them (main() not run)."""
    return runpy.run_path(str(BENCHMARKS / script), run_name="benchmark_under_test")


def test_bench_sdf_runs_and_times_the_uncached_step_without_the_cache(tmp_path, capsys, monkeypatch):
    lookups = []
    get = sdf.GT_FIELD_CACHE.get
    monkeypatch.setattr(sdf.GT_FIELD_CACHE, "get", lambda key: lookups.append(key) or get(key))
    out = tmp_path / "bench_sdf.json"
    main = load("bench_sdf.py")["main"]
    assert main(["--batch", "2", "--size", "32", "--grid", "3", "--repeats", "1", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["batch"] == 2 and res["sdf_s"] > 0 and res["train_step_s"] > 0 and res["train_step_cached_s"] > 0
    assert "SDF loss benchmark" in capsys.readouterr().out
    # total_loss reads sdf.GT_FIELD_CACHE: the cached warm-up and the cached step look up each
    # frame once; the uncached warm-up and step never do
    assert len(lookups) == 2 * 2


def test_bench_render_runs(capsys):
    main = load("bench_render.py")["main"]
    assert main(["--size", "32", "--frames", "1", "--repeats", "1"]) == 0
    assert "frames/s" in capsys.readouterr().out
