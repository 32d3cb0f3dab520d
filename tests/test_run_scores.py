"""A run's scores kept in its run folder: scored once, reused while nothing they depend on changed,
recomputed when the checkpoint, an evaluation set or the scoring code changed, and a damaged file
named and replaced rather than trusted."""

import functools
import hashlib
import json
import pickle
import shutil
import warnings
from pathlib import Path

import pytest
import torch
from conftest import save_untrained_checkpoint

from geodepth_lite.core import metrics
from geodepth_lite.evaluation import evaluate, run_scores, study
from geodepth_lite.training import config, run_cache

PRIMARY = study.PRIMARY


@pytest.fixture
def counted(monkeypatch):
    """Every evaluation run_scores makes, counted: calls["n"]."""
    calls = {"n": 0}
    real = evaluate.evaluate_model

    def counting(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(run_scores.evaluate, "evaluate_model", counting)
    return calls


@pytest.fixture
def run(tmp_path):
    """An untrained checkpoint in a run folder of its own (network input 32)."""
    folder = tmp_path / "runs" / "case1_seed0-00000000"
    folder.mkdir(parents=True)
    return save_untrained_checkpoint(folder / "checkpoint.pt")


@pytest.fixture
def sets(smoke_root):
    """Two small evaluation sets: the smoke dataset's test split (the primary set) and its validation split."""
    return {PRIMARY: evaluate.open_eval_dataset(str(smoke_root), split="test"),
            "other": evaluate.open_eval_dataset(str(smoke_root), split="val")}


def test_a_run_is_scored_once_and_read_back_the_same(run, sets, counted):
    first = run_scores.scores(run, sets, frames_of=PRIMARY)
    assert counted["n"] == len(sets)
    assert run_scores.scores_path(run).is_file()
    again = run_scores.scores(run, sets, frames_of=PRIMARY)
    assert counted["n"] == len(sets), "the kept scores were not reused"
    assert again == first
    # what was kept is what evaluating the model gives
    net, cfg = run_scores.checkpoint.load_model(run)
    direct = evaluate.evaluate_model(net, sets["other"], image_size=cfg["image_size"])
    assert again["sets"]["other"]["n"] == direct["n"] == len(sets["other"])
    assert again["sets"]["other"]["overall"] == {m: direct["overall"][m] for m in metrics.METRIC_NAMES}
    assert [f["index"] for f in again["frames"]] == list(range(len(sets[PRIMARY])))


def test_the_study_reads_kept_scores_into_the_same_rows(run, sets, counted):
    computed = study.score({("silog", 1, 0): run}, sets)
    assert counted["n"] == len(sets)
    read = study.score({("silog", 1, 0): run}, sets)
    assert counted["n"] == len(sets)
    assert read == computed
    assert [r["set"] for r in read[0]] == list(sets) and len(read[1]) == len(sets[PRIMARY])
    # the rows as the study's tables had them before scores were kept: evaluate, then 6 significant digits
    net, cfg = run_scores.checkpoint.load_model(run)
    r = evaluate.evaluate_model(net, sets[PRIMARY], image_size=cfg["image_size"])
    assert read[0][0] == {"depth_term": "silog", "case": 1, "seed": 0, "set": PRIMARY, "frames": r["n"],
                          **{m: f"{r['overall'][m]:.6g}" for m in metrics.METRIC_NAMES}}
    assert [f["abs_rel"] for f in read[1]] == [f"{f['abs_rel']:.6g}" for f in r["frames"]]


def test_a_retrained_checkpoint_is_scored_again(run, sets, counted):
    before = run_scores.scores(run, sets, frames_of=PRIMARY)
    state = torch.load(run, weights_only=True)
    key = next(k for k, v in state["model"].items() if k.endswith("weight") and v.is_floating_point())
    state["model"][key] = state["model"][key] * 1.5
    torch.save(state, run)
    after = run_scores.scores(run, sets, frames_of=PRIMARY)
    assert counted["n"] == 2 * len(sets)
    assert after != before
    assert json.loads(run_scores.scores_path(run).read_text())["sets"] == after["sets"]


def test_scores_of_another_set_or_other_code_are_not_reused(run, sets, smoke_root, counted, monkeypatch):
    run_scores.scores(run, sets, frames_of=PRIMARY)
    # the same name for another set: the train split under "other"
    swapped = {PRIMARY: sets[PRIMARY], "other": evaluate.open_eval_dataset(str(smoke_root), split="train")}
    got = run_scores.scores(run, swapped, frames_of=PRIMARY)
    assert counted["n"] == 2 * len(sets)
    assert got["sets"]["other"]["n"] == len(swapped["other"]) != len(sets["other"])
    # another set's frame rows kept
    run_scores.scores(run, swapped, frames_of="other")
    assert counted["n"] == 3 * len(sets)
    # changed scoring code
    monkeypatch.setattr(run_scores, "code_fingerprint", lambda: "0" * 64)
    run_scores.scores(run, swapped, frames_of="other")
    assert counted["n"] == 4 * len(sets)
    run_scores.scores(run, swapped, frames_of="other")
    assert counted["n"] == 4 * len(sets)


def test_a_set_whose_frames_changed_under_the_same_manifest_is_scored_again(run, smoke_root, tmp_path, counted):
    """A copy of the smoke dataset with one depth map replaced (and its checksum line with it): the
    same manifest and frame list, other frames, so the kept scores do not hold for it."""
    first = Path(shutil.copytree(smoke_root, tmp_path / "ds"))
    changed = Path(shutil.copytree(smoke_root, tmp_path / "ds_changed"))
    target, donor = "test/depth/000000.npy", "test/depth/000001.npy"
    shutil.copy(changed / donor, changed / target)
    digest = hashlib.sha256((changed / target).read_bytes()).hexdigest()
    sums = changed / run_scores.CHECKSUMS_NAME
    sums.write_text("".join(f"{digest}  {target}\n" if line.endswith(f"  {target}") else line + "\n"
                            for line in sums.read_text().splitlines()))
    a = {PRIMARY: evaluate.open_eval_dataset(str(first), split="test")}
    b = {PRIMARY: evaluate.open_eval_dataset(str(changed), split="test")}
    before = run_scores.scores(run, a, frames_of=PRIMARY)
    after = run_scores.scores(run, b, frames_of=PRIMARY)
    assert counted["n"] == 2
    assert after["frames"][0] != before["frames"][0] and after["frames"][1:] == before["frames"][1:]
    run_scores.scores(run, b, frames_of=PRIMARY)
    assert counted["n"] == 2


def test_a_dataset_of_another_kind_is_scored_every_time(run, sets, counted):
    resized = {"resized": evaluate.SyntheticDepthDataset(sets[PRIMARY].root, "test", image_size=32)}
    assert run_scores.set_fingerprint(resized["resized"]) is None
    run_scores.scores(run, resized)
    run_scores.scores(run, resized)
    assert counted["n"] == 2 and not run_scores.scores_path(run).exists()


def _kept(run) -> dict:
    return json.loads(run_scores.scores_path(run).read_text())


@pytest.mark.parametrize("damage, reason", [
    (lambda text, d: text[: len(text) // 2], "not plain JSON"),
    (lambda text, d: b"\xff" + text.encode(), "not plain JSON"),
    (lambda text, d: text.replace(str(d["sets"]["other"]["overall"]["rmse"]), "NaN", 1), "not plain JSON"),
    (lambda text, d: json.dumps({**d, "sets": {PRIMARY: d["sets"][PRIMARY]}}), "evaluation sets"),
    (lambda text, d: json.dumps({**d, "sets": {**d["sets"], "other": {**d["sets"]["other"], "n": "6"}}}),
     "frame count"),
    (lambda text, d: json.dumps({**d, "frames": d["frames"][:2]}), "frame rows for"),
    (lambda text, d: json.dumps({**d, "frames": [{"index": 0}] + d["frames"][1:]}), "frame rows"),
    (lambda text, d: json.dumps({**d, "format": 0}), "not a scores file"),
    (lambda text, d: json.dumps([d]), "not a scores file"),
])
def test_a_damaged_scores_file_is_named_and_scored_again(run, sets, counted, damage, reason):
    good = run_scores.scores(run, sets, frames_of=PRIMARY)
    file = run_scores.scores_path(run)
    text = file.read_text()
    bad = damage(text, json.loads(text))
    file.write_bytes(bad if isinstance(bad, bytes) else bad.encode())
    key = run_scores.score_key(run, sets, PRIMARY)
    with pytest.raises(run_scores.ScoresFileError, match=reason) as exc:
        run_scores.read_kept_scores(run, key, sets, PRIMARY)
    assert str(file) in str(exc.value)
    with pytest.warns(UserWarning, match="scoring the run again") as warned:
        again = run_scores.scores(run, sets, frames_of=PRIMARY)
    assert str(file) in str(warned[0].message)
    assert counted["n"] == 2 * len(sets) and again == good
    assert _kept(run)["key"] == key  # replaced by a good one, read from now on
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run_scores.scores(run, sets, frames_of=PRIMARY)
    assert counted["n"] == 2 * len(sets)


def test_an_oversized_scores_file_is_refused_before_it_is_read(run, sets, counted, monkeypatch):
    run_scores.scores(run, sets, frames_of=PRIMARY)
    size = run_scores.scores_path(run).stat().st_size
    monkeypatch.setattr(run_scores, "MAX_SCORES_BYTES", size - 1)
    key = run_scores.score_key(run, sets, PRIMARY)
    with pytest.raises(run_scores.ScoresFileError, match=f"over {size - 1} bytes"):
        run_scores.read_kept_scores(run, key, sets, PRIMARY)
    monkeypatch.setattr(run_scores, "MAX_SCORES_BYTES", size)
    assert run_scores.read_kept_scores(run, key, sets, PRIMARY)["key"] == key


def test_scores_of_another_checkpoint_copied_beside_this_one_are_not_trusted(run, sets, counted, tmp_path):
    other = save_untrained_checkpoint(tmp_path / "other.pt", {"image_size": 64})
    run_scores.scores(run, sets, frames_of=PRIMARY)
    folder = tmp_path / "copied"
    folder.mkdir()
    shutil.copy(other, folder / "checkpoint.pt")
    shutil.copy(run_scores.scores_path(run), folder / run_scores.SCORES_NAME)
    assert run_scores.read_kept_scores(folder / "checkpoint.pt", run_scores.score_key(folder / "checkpoint.pt", sets,
                                                                                 PRIMARY), sets, PRIMARY) is None
    run_scores.scores(folder / "checkpoint.pt", sets, frames_of=PRIMARY)
    assert counted["n"] == 2 * len(sets)


def test_frames_of_must_name_a_set(run, sets):
    with pytest.raises(ValueError, match="frames_of='nope'"):
        run_scores.scores(run, sets, frames_of="nope")


def test_runs_trained_here_are_handed_to_after_in_the_process_that_trained_them(tmp_path, monkeypatch):
    trained, handed = [], []

    def fake_checkpoint(run, *, progress=False, announce=True):
        path = run_cache.checkpoint_dir(run) / "checkpoint.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
        trained.append((run.case, run.seed))
        return path

    monkeypatch.setattr(run_cache, "ensure_checkpoint", fake_checkpoint)
    monkeypatch.setattr(run_cache, "resolve_dataset", lambda cfg, progress=False: None)
    monkeypatch.setattr(run_cache, "is_complete", lambda run: (run.case, run.seed) == (2, 0))
    smoke = config.profile("smoke")
    paths = run_cache.ensure_runs([smoke.run(1, 0), smoke.run(2, 0), smoke.run(1, 1)], workers=1, after=handed.append)
    assert trained == [(1, 0), (1, 1)]
    assert handed == [paths[0], paths[2]]


def test_the_study_scores_its_runs_through_a_picklable_hook():
    teach, smoke = config.profile("teach"), config.profile("smoke")
    hook = pickle.loads(pickle.dumps(functools.partial(study.score_run, teach)))
    assert hook.func is study.score_run and hook.args == (teach,) and hook.args[0]["image_size"] == 64
    # the runs the retrained subset reads: teach's own (silog) ablation runs, not the L1 cells nor
    # the predict model; smoke's own runs use L1, so reproduce --profile smoke scores none of them
    assert study.is_subset_run(teach, teach.run(1, 0)) and study.is_subset_run(teach, teach.run(4, 7))
    assert not study.is_subset_run(teach, teach.run(4, 0, depth_term="l1"))
    assert not study.is_subset_run(teach, teach.predict_run(4, 0))
    assert not study.is_subset_run(smoke, smoke.run(4, 0))
    assert study.is_subset_run(smoke, smoke.run(4, 0, depth_term="silog"))


# --------------------------------------------------------------------------- kept predictions


@pytest.fixture
def predicted(monkeypatch):
    """Every network pass inference.predict_depth makes for run_scores, counted: calls["n"]."""
    calls = {"n": 0}
    real = run_scores.inference.predict_depth

    def counting(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(run_scores.inference, "predict_depth", counting)
    return calls


def test_kept_predictions_score_as_the_model_itself_and_are_made_once(run, sets, predicted):
    ds = sets["other"]
    net, cfg = run_scores.checkpoint.load_model(run)
    direct = evaluate.evaluate_predictor(
        lambda im: run_scores.inference.predict_depth(net, im, cfg["image_size"], "h"), ds)
    predicted["n"] = 0
    first = run_scores.kept_predictor(run, ds, "h")
    batches = -(-len(ds) // 8)
    assert predicted["n"] == batches
    kept = evaluate.evaluate_predictor(first, ds)
    assert predicted["n"] == batches and first.misses == 0, "evaluation predicted again"
    assert kept["frames"] == direct["frames"], "kept predictions score differently from the model's own"
    again = run_scores.kept_predictor(run, ds, "h")  # a second execution: read from the run folder
    assert evaluate.evaluate_predictor(again, ds)["frames"] == direct["frames"]
    assert predicted["n"] == batches, "the kept predictions were not reused"
    depth_file, digest_file = run_scores.predictions_paths(run, run_scores.prediction_key(run, ds, "h"))
    assert depth_file.parent == run.parent / "predictions" and depth_file.is_file() and digest_file.is_file()


def test_other_flips_another_set_or_a_retrained_model_are_predicted_again(run, sets, predicted):
    ds = sets["other"]
    run_scores.kept_predictor(run, ds, "h")
    n = predicted["n"]
    run_scores.kept_predictor(run, ds, "none")
    run_scores.kept_predictor(run, sets[PRIMARY], "h")
    assert predicted["n"] == n + -(-len(ds) // 8) + -(-len(sets[PRIMARY]) // 8)
    keys = {run_scores.prediction_key(run, ds, "h"), run_scores.prediction_key(run, ds, "none"),
            run_scores.prediction_key(run, sets[PRIMARY], "h")}
    assert len(keys) == 3
    before = run_scores.prediction_key(run, ds, "h")
    state = torch.load(run, weights_only=True)
    key = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][key] = state["model"][key] + 0.01
    torch.save(state, run)
    assert run_scores.prediction_key(run, ds, "h") != before


def test_an_image_of_no_kept_frame_is_predicted_afresh(run, sets, predicted):
    ds = sets["other"]
    served = run_scores.kept_predictor(run, ds, "none")
    n = predicted["n"]
    images = torch.stack([ds[0]["image"], ds[1]["image"]])
    other = images.flip(-1)  # frames the set does not hold
    net, cfg = run_scores.checkpoint.load_model(run)
    want = run_scores.inference.predict_depth(net, other, cfg["image_size"], "none")[:, 0].numpy()
    got = served(other)
    assert served.misses == 1 and predicted["n"] == n + 2
    assert (got == want).all()
    same = run_scores.inference.predict_depth(net, images, cfg["image_size"], "none")[:, 0].numpy()
    assert (served(images) == same).all()
    assert served.misses == 1


@pytest.mark.parametrize("damage, reason", [
    (lambda p: p.write_bytes(p.read_bytes()[:-40]), "cut-short"),
    (lambda p: p.write_bytes(b"\x93NUMPY" + b"\0" * 100), "damaged"),
    (lambda p: p.write_bytes(pickle.dumps([1, 2, 3])), "not a .npy file"),
    (lambda p: p.write_bytes(p.read_bytes() + b"\0" * (64 * 2**10)), "more than"),
])
def test_a_damaged_predictions_file_is_named_and_predicted_again(run, sets, predicted, damage, reason):
    ds = sets["other"]
    run_scores.kept_predictor(run, ds, "none")
    depth_file, _ = run_scores.predictions_paths(run, run_scores.prediction_key(run, ds, "none"))
    damage(depth_file)
    n = predicted["n"]
    with pytest.warns(UserWarning) as caught:
        served = run_scores.kept_predictor(run, ds, "none")
    message = str(caught[0].message)
    assert str(depth_file) in message and reason in message and "predicting again" in message
    assert predicted["n"] > n
    assert evaluate.evaluate_predictor(served, ds)["n"] > 0 and served.misses == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # replaced: read back without a word
        run_scores.kept_predictor(run, ds, "none")


def test_kept_predictions_of_another_shape_or_with_nan_are_not_trusted(run, sets, predicted):
    ds = sets["other"]
    run_scores.kept_predictor(run, ds, "none")
    key = run_scores.prediction_key(run, ds, "none")
    depth_file, digest_file = run_scores.predictions_paths(run, key)
    depth = run_scores.bounds.read_npy(depth_file)
    run_scores._write_kept(depth_file, depth[:-1])  # one frame short
    with pytest.warns(UserWarning, match="not float32"):
        run_scores.kept_predictor(run, ds, "none")
    depth[0, 0, 0] = float("nan")
    run_scores._write_kept(depth_file, depth)
    with pytest.warns(UserWarning, match="non-finite"):
        run_scores.kept_predictor(run, ds, "none")
