"""Every training run's log.json records where and with what it was made, one record per session."""

import json
import subprocess

import numpy
import torch

from geodepth_lite import utils
from geodepth_lite.training import config, provenance, train


def _cfg(root, **kw):
    return config.make_config("smoke", 4, 0, dataset=str(root), batch_size=4, image_size=32, **kw)


def _sessions(run) -> list[dict]:
    return json.loads((run / "log.json").read_text())["provenance"]


def test_a_fresh_run_logs_its_provenance(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, epochs=1)
    before = provenance.utc_now()
    train.fit(cfg, tmp_path / "run", progress=False)
    after = provenance.utc_now()
    (rec,) = _sessions(tmp_path / "run")
    assert provenance.problems(rec, cfg) == []
    assert before <= rec["start_utc"] <= rec["end_utc"] <= after
    assert (rec["first_epoch"], rec["epochs_done"]) == (0, 1)
    assert rec["config_hash"] == config.config_hash(cfg)
    assert rec["torch"] == torch.__version__ and rec["numpy"] == numpy.__version__
    # the threads the run trained with: the profile's where it fixes them (fit restores the caller's after)
    assert rec["device"] == "cpu" and rec["threads"] == (cfg["threads"] or torch.get_num_threads()) and rec["cpu"]
    root = utils.project_root()
    if root is not None and (root / ".git").exists():  # a checkout: the commit is HEAD's
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
        assert rec["git_commit"] == head.stdout.strip() and isinstance(rec["git_clean"], bool)


def test_a_resumed_run_keeps_each_sessions_record(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, epochs=2)
    train.fit(cfg, tmp_path / "run", progress=False, stop_after=1)
    (first,) = _sessions(tmp_path / "run")
    train.fit(cfg, tmp_path / "run", progress=False, resume=True)
    again, second = _sessions(tmp_path / "run")
    assert again == first and (first["first_epoch"], first["epochs_done"]) == (0, 1)
    assert (second["first_epoch"], second["epochs_done"]) == (1, 1) and second["start_utc"] >= first["end_utc"]
    assert provenance.problems(second, cfg) == []


def test_the_record_check_can_fail(smoke_root):
    cfg = _cfg(smoke_root, epochs=1)
    good = {**provenance.session(cfg, "cpu", 0), "end_utc": "2099-01-01T00:00:00Z", "epochs_done": 1}
    assert provenance.problems(good, cfg) == []
    assert provenance.problems({k: v for k, v in good.items() if k != "git_commit"}, cfg) == ["no git_commit"]
    assert provenance.problems({**good, "end_utc": None}, cfg) == ["its end is not recorded"]
    assert "before it starts" in provenance.problems({**good, "end_utc": "2000-01-01T00:00:00Z"}, cfg)[0]
    other = _cfg(smoke_root, epochs=2)  # another configuration's hash
    assert "is not the run's" in provenance.problems(good, other)[0]
    assert provenance.problems({**good, "epochs_done": 0}, cfg) == ["no epoch recorded"]


def test_study_tables_carry_each_run_s_sessions_and_invent_none(tmp_path):
    """provenance.csv beside a study's tables: one row per session of each run, read from its log; a run
    whose log has no record gets empty fields, not made-up ones."""
    import csv
    import json as _json

    from geodepth_lite.evaluation import study

    def run(name, sessions):
        folder = tmp_path / name
        folder.mkdir()
        log = {"epochs": []} if sessions is None else {"epochs": [], "provenance": sessions}
        (folder / "log.json").write_text(_json.dumps(log))
        return folder / "checkpoint.pt"

    first = {k: f"{k}-1" for k in provenance.FIELDS}
    second = {**first, "start_utc": "2026-11-27T10:00:00Z", "git_commit": "abc", "git_clean": False}
    paths = {("silog", 1, 0): run("a", [first, second]), ("silog", 4, 1): run("b", None)}
    rows = study.provenance_rows(paths)
    assert [(r["case"], r["seed"], r["session"]) for r in rows] == [(1, 0, 0), (1, 0, 1), (4, 1, 0)]
    assert rows[1]["git_commit"] == "abc" and rows[1]["git_clean"] is False and rows[0]["git_commit"] == "git_commit-1"
    assert all(rows[2][k] == "" for k in provenance.FIELDS)  # trained before runs kept a record
    out = study.write_tables(tmp_path / "tables", [{"x": 1}], [{"y": 2}], [{"z": 3}], rows)
    back = list(csv.DictReader(open(out / study.PROVENANCE_CSV)))
    assert [r["start_utc"] for r in back] == ["start_utc-1", "2026-11-27T10:00:00Z", ""]
    # the check can fail: a reader that keeps only a run's last session gives other rows
    keep_last = study.provenance.earlier_sessions
    try:
        study.provenance.earlier_sessions = lambda log: keep_last(log)[-1:]
        assert [(r["case"], r["seed"], r["session"]) for r in study.provenance_rows(paths)] != [
            (1, 0, 0), (1, 0, 1), (4, 1, 0)]
    finally:
        study.provenance.earlier_sessions = keep_last
