"""``python -m geodepth_lite gpu-check``: its dry run (``--device cpu --tiny``) runs every step's glue here."""

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from geodepth_lite import cli
from geodepth_lite.apps import gpu_check

ROOT = Path(__file__).resolve().parents[1]

# imports a GPU machine may lack: gpu-check and training must not need them
HEAVY = ("matplotlib", "vtk", "vtkmodules", "pyvista", "imageio", "tifffile", "ipywidgets", "IPython", "pandas",
         "papermill", "nbformat")


def blocked_env(tmp_path: Path) -> dict:
    """An environment in which HEAVY cannot be imported, in this process's children and theirs (a
    ``sitecustomize`` on the import path marks each as missing, as Python does for a package that
    is not installed: ``import`` fails, ``importlib.util.find_spec`` says None)."""
    folder = tmp_path / "blocker"
    folder.mkdir()
    (folder / "sitecustomize.py").write_text(f"import sys\nfor name in {HEAVY!r}:\n    sys.modules[name] = None\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(folder)]))


def test_the_blocker_blocks(tmp_path):
    """The blocked environment refuses what it names (else the dry run would prove nothing)."""
    code = "import importlib.util as u, sys; print(u.find_spec('pyvista')); import matplotlib"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env=blocked_env(tmp_path))
    assert proc.returncode == 1 and proc.stdout.strip() == "None"
    assert "ModuleNotFoundError: import of matplotlib halted" in proc.stderr


def cuda_status_problems(record: dict, cuda_available: bool) -> list[str]:
    """A report's CUDA-test status against the pytest summary line it recorded: "passed" only where
    the summary counts a passed test and no failed one; on a machine without CUDA every CUDA test
    skips, so the status says so and the summary counts skips alone."""
    if importlib.util.find_spec("pytest") is None:
        return [] if record["status"] == "not run: pytest is not installed" else [f"status {record['status']!r}"]
    summary, status = record.get("summary", ""), record["status"]
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (passed|failed|skipped)", summary)}
    problems = []
    if (status == "passed") != (counts.get("passed", 0) > 0 and counts.get("failed", 0) == 0):
        problems.append(f"status {status!r} for the summary {summary!r}")
    if not cuda_available and (status != "skipped (no CUDA)" or set(counts) != {"skipped"}):
        problems.append(f"without CUDA: status {status!r}, summary {summary!r}")
    return problems


def test_the_full_dry_run_records_every_step_without_heavy_imports(tmp_path):
    out = tmp_path / "check"
    proc = subprocess.run([sys.executable, "-m", "geodepth_lite", "gpu-check", "--device", "cpu", "--tiny", "--full",
                           "--out", str(out)], capture_output=True, text=True, timeout=300, cwd=ROOT,
                          env=blocked_env(tmp_path))
    assert proc.returncode == 0, proc.stderr[-3000:]
    rep = json.loads((out / "gpu_check.json").read_text())
    assert rep["tiny"] and rep["environment"]["device"] == "cpu"
    assert rep["search"]["agree"] == rep["search"]["queries"] > 0
    import torch

    assert cuda_status_problems(rep["cuda_tests"], torch.cuda.is_available()) == []
    full = rep["paper_run"]  # --full: the profile's own run, through train-many, here at toy sizes
    assert full["status"] == "completed" and (full["train_frames"], full["val_frames"]) == (12, 4)
    assert [r["epoch"] for r in full["epochs"]] == [1, 2] and all(r["val_rmse"] > 0 for r in full["epochs"])
    pred = full["prediction"]
    assert pred["total_s"] == pytest.approx(pred["first_epoch_s"] + 17 * pred["later_epoch_s"], abs=1.0)
    assert full["run_s"] > 0 and full["device_data"] is False and "load_data_s" in full  # on the CPU: the loader
    search = rep["search"]  # both memory formats timed; the runs train in the faster one
    assert search["channels_last"] == (search["network_fwd_bwd_channels_last_s"] < search["network_fwd_bwd_nchw_s"])
    assert full["channels_last"] == search["channels_last"] == rep["sdf_share"]["channels_last"]
    test = rep["paper_test"]  # the TEST split: the model beside two baselines on the same frames
    assert test["frames"] == 4 and test["model_epoch"] == 2
    scores = [r["val_abs_rel"] for r in full["epochs"]]  # and the model chosen on the validation split
    assert test["best"]["epoch"] == 1 + scores.index(min(scores)) and test["best"]["val_abs_rel"] == min(scores)
    assert test["best"]["abs_rel"] > 0
    assert test["best"]["epoch"] != 2 or test["best"]["abs_rel"] == test["model"]["abs_rel"]
    assert all(test[name]["abs_rel"] > 0 and test[name]["rmse"] > 0 for name in ("model", "shading_prior", "constant"))
    share = rep["sdf_share"]
    assert share["share_first"] == 1 - share["case2_first_s"] / share["case4_first_s"]
    many = rep["many_runs"]  # the further runs, trained together
    assert [lv["k"] for lv in many["levels"]] == [1, 2] and [lv["completed"] for lv in many["levels"]] == [1, 2]
    assert many["levels"][0]["speedup_wall"] == 1.0 and many["levels"][1]["steps"] == 2 * many["steps_per_epoch"]
    table = (out / "gpu_check.md").read_text()
    assert "| paper profile run, Case 4 seed 0, 12 + 4 frames | 2 of 2 epochs" in table
    assert "agrees with cKDTree" in table
    assert "| TEST split, 4 frames (model after epoch 2): Abs Rel / RMSE | model " in table
    assert "| TEST split, the model of the least validation Abs Rel (epoch " in table
    assert "| paper profile run end to end (process start to exit" in table
    assert "| K runs together |" in table and "| 2 |" in table and "SDF loss share of a training step" in table


def test_the_status_check_refuses_passed_when_every_cuda_test_skipped():
    """A record of the form the dry run writes (every CUDA test skipped), its status planted as
    "passed" (what a status that trusted pytest's exit 0 would write), fails the check."""
    record = {"status": "skipped (no CUDA)", "summary": "9 skipped in 6.75s"}
    assert cuda_status_problems(record, cuda_available=False) == []
    planted = dict(record, status="passed")
    assert cuda_status_problems(planted, cuda_available=False)
    assert cuda_status_problems(planted, cuda_available=True)
    assert cuda_status_problems({"status": "passed", "summary": "1 failed, 8 passed in 32.95s"}, True)
    assert cuda_status_problems({"status": "passed", "summary": "8 passed, 1 skipped in 30.1s"}, True) == []


def test_all_skipped_is_not_passed():
    """pytest exits 0 when every test skips: the status tells that apart from a pass."""
    status = gpu_check.cuda_test_status
    assert status(0, "9 skipped in 6.75s", cuda_available=False) == "skipped (no CUDA)"
    assert status(0, "9 passed in 30.1s", cuda_available=True) == "passed"
    assert status(0, "8 passed, 1 skipped in 30.1s", cuda_available=True) == "passed"
    assert status(1, "1 failed, 8 passed in 32.95s", cuda_available=True) == "failed (exit 1)"
    assert status(5, "no tests ran in 0.01s", cuda_available=True) == "not run: no test was collected"
    assert status(0, "9 skipped in 1s", cuda_available=True).startswith("skipped")


def test_a_failing_step_is_recorded_and_the_rest_still_run(tmp_path, monkeypatch, capsys):
    """The record is written after every step: a step that raises is kept with its reason, the
    steps after it still run (here without --full, at toy sizes)."""

    def broken(*a, **k):
        raise RuntimeError("planted")

    monkeypatch.setattr(gpu_check, "bench_search", broken)
    monkeypatch.setattr(gpu_check, "time_training", lambda *a, **k: {"status": "completed", "epochs": []})
    out = tmp_path / "o"
    assert cli.main(["gpu-check", "--device", "cpu", "--tiny", "--no-pytest", "--out", str(out)]) == 0
    rep = json.loads((out / "gpu_check.json").read_text())
    assert rep["search"]["status"] == "failed: RuntimeError: planted" and rep["training"]["status"] == "completed"
    assert "| nearest-point search | failed: RuntimeError: planted |" in (out / "gpu_check.md").read_text()


def test_the_prediction_scales_measured_epochs_to_the_paper_split():
    # 10 training frames at 5 frames/s = 2 s of training; 4 s epochs leave 2 s for 5 validation frames
    rows = [{"epoch_s": 6.0, "train_frames_per_s": 2.5}, {"epoch_s": 4.0, "train_frames_per_s": 5.0}]
    p = gpu_check.predict_paper_time(rows, n_train=10, n_val=5)
    assert p["later_epoch_s"] == 3600 * 0.2 + 900 * 0.4
    assert p["first_epoch_s"] == 3600 * 0.4 + 900 * 0.4
    assert p["total_s"] == p["first_epoch_s"] + 17 * p["later_epoch_s"]


def test_a_folder_it_did_not_write_is_refused(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert cli.main(["gpu-check", "--device", "cpu", "--tiny", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and str(out) in err and "did not write" in err and len(err.splitlines()) == 1
    assert (out / "notes.txt").read_text() == "keep me" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_cuda_without_a_gpu_is_one_line(tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert cli.main(["gpu-check", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no CUDA device" in err and "--device cpu --tiny" in err


def _stated_figures(rec: dict) -> dict[str, str]:
    """The figures README and docs/timings.md quote from a gpu-check record, recomputed from it."""
    import statistics

    epochs, run = rec["paper_run"]["epochs"], rec["paper_run"]
    first, later = epochs[0]["epoch_s"], statistics.median(e["epoch_s"] for e in epochs[1:])
    test, share, search = rec["paper_test"], rec["sdf_share"], rec["search"]
    done = sum(e["epoch_s"] for e in epochs)
    return {
        "first": f"{first:.1f} s", "later": f"{later:.1f} s", "epochs": f"{done:.0f} s",
        "run": f"{run['run_s']:.1f} s ({run['run_s'] / 60:.2f} min)", "load": f"{run['load_data_s']:.1f} s",
        "rest": f"{run['run_s'] - done - run['load_data_s']:.1f} s",
        "search": f"{1e3 * search['methods']['triton']['batch_s']:.2f} ms",
        "share": f"{100 * share['share_later']:.1f} %", "share_first": f"{100 * share['share_first']:.1f} %",
        "model": f"{test['model']['abs_rel']:.4f}", "prior": f"{test['shading_prior']['abs_rel']:.4f}",
        "best": f"{test['best']['abs_rel']:.4f}", "best_epoch": f"epoch {test['best']['epoch']}",
        "nchw": f"{1e3 * search['network_fwd_bwd_nchw_s']:.1f} ms",
        "channels_last": f"{1e3 * search['network_fwd_bwd_channels_last_s']:.1f} ms",
        "data": f"{run['data_s']:.1f} s",
    }


def _normalised(name: str) -> str:
    return " ".join((ROOT / name).read_text().split())


def test_the_stated_gpu_figures_come_from_the_committed_record():
    """README and docs/timings.md quote the H200 record in benchmarks/gpu/; recomputed here."""
    rec = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-27_c.json").read_text())
    figures = _stated_figures(rec)
    assert figures["run"] == "211.9 s (3.53 min)"  # the figure the README states in bold
    texts = {name: _normalised(name) for name in ("README.md", "docs/timings.md")}
    in_readme = ("first", "later", "run", "search", "share", "model", "prior", "best", "best_epoch")

    def missing(text, keys=tuple(figures)):
        return [what for what in keys if figures[what] not in text]

    assert missing(texts["docs/timings.md"]) == []
    assert missing(texts["README.md"], in_readme) == []
    # beside the earlier checks: a later epoch against record b's and the first check's projection
    import statistics

    later = statistics.median(e["epoch_s"] for e in rec["paper_run"]["epochs"][1:])
    frames = statistics.median(e["train_frames_per_s"] for e in rec["paper_run"]["epochs"][1:])
    old = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-27_b.json").read_text())["paper_run"]["epochs"]
    first_check = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-26.json").read_text())["paper_run"]
    compared = [f"{statistics.median(e['epoch_s'] for e in old[1:]) / later:.2f}x faster",
                f"{first_check['prediction']['later_epoch_s'] / later:.1f}x", f"{frames:.1f} training frames/s"]
    assert [c for c in compared if c not in texts["docs/timings.md"]] == []
    # the check can fail: a text whose time disagrees with the record is caught, and so is a record
    # whose model scores differently from what the text states
    assert missing(texts["README.md"].replace("3.53 min", "3.35 min"), in_readme) == ["run"]
    rec["paper_test"]["model"]["abs_rel"] = rec["paper_test"]["shading_prior"]["abs_rel"] * 0.9
    figures = _stated_figures(rec)
    assert missing(texts["README.md"], in_readme) == ["model"]


def test_the_stated_throughput_and_first_epoch_figures_come_from_their_records():
    """docs/timings.md's table of runs together and its first-epoch figures, recomputed from the records."""
    import statistics

    text = _normalised("docs/timings.md")
    many = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-27_throughput.json").read_text())
    rows = [f"| {lv['k']} | {lv['wall_s']:.2f} | {lv['time_vs_one']:.2f} | {lv['steps_per_s_wall']:.2f} | "
            f"{lv['speedup_wall']:.2f} |" for lv in many["levels"]]
    assert [lv["completed"] for lv in many["levels"]] == [1, 2, 4, 8]
    assert [r for r in rows if r not in text] == []
    one = many["levels"][0]
    outside = one["wall_s"] - one["runs"][0]["epochs"][0]["epoch_s"]
    assert f"about {outside:.0f} s of the {one['wall_s']:.1f} s at K = 1" in text
    fe = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-27_first_epoch.json").read_text())
    steps = fe["steps"]
    n = fe["epochs"][0]["steps"]
    stated = [f"{steps[0]['s']:.2f} s", f"{steps[0]['searches_s'][0]:.2f} s",
              f"{1e3 * statistics.median(x['s'] for x in steps[1:n]):.1f} ms",
              f"{1e3 * statistics.median(x['s'] for x in steps[n:]):.1f} ms",
              f"{1e3 * statistics.median(x['searches_s'][1] for x in steps[1:n]):.1f} ms"]
    assert [f for f in stated if f not in text] == []
    k8 = many["levels"][-1]
    said = f"{k8['time_vs_one']:.2f}x one run's time, {k8['speedup_wall']:.2f}x the steps per second"
    assert said in _normalised("docs/training_and_evaluation.md")
    # a row planted with another wall time is caught
    assert rows[1].replace(f"{many['levels'][1]['wall_s']:.2f}", "99.99") not in text


def test_a_paper_run_cut_off_by_its_time_limit_is_recorded(tmp_path, monkeypatch):
    """--full-timeout reached: the run is stopped (or not started when the data took the time) and the
    record says so. How many epochs end inside 2 s depends on the machine, so both outcomes are checked:
    no epoch, and the test-split step says why it has no model; some epochs, and it scores the model
    of the last one recorded."""
    monkeypatch.setattr(gpu_check, "sdf_step_share", lambda *a, **k: {"status": "left out in this test"})
    monkeypatch.setattr(gpu_check, "many_runs", lambda *a, **k: {"status": "left out in this test"})
    out = tmp_path / "o"
    assert cli.main(["gpu-check", "--device", "cpu", "--tiny", "--full", "--no-pytest", "--full-timeout", "2",
                     "--out", str(out)]) == 0
    rep = json.loads((out / "gpu_check.json").read_text())
    run, tested = rep["paper_run"], rep["paper_test"]
    assert run["status"].startswith(("stopped at the time limit of", "not run: the data took the whole"))
    assert run["status"] in (out / "gpu_check.md").read_text()
    assert _cut_off_record_problems(run, tested) == []
    # the check can fail: a record that scores a model although no epoch ended, or the wrong epoch's model
    if run["epochs"]:
        assert _cut_off_record_problems(run, {**tested, "model_epoch": 0}) != []
    assert _cut_off_record_problems({**run, "epochs": []}, {"status": "completed", "model_epoch": 1}) != []


def _cut_off_record_problems(run: dict, tested: dict) -> list[str]:
    """What is wrong with a cut-off paper run's record: fewer epochs than asked, and a test-split score
    only of the last epoch recorded (none when no epoch ended)."""
    problems = []
    if len(run["epochs"]) >= run["epochs_asked"]:
        problems.append("every epoch ended, so the run was not cut off")
    if not run["epochs"] and not tested["status"].startswith("not run: "):
        problems.append("a model was scored although no epoch ended")
    if run["epochs"] and tested.get("model_epoch") != run["epochs"][-1]["epoch"]:
        problems.append(f"scored epoch {tested.get('model_epoch')}, not the last recorded")
    return problems


def test_sdf_share_in_words_calls_a_faster_case4_step_noise():
    from geodepth_lite.apps.gpu_check import share_words

    sh = {"case4_first_s": 0.100, "case2_first_s": 0.080, "share_first": 1 - 0.080 / 0.100}
    assert share_words(sh, "first") == "20.0 % (100.0 ms a step)"
    noisy = {"case4_first_s": 0.080, "case2_first_s": 0.100, "share_first": 1 - 0.100 / 0.080}
    assert share_words(noisy, "first").startswith("below the timing noise")
    assert "%" not in share_words(noisy, "first")
