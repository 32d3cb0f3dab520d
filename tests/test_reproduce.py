"""reproduce: every user error is caught before a notebook runs; runs, report, skip on rerun."""

import json
from pathlib import Path

import nbformat
import pytest

from geodepth_lite import reproduce


def _notebook(path: Path, params: str, body: str) -> Path:
    nb = nbformat.v4.new_notebook()
    cell = nbformat.v4.new_code_cell(params)
    cell.metadata["tags"] = ["parameters"]
    nb.cells = [nbformat.v4.new_markdown_cell("# test"), cell, nbformat.v4.new_code_cell(body)]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(nb, str(path))
    return path


BODY = """\
from geodepth_lite import notebook, reproduce
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
out = reproduce.resolve_run_dir(profile, run_dir)
notebook.save_table(out, f"{NAME}_numbers", ["what", "value"], [["scale", scale], ["profile", profile]], \
title="T{NAME}")
fig = plt.figure(); plt.plot([0, scale]); notebook.save_figure(fig, out, f"{NAME}_line")
(out / f"ran_{NAME}.txt").open("a").write("x")
"""


@pytest.fixture
def fake_notebooks(tmp_path, monkeypatch):
    d = tmp_path / "nbs"
    d.mkdir()
    _notebook(d / "01_first.ipynb",
              'profile = "teach"  # smoke | teach | paper\nrun_dir = ""  # out\nscale = 2.0  # a float',
              BODY.replace("{NAME}", "01"))
    _notebook(d / "02_second.ipynb",
              'profile = "teach"  # p\nrun_dir = ""  # out\nscale = 1.0  # a float\nlabel = "a"  # text',
              BODY.replace("{NAME}", "02"))
    (d / "scratch.ipynb").write_text("{}")  # not numbered: never run
    monkeypatch.setattr(reproduce, "notebooks_dir", lambda: d)
    return d


@pytest.fixture
def no_papermill(monkeypatch):
    import papermill

    def refuse(*a, **k):
        raise AssertionError("a notebook ran although the request was invalid")

    monkeypatch.setattr(papermill, "execute_notebook", refuse)


@pytest.mark.parametrize("argv, message", [
    (["--profile", "laptop"], "unknown profile 'laptop'"),
    (["-p", "epochs", "3"], "unknown notebook parameter 'epochs'"),
    (["-p", "scale", "big"], "parameter 'scale' of 01_first.ipynb expects float"),
    (["-p", "profile", "paper"], "use --profile"),
    (["--notebooks", "07"], "no notebook '07'"),
    (["--notebooks", "01", "-p", "label", "b"], "unknown notebook parameter 'label'"),
])
def test_bad_requests_fail_before_anything_runs(fake_notebooks, no_papermill, argv, message, capsys):
    from geodepth_lite import cli

    assert cli.main(["reproduce", *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (reproduce.utils.runs_dir()).exists()  # nothing written either


def test_the_real_notebooks_declare_profile_and_run_dir():
    nbs = reproduce.list_notebooks()
    for nb in nbs:
        params = reproduce.notebook_parameters(nb)
        assert params.get("profile") == "teach" and params.get("run_dir") == "", nb.name


def test_runs_writes_report_then_skips_completed_notebooks(fake_notebooks, tmp_path, capsys):
    from geodepth_lite import cli

    assert cli.main(["reproduce", "--profile", "smoke", "-p", "scale", "3", "--no-progress"]) == 0
    out = reproduce.utils.runs_dir() / "smoke"
    report = json.loads((out / "report.json").read_text())
    assert report["tables"]["01_numbers"]["rows"] == [["scale", 3], ["profile", "smoke"]]
    assert report["figures"] == ["figures/01_line.png", "figures/02_line.png"]
    md = (out / "report.md").read_text()
    assert "| scale | 3 |" in md and "![01_line](figures/01_line.png)" in md
    assert (out / "notebooks" / "02_second.ipynb").exists()

    # a rerun with the same request skips both; a changed parameter reruns them; --notebooks picks one
    assert cli.main(["reproduce", "--profile", "smoke", "-p", "scale", "3", "--no-progress"]) == 0
    assert (out / "ran_01.txt").read_text() == "x" and "skipped" in capsys.readouterr().out
    assert cli.main(["reproduce", "--profile", "smoke", "--notebooks", "2", "--no-progress"]) == 0
    assert (out / "ran_01.txt").read_text() == "x" and (out / "ran_02.txt").read_text() == "xx"


def test_a_failing_notebook_is_named_and_not_marked_complete(fake_notebooks, capsys):
    from geodepth_lite import cli

    _notebook(fake_notebooks / "03_broken.ipynb", 'profile = "teach"  # p\nrun_dir = ""  # out', "1 / 0")
    assert cli.main(["reproduce", "--profile", "smoke", "--notebooks", "03", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "03_broken.ipynb failed (ZeroDivisionError" in err
    out = reproduce.utils.runs_dir() / "smoke"
    assert (out / "notebooks" / "03_broken.ipynb").exists()  # the executed copy with the traceback
    assert not (out / ".reproduce" / "03_broken.json").exists()  # not marked complete: a rerun runs it again


def test_the_models_of_the_real_notebooks_are_trained_together():
    """reproduce trains what notebooks 04-07 load before it runs them: the predict model of 04, 06
    and 07 (one run folder), 07's model for real frames, and 05's case x seed runs, with 05's
    worker count."""
    from geodepth_lite import run_cache

    nbs = {p.name[:2]: p for p in reproduce.list_notebooks()}
    predict, real = run_cache.predict_settings("teach"), run_cache.real_settings("teach")
    runs, workers = reproduce.training_runs("teach", [(nbs["04"], {}), (nbs["05"], {"seeds": [0, 1], "workers": 1}),
                                                     (nbs["06"], {"seed": 2}), (nbs["07"], {})])
    assert runs[0] == (4, 0, predict) and runs[-2:] == [(4, 2, predict), (4, 0, real)] and len(runs) == 11
    assert runs[1:-2] == [(c, s, {}) for c in (1, 2, 3, 4) for s in (0, 1)] and workers == 1
    assert reproduce.training_runs("teach", [(nbs["01"], {}), (nbs["05"], {})]) == (
        [(c, s, {}) for c in (1, 2, 3, 4) for s in (0, 1, 2)], None)
    assert reproduce.training_runs("teach", [(nbs["00"], {})]) == ([], None)


def test_a_notebook_that_must_train_says_so_with_the_expected_minutes(monkeypatch, capsys):
    from geodepth_lite import config, run_cache

    teach = run_cache.estimated_minutes(config.make_config("teach", 1, 0))
    predict = run_cache.estimated_minutes(config.make_config("teach", 4, 0, **run_cache.predict_settings("teach")))
    assert 2.4 <= teach <= 3.4 and 8.0 <= predict <= 12.0  # docs/timings.md: 2.6-3.0 and 9.3 min
    trained = []
    monkeypatch.setattr(run_cache, "fit", lambda cfg, run_dir, **kw: trained.append(run_dir) or run_dir / "ckpt.pt")
    run_cache.ensure_checkpoint("teach", 1, 0)
    said = capsys.readouterr().out
    assert trained and "Case 1, seed 0 (teach, 64 px)" in said and "about 3 min" in said
    run_cache.ensure_checkpoint("teach", 1, 0, announce=False)
    assert capsys.readouterr().out == ""


def test_the_study_target_runs_notebook_05_on_its_own_tables(tmp_path, monkeypatch, capsys):
    """``reproduce --study``: the study's tables first (``run_study``, here a stand-in), then notebook
    05 alone, forced, with ``study_tables`` pointing at them; its dry run trains nothing."""
    from geodepth_lite import cli

    d = tmp_path / "nbs"
    d.mkdir()
    body = 'from pathlib import Path\nPath(run_dir, "seen.txt").write_text(study_tables)'
    _notebook(d / "04_other.ipynb", 'profile = "teach"  # p\nrun_dir = ""  # out', "raise SystemExit('ran')")
    _notebook(d / "05_study.ipynb", 'profile = "teach"  # p\nrun_dir = ""  # out\nstudy_tables = ""  # t', body)
    monkeypatch.setattr(reproduce, "notebooks_dir", lambda: d)
    tables = tmp_path / "tables"
    calls = []
    monkeypatch.setattr(reproduce, "run_study", lambda profile, out, progress: calls.append(profile) or tables)
    assert cli.main(["reproduce", "--study", "--notebooks", "05"]) == 2
    assert "leave out --notebooks" in capsys.readouterr().err
    assert cli.main(["reproduce", "--study", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "study: 48 runs (48 to train)" in out and "05_study.ipynb" in out and "04_other" not in out
    assert calls == []
    run_dir = tmp_path / "run"
    assert cli.main(["reproduce", "--study", "--out", str(run_dir), "--no-progress"]) == 0
    assert calls == ["teach"] and (run_dir / "seen.txt").read_text() == str(tables)


def test_the_study2_target_runs_notebook_05_on_the_second_studys_tables(tmp_path, monkeypatch, capsys):
    """``reproduce --study2``: refused before any training when notebook 05 does not declare
    ``study2_tables``; else the tables first (``run_study2``, a stand-in), then notebook 05 with
    ``study2_tables`` pointing at them; its dry run trains nothing."""
    from geodepth_lite import cli

    d = tmp_path / "nbs"
    d.mkdir()
    _notebook(d / "05_study.ipynb", 'profile = "teach"  # p\nrun_dir = ""  # out\nstudy_tables = ""  # t', "x = 1")
    monkeypatch.setattr(reproduce, "notebooks_dir", lambda: d)
    tables, calls = tmp_path / "tables2", []
    monkeypatch.setattr(reproduce, "run_study2", lambda profile, out, progress: calls.append(profile) or tables)
    assert cli.main(["reproduce", "--study2", "--no-progress"]) == 2
    assert "does not declare the parameter 'study2_tables'" in capsys.readouterr().err and calls == []
    body = 'from pathlib import Path\nPath(run_dir, "seen.txt").write_text(study2_tables)'
    _notebook(d / "05_study.ipynb", 'profile = "teach"  # p\nrun_dir = ""  # out\nstudy2_tables = ""  # t', body)
    assert cli.main(["reproduce", "--study2", "--notebooks", "05"]) == 2
    assert "leave out --notebooks" in capsys.readouterr().err
    assert cli.main(["reproduce", "--study2", "--dry-run"]) == 0
    assert "study2: 24 runs (24 to train)" in capsys.readouterr().out and calls == []
    run_dir = tmp_path / "run"
    assert cli.main(["reproduce", "--study2", "--out", str(run_dir), "--no-progress"]) == 0
    assert calls == ["teach"] and (run_dir / "seen.txt").read_text() == str(tables)
