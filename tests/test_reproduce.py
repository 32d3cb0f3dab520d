"""reproduce: every user error is caught before a notebook runs; runs, report, skip on rerun."""

import json
from pathlib import Path

import nbformat
import pytest

from geodepth_lite.workbook import reproduce


def _notebook(path: Path, params: str, body: str) -> Path:
    nb = nbformat.v4.new_notebook()
    cell = nbformat.v4.new_code_cell(params)
    cell.metadata["tags"] = ["parameters"]
    nb.cells = [nbformat.v4.new_markdown_cell("# test"), cell, nbformat.v4.new_code_cell(body)]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(nb, str(path))
    return path


BODY = """\
from geodepth_lite.training import config
from geodepth_lite.workbook import notebook, reproduce
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
out = reproduce.resolve_run_dir(config.profile(profile), run_dir)
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
    from geodepth_lite.training import config

    nbs = {p.name[:2]: p for p in reproduce.list_notebooks()}
    teach = config.profile("teach")
    runs, workers = reproduce.training_runs(teach, [(nbs["04"], {}), (nbs["05"], {"seeds": [0, 1], "workers": 1}),
                                                   (nbs["06"], {"seed": 2}), (nbs["07"], {})])
    assert runs[0] == teach.predict_run(4, 0) and len(runs) == 11
    assert runs[-2:] == [teach.predict_run(4, 2), teach.real_run(4, 0)]
    assert runs[1:-2] == [teach.run(c, s) for c in (1, 2, 3, 4) for s in (0, 1)] and workers == 1
    assert reproduce.training_runs(teach, [(nbs["01"], {}), (nbs["05"], {})]) == (
        [teach.run(c, s) for c in (1, 2, 3, 4) for s in (0, 1)], None)
    assert reproduce.training_runs(teach, [(nbs["00"], {})]) == ([], None)


def test_a_notebook_that_must_train_says_so_with_the_expected_minutes(monkeypatch, capsys):
    from geodepth_lite.training import config, run_cache

    prof = config.profile("teach")
    teach = run_cache.estimated_minutes(prof.run(1, 0))
    predict = run_cache.estimated_minutes(prof.predict_run(4, 0))
    assert 2.4 <= teach <= 3.4 and 8.0 <= predict <= 12.0  # docs/timings.md: 2.6-3.0 and 9.3 min
    trained = []
    monkeypatch.setattr(run_cache, "fit", lambda cfg, run_dir, **kw: trained.append(run_dir) or run_dir / "ckpt.pt")
    run_cache.ensure_checkpoint(prof.run(1, 0))
    said = capsys.readouterr().out
    assert trained and "Case 1, seed 0 (teach, 64 px)" in said and "about 3 min" in said
    run_cache.ensure_checkpoint(prof.run(1, 0), announce=False)
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
    monkeypatch.setattr(reproduce, "run_study", lambda prof, out, progress: calls.append(prof.name) or tables)
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
    monkeypatch.setattr(reproduce, "run_study2", lambda prof, out, progress: calls.append(prof.name) or tables)
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


# --------------------------------------------------------------------------- the jobs' scheduler (fake jobs)


class ThreadJob:
    """A stand-in for ``reproduce.ProcessJob``: the job's function in a thread of this process."""

    def __init__(self, job, env=None):
        import threading

        self.job, self.error = job, None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            self.job.fn()
        except Exception as exc:  # noqa: BLE001 - the scheduler reports it
            self.error = reproduce.failure_line(self.job.name, exc)

    def result(self):
        return None if self.thread.is_alive() else (self.error or "")

    def stop(self):
        pass


class Timeline:
    """Fake jobs that record when they start and end (seconds since the first start)."""

    def __init__(self):
        import threading
        import time

        self.lock, self.t0, self.clock, self.spans = threading.Lock(), time.monotonic(), time.monotonic, {}

    def job(self, name, seconds, fail=False):
        def fn():
            import time

            with self.lock:
                self.spans[name] = [self.clock() - self.t0, None]
            time.sleep(seconds)
            with self.lock:
                self.spans[name][1] = self.clock() - self.t0
            if fail:
                raise RuntimeError("planted failure")

        return fn


def max_running(spans: dict) -> int:
    """The most jobs whose [start, end) intervals overlap at one instant."""
    edges = sorted([(s, 1) for s, _ in spans.values()] + [(e, -1) for _, e in spans.values()])  # ends first
    now = most = 0
    for _, step in edges:
        now += step
        most = max(most, now)
    return most


def too_early(spans: dict, needs: dict) -> list[str]:
    """The jobs that started before one of the jobs they need had ended."""
    return [n for n, ns in needs.items() if n in spans and any(spans[n][0] < spans[d][1] for d in ns)]


def test_the_timeline_checks_catch_a_bad_schedule():
    """The two checks below flag three jobs at once, and a job started before its need ended."""
    bad = {"a": [0.0, 1.0], "b": [0.1, 0.5], "c": [0.2, 0.6], "n": [0.9, 1.2]}
    assert max_running(bad) == 3 and max_running({"a": [0, 1], "b": [1, 2]}) == 1
    assert too_early(bad, {"n": ("a",), "c": ("b",)}) == ["n", "c"]
    assert too_early(bad, {"n": ("b", "c")}) == []


def _fake_jobs(tl: Timeline, fail: str = ""):
    J = reproduce.Job
    jobs = [J("predict", tl.job("predict", 0.30, fail == "predict"), seconds=600),
            J("abl1", tl.job("abl1", 0.12), seconds=180), J("abl2", tl.job("abl2", 0.12), seconds=180),
            J("abl3", tl.job("abl3", 0.12), seconds=180),
            J("nb00", tl.job("nb00", 0.05), (), 4, "notebook"), J("nb01", tl.job("nb01", 0.05), (), 21, "notebook"),
            J("nb04", tl.job("nb04", 0.05), ("predict",), 50, "notebook"),
            J("nb05", tl.job("nb05", 0.05), ("abl1", "abl2", "abl3"), 30, "notebook"),
            J("nb07", tl.job("nb07", 0.05), ("predict", "abl1"), 37, "notebook")]
    return jobs, {j.name: j.needs for j in jobs}


def test_the_scheduler_keeps_two_jobs_running_each_after_its_needs():
    """At most two at once (and two at once while enough are ready); a notebook only after the
    models it loads; the notebooks that load none start while the models still train."""
    tl = Timeline()
    jobs, needs = _fake_jobs(tl)
    reproduce.run_jobs(jobs, 2, start=ThreadJob, poll_s=0.002)
    spans = tl.spans
    assert sorted(spans) == sorted(needs) and all(e is not None for _, e in spans.values())
    assert max_running(spans) == 2
    assert too_early(spans, needs) == []
    first_model = min(spans[n][1] for n in ("predict", "abl1", "abl2", "abl3"))
    assert spans["nb00"][0] < first_model  # beside the models from the start, not after them
    assert spans["predict"][0] < spans["abl1"][0]  # the longest chain of work first among the models


def test_a_failed_job_stops_new_ones_and_is_named():
    """The failed job is named in one line; the job running beside it finishes; no job starts after."""
    tl = Timeline()
    jobs, _ = _fake_jobs(tl, fail="predict")
    with pytest.raises(reproduce.JobFailed) as err:
        reproduce.run_jobs(jobs, 2, start=ThreadJob, poll_s=0.002)
    msg = str(err.value)
    assert msg.startswith("predict failed (RuntimeError: planted failure)") and "\n" not in msg
    failed_at = tl.spans["predict"][1]
    assert all(s < failed_at for n, (s, _) in tl.spans.items())  # nothing started after the failure
    assert all(e is not None for _, e in tl.spans.values())  # the running ones finished
    assert "nb04" not in tl.spans and "nb07" not in tl.spans


def test_the_time_left_counts_the_longest_chain_and_the_workers():
    """Hand-computed: A 100 s and B 100 s, C 50 s after A, on two workers: the chain A-C (150 s) is
    longer than the work over the workers (250 / 2); A 40 s in, 110 s; everything done, 0."""
    J = reproduce.Job
    jobs = [J("A", None, (), 100), J("B", None, (), 100), J("C", None, ("A",), 50, "notebook")]
    assert reproduce.seconds_left(jobs, set(), {}, 2) == 150
    assert reproduce.seconds_left(jobs, set(), {"A": 40, "B": 40}, 2) == 110
    assert reproduce.seconds_left(jobs, {"A"}, {"B": 90}, 1) == 60
    assert reproduce.seconds_left(jobs, {"A", "B", "C"}, {}, 2) == 0
    assert reproduce.seconds_left([J("A", None, (), 100), J("B", None, (), 100)], set(), {}, 2) == 100


def test_the_time_left_follows_this_machines_pace():
    """Hand-computed: A and B train (100 s expected each), C is a notebook (50 s) after A. A took 200 s
    here, so B is expected at 200 s and, no notebook having finished, C at 2 x 50 s: with B 50 s in on
    one worker, 150 + 100 = 250 s left (the expected times alone say 50 + 50 = 100 s)."""
    J = reproduce.Job
    jobs = [J("A", None, (), 100), J("B", None, (), 100), J("C", None, ("A",), 50, "notebook")]
    assert reproduce.pace(jobs, {}) == {"train": 1.0, "notebook": 1.0}
    assert reproduce.pace(jobs, {"A": 200.0}) == {"train": 2.0, "notebook": 2.0}
    assert reproduce.seconds_left(jobs, {"A"}, {"B": 50}, 1, {"A": 200.0}) == 250
    assert reproduce.seconds_left(jobs, {"A"}, {"B": 50}, 1) == 100  # the estimate that undercounts
    # a kind's own finished jobs set its pace: the notebook ran at half its expected time
    assert reproduce.pace(jobs, {"A": 200.0, "C": 25.0}) == {"train": 2.0, "notebook": 0.5}
    assert reproduce.seconds_left(jobs, {"A", "C"}, {"B": 50}, 1, {"A": 200.0, "C": 25.0}) == 150


def test_the_progress_line_in_place_on_a_terminal_and_as_lines_elsewhere():
    import io

    plain = io.StringIO()
    show = reproduce.JobProgress(9, 2, stream=plain, tty=False, every=3600)
    show.update(["predict", "nb00"], 3, 600, changed=True)
    show.update(["predict", "nb00"], 3, 590)  # nothing changed, not yet time for a line
    show.event("nb00 done in 4 s")
    assert plain.getvalue() == ("[reproduce] 3/9 done; running: predict, nb00; about 10 min left\n"
                                "[reproduce] nb00 done in 4 s\n")
    term = io.StringIO()
    show = reproduce.JobProgress(9, 2, stream=term, tty=True)
    show.update(["predict"], 4, 30)
    show.update(["abl1"], 5, 20)
    assert "\n" not in term.getvalue() and term.getvalue().count("\r") == 2
    assert term.getvalue().endswith("[reproduce] 5/9 done; running: abl1; under a minute left\x1b[K")
    show.close()
    assert term.getvalue().endswith("\n")


def test_jobs_run_in_processes_of_their_own_and_a_failure_names_its_log(tmp_path):
    """The real ``ProcessJob``: one job writes a file, one divides by zero; the failure's line names
    the job and its log, which holds the traceback."""
    import functools
    import operator
    import os

    ok, log = tmp_path / "ok.txt", tmp_path / "bad.txt"
    jobs = [reproduce.Job("writer", functools.partial(Path.write_text, ok, "x"), log=tmp_path / "w.txt"),
            reproduce.Job("divider", functools.partial(operator.truediv, 1, 0), log=log)]
    with pytest.raises(reproduce.JobFailed) as err:
        reproduce.run_jobs(jobs, 2, poll_s=0.05)
    assert str(err.value) == f"divider failed (ZeroDivisionError: division by zero); its output: {log}"
    assert ok.read_text() == "x" and "ZeroDivisionError" in log.read_text()
    # a process that ends without a word (killed, or it could not start) is named with its exit code
    with pytest.raises(reproduce.JobFailed, match="^quitter failed: its process ended with exit code 3$"):
        reproduce.run_jobs([reproduce.Job("quitter", functools.partial(os._exit, 3))], 1, poll_s=0.05)


# --------------------------------------------------------------------------- reproduce with fake jobs


@pytest.fixture
def fake_jobs(tmp_path, monkeypatch):
    """Notebooks 01 (no model), 02 (cases 1 and 2 of the ablation) and 03 (no model); training and
    notebook execution replaced by fakes that record their spans and write tables as a notebook does;
    the jobs run in threads. Case 2 trains longest: 02 ends last."""
    from geodepth_lite.training import run_cache
    from geodepth_lite.workbook import notebook

    d = tmp_path / "nbs"
    d.mkdir()
    params = 'profile = "teach"  # p\nrun_dir = ""  # out'
    for name in ("01_first", "02_models", "03_third"):
        _notebook(d / f"{name}.ipynb", params, "x = 1")
    nb = nbformat.read(str(d / "02_models.ipynb"), as_version=4)
    nb.metadata["geodepth_lite"] = {"models": [{"cases": [1, 2], "seeds": [0], "settings": "ablation"}]}
    nbformat.write(nb, str(d / "02_models.ipynb"))
    monkeypatch.setattr(reproduce, "notebooks_dir", lambda: d)
    tl = Timeline()
    delay = {"01_first": 0.3, "02_models": 0.02, "03_third": 0.01, "case1": 0.1, "case2": 0.8}

    def fake_notebook(nb, params, out, *, inject_run_dir, progress):
        tl.job(nb.stem, delay[nb.stem])()
        k = nb.stem[:2]
        notebook.save_table(out, f"{k}_numbers", ["what", "value"], [["k", int(k)]], title=f"T{k}")
        (out / "figures").mkdir(exist_ok=True)
        (out / "figures" / f"{k}_line.png").write_bytes(b"png")
        reproduce.utils.write_json_atomic(out / reproduce.MARKER_DIR / f"{nb.stem}.json",
                                          {**reproduce._marker(nb, params), "seconds": float(k) * 60})
        return float(k)

    def fake_train(run, *, after=None, progress=False):
        tl.job(f"case{run.case}", delay[f"case{run.case}"])()

    monkeypatch.setattr(reproduce, "run_notebook", fake_notebook)
    monkeypatch.setattr(run_cache, "train_run", fake_train)
    monkeypatch.setattr(run_cache, "is_complete", lambda *a, **k: False)
    monkeypatch.setattr(reproduce, "prepare_training", lambda *a, **k: None)
    monkeypatch.setattr(reproduce, "ProcessJob", ThreadJob)
    monkeypatch.setattr(reproduce, "JOB_POLL_S", 0.005)
    return tl


def test_reproduce_trains_and_runs_side_by_side_and_the_report_keeps_its_order(fake_jobs, capsys):
    """Through the command: two at once, notebook 02 after both of its models, 01 and 03 beside them
    while they train; 02 ends last, and the report still reads 01, 02, 03."""
    from geodepth_lite import cli

    assert cli.main(["reproduce", "--profile", "smoke"]) == 0
    spans = fake_jobs.spans
    assert sorted(spans) == ["01_first", "02_models", "03_third", "case1", "case2"]
    assert max_running(spans) == 2
    assert too_early(spans, {"02_models": ("case1", "case2")}) == []
    assert spans["01_first"][0] < min(spans["case1"][1], spans["case2"][1])
    assert spans["03_third"][0] < spans["case2"][1]
    assert spans["02_models"][1] > max(spans["01_first"][1], spans["03_third"][1])  # 02 ended last
    out = reproduce.utils.runs_dir() / "smoke"
    md = (out / "report.md").read_text()
    heads = [line for line in md.splitlines() if line.startswith("## ")]
    assert heads == ["## 01_first", "## 02_models", "## 03_third"]
    assert md.index("| 01_first | 1.0 |") < md.index("| 02_models | 2.0 |") < md.index("| 03_third | 3.0 |")
    report = json.loads((out / "report.json").read_text())
    assert list(report["tables"]) == ["01_numbers", "02_numbers", "03_numbers"]
    assert report["figures"] == ["figures/01_line.png", "figures/02_line.png", "figures/03_line.png"]
    said = capsys.readouterr().out
    assert "2 model(s) to train and 3 notebook(s) to run, 2 at a time" in said
    assert "[reproduce] 5/5 done; running: nothing; under a minute left" in said


def test_a_failed_training_job_ends_the_command_with_its_name(fake_jobs, monkeypatch, capsys):
    """Case 2's training fails: one line names it, exit 1; the notebook that loads it never starts,
    the notebooks that ran beside it keep what they wrote; no report."""
    from geodepth_lite import cli
    from geodepth_lite.training import run_cache

    trained = run_cache.train_run

    def failing(run, **kw):
        trained(run, **kw)
        if run.case == 2:
            raise ValueError("planted")

    monkeypatch.setattr(run_cache, "train_run", failing)
    assert cli.main(["reproduce", "--profile", "smoke", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: case 2 seed 0 (64 px) failed (ValueError: planted)")
    assert sorted(fake_jobs.spans) == ["01_first", "03_third", "case1", "case2"]
    out = reproduce.utils.runs_dir() / "smoke"
    assert not (out / "report.md").exists()
    assert (out / ".reproduce" / "01_first.json").exists() and (out / "tables" / "03_numbers.json").exists()


def test_the_real_notebooks_jobs_wait_for_the_models_they_load(tmp_path, monkeypatch):
    """From the real notebooks' metadata (nothing trained): 10 training jobs; 00-03 need none, 04
    and 06 the predict model, 05 the eight ablation runs, 07 the predict model and the one for real
    frames. Estimates: ``run_cache.estimated_minutes`` and each notebook's recorded duration."""
    from geodepth_lite.training import config, run_cache

    monkeypatch.setattr(run_cache, "is_complete", lambda *a, **k: False)
    monkeypatch.setattr(reproduce, "prepare_training", lambda *a, **k: None)
    plan = [(nb, {"profile": "teach", "run_dir": str(tmp_path)}, False) for nb in reproduce.list_notebooks()]
    jobs, slots = reproduce.plan_jobs(config.profile("teach"), plan, tmp_path, inject_run_dir=True, progress=False)
    assert slots == max(1, reproduce.os.cpu_count() or 1)
    trains = {j.name: j for j in jobs if j.kind == "train"}
    predict, real = "case 4 seed 0 (predict model, 96 px)", "case 4 seed 0 (real model, 96 px)"
    ablation = {f"case {c} seed {s} (64 px)" for c in (1, 2, 3, 4) for s in (0, 1)}
    assert set(trains) == ablation | {predict, real}
    needs = {j.name[:2]: set(j.needs) for j in jobs if j.kind == "notebook"}
    assert needs == {"00": set(), "01": set(), "02": set(), "03": set(), "04": {predict}, "05": ablation,
                     "06": {predict}, "07": {predict, real}}
    assert trains[predict].seconds == 60 * run_cache.estimated_minutes(config.profile("teach").predict_run())
    for j in jobs:
        if j.kind == "notebook":
            nb = next(nb for nb, _, _ in plan if nb.stem == j.name)
            assert j.seconds == json.loads(nb.read_text())["metadata"]["papermill"]["duration"] > 0


def _teach_folder_names(prof) -> list[str]:
    plan = [(nb, {"profile": "teach"}) for nb in reproduce.list_notebooks()]
    return sorted(run.folder_name for run in reproduce.training_runs(prof, plan)[0])


def test_the_run_folders_of_the_previous_release_are_still_found():
    """The teach models a workspace (or a class bundle, which keeps the folder names) holds from before run
    configurations became objects: reproduce names exactly those folders, so it finds them and trains none."""
    from geodepth_lite.training import config

    committed = json.loads((Path(__file__).parent / "data" / "teach_run_folders.json").read_text())
    assert _teach_folder_names(config.profile("teach")) == committed["folders"]


def test_the_folder_check_sees_a_changed_setting(monkeypatch):
    """One more epoch in the teach profile renames every folder: the check above would fail."""
    from geodepth_lite.training import config

    committed = json.loads((Path(__file__).parent / "data" / "teach_run_folders.json").read_text())["folders"]
    monkeypatch.setitem(config.PROFILES, "teach", dict(config.PROFILES["teach"],
                                                       epochs=config.PROFILES["teach"]["epochs"] + 1))
    assert not set(_teach_folder_names(config.profile("teach"))) & set(committed)
