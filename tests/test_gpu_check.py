"""``python -m geodepth_lite gpu-check``: its dry run (``--device cpu --tiny``) runs every step's glue here."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from geodepth_lite import cli, gpu_check

ROOT = Path(__file__).resolve().parents[1]

# imports a GPU machine may lack: gpu-check and training must not need them
HEAVY = ("matplotlib", "vtk", "vtkmodules", "imageio", "tifffile", "ipywidgets", "IPython", "pandas", "papermill",
         "nbformat")


def test_the_dry_run_writes_its_json_and_table_without_heavy_imports(tmp_path):
    out = tmp_path / "check"
    blocker = (
        "import sys, runpy\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] in {HEAVY!r}:\n"
        "            raise ImportError('not on the GPU machine: ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "sys.argv = ['geodepth_lite'] + sys.argv[1:]\n"
        "runpy.run_module('geodepth_lite', run_name='__main__')\n"
    )
    proc = subprocess.run([sys.executable, "-c", blocker, "gpu-check", "--device", "cpu", "--tiny", "--full", "--out",
                           str(out)], capture_output=True, text=True, timeout=170, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rep = json.loads((out / "gpu_check.json").read_text())
    assert rep["tiny"] and rep["environment"]["device"] == "cpu"
    assert rep["search"]["agree"] == rep["search"]["queries"] > 0
    assert rep["training"]["status"] == "completed" and len(rep["training"]["epochs"]) == 2
    pred = rep["training"]["prediction"]
    assert pred["total_s"] == pytest.approx(pred["first_epoch_s"] + 17 * pred["later_epoch_s"], abs=1.0)
    assert rep["cuda_tests"]["status"] in ("passed", "not run: pytest is not installed")
    full = rep["paper_run"]  # --full: the profile's own run, here at toy sizes
    assert full["status"] == "completed" and (full["train_frames"], full["val_frames"]) == (12, 4)
    assert [r["epoch"] for r in full["epochs"]] == [1, 2] and all(r["val_rmse"] > 0 for r in full["epochs"])
    table = (out / "gpu_check.md").read_text()
    assert "| predicted paper profile" in table and "agrees with cKDTree" in table
    assert "| paper profile run, Case 4 seed 0, 12 + 4 frames | 2 of 2 epochs" in table


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


def test_the_stated_gpu_figures_come_from_the_committed_record():
    """README and docs/timings.md quote the H200 record in benchmarks/gpu/; recomputed here."""
    import statistics

    rec = json.loads((ROOT / "benchmarks" / "gpu" / "h200_2026-11-26.json").read_text())
    epochs = rec["paper_run"]["epochs"]
    first, later = epochs[0]["epoch_s"], statistics.median(e["epoch_s"] for e in epochs[1:])
    figures = {
        "first": f"{first:.1f} s", "later": f"{later:.1f} s", "total": f"{(first + 17 * later) / 60:.1f} min",
        "field": f"{1e3 * rec['search']['search_batch_s'] / rec['search']['batch']:.2f} ms per field",
        "net": f"{1e3 * rec['search']['network_fwd_bwd_s']:.1f} ms",
        "step": f"{1e3 * 20 / statistics.median(e['train_frames_per_s'] for e in epochs[1:]):.0f} ms",
        "done": f"{len(epochs)} of 18 epochs",
    }
    assert figures["total"] == "11.7 min"  # the figure the README states in bold
    texts = {name: " ".join((ROOT / name).read_text().split()) for name in ("README.md", "docs/timings.md")}

    def missing(text):
        return [what for what, fig in figures.items() if fig not in text]

    for name, text in texts.items():
        assert missing(text) == [], f"{name} does not state the record's {missing(text)}"
    # the check can fail: a text whose total disagrees with the record is caught
    assert missing(texts["README.md"].replace("11.7 min", "12.1 min")) == ["total"]
