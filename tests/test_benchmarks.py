"""The scripts in benchmarks/ still run, at tiny sizes (the README's figures come from full runs),
and ``train.fit`` trains the network it is given (what ``tune_teach.py --network`` relies on)."""

import json
import runpy
from pathlib import Path

import pytest
import torch

from geodepth_lite import utils
from geodepth_lite.core import model, sdf
from geodepth_lite.evaluation import evaluate
from geodepth_lite.training import checkpoint, config, train
from geodepth_lite.workbook import notebook

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


def test_bench_sdf_compare_times_both_losses_on_the_same_batch(tmp_path, capsys):
    out = tmp_path / "compare.json"
    main = load("bench_sdf.py")["main"]
    assert main(["--compare", "--batch", "3", "--size", "32", "--grid", "4", "--repeats", "1", "--data", "analytic",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    for k in ("", "_cached", "_given"):
        assert res[f"compare_ratio{k}"] == res[f"compare_ref{k}_s"] / res[f"compare_new{k}_s"] > 0
        assert len(res["compare_times"][f"ref{k}"]) == len(res["compare_times"][f"new{k}"]) == 1
    assert "per image (former)" in capsys.readouterr().out


def test_bench_render_runs(capsys):
    main = load("bench_render.py")["main"]
    assert main(["--size", "32", "--frames", "1", "--repeats", "1"]) == 0
    assert "frames/s" in capsys.readouterr().out


def test_every_evidence_row_is_a_logged_run():
    """The tables that justify the teach recipe (benchmarks/teach_recipe.json, lambda_search.json,
    view_evidence.json; notebook 04 and docs/teach_recipe.md show them) quote
    benchmarks/tuning_log.jsonl: each row's validation
    Abs Rel and RMSE are those of a logged run of its name, and its close-up score that of the run or
    of its "<run>_closeups" scoring row."""
    log = [json.loads(line) for line in (BENCHMARKS / "tuning_log.jsonl").read_text().splitlines()]
    rows = [row for name in ("teach_recipe", "lambda_search", "view_evidence") for row in notebook.evidence(name)]
    assert len(rows) > 20
    for row in rows:
        assert _logged(row, log), row
    # the check can fail: a row quoting a number its run did not give is caught
    wrong = dict(rows[0], abs_rel=rows[0]["abs_rel"] + 0.002)
    assert not _logged(wrong, log)
    several = next(row for row in rows if "runs" in row)
    assert not _logged(dict(several, rmse=several["rmse"] + 0.002), log)


def _logged(row: dict, log: list[dict]) -> bool:
    """Whether ``row``'s validation Abs Rel and RMSE (and close-up score) are those of its logged run,
    or the means over its logged "runs" (a row of several seeds)."""
    if "runs" in row:
        names = [n.strip() for n in row["runs"].split(",")]
        found = [next((r for r in log if r["name"] == n), None) for n in names]
        return None not in found and all(
            abs(sum(r[f"val_{k}"] for r in found) / len(found) - row[k]) <= 5e-4 for k in ("abs_rel", "rmse"))
    runs = [r for r in log if r["name"] == row["run"]]
    ok = any(abs(r.get("val_abs_rel", -1) - row["abs_rel"]) <= 5e-4
             and abs(r.get("val_rmse", -1) - row["rmse"]) <= 5e-4 for r in runs)
    if ok and row.get("closeup_abs_rel") not in (None, ""):
        scored = [r.get("closeup_abs_rel", -1) for r in log if r["name"] in (row["run"], row["run"] + "_closeups")]
        ok = any(abs(c - row["closeup_abs_rel"]) <= 5e-4 for c in scored)
    return ok


def test_tune_teach_parses_its_commands_with_train_the_default(tmp_path):
    """``tune_teach.py NAME ...`` is ``tune_teach.py train NAME ...`` (the README's commands); --set
    values are JSON where they parse; --network names a class in a file or a module."""
    g = load("tune_teach.py")
    args = g["parse_args"](["tiny", "--case", "4", "--set", "image_size=96", "--set", "lambdas=[1,0.1,0.1]",
                            "--set", "augment=camera", "--set", "train_frames=null", "--border"])
    assert args.command == "train" and args.name == "tiny" and args.case == 4 and args.seed == 0 and args.border
    assert args.settings == {"image_size": 96, "lambdas": [1, 0.1, 0.1], "augment": "camera", "train_frames": None}
    assert g["parse_args"](["train", "tiny"]).settings == {}
    flips = g["parse_args"](["flips", "a", "b", "--flips", "none", "hv", "--input-pad", "16"])
    assert flips.runs == ["a", "b"] and flips.flips == ["none", "hv"] and flips.input_pad == 16
    assert g["parse_args"](["closeups", "a"]).runs == ["a"]
    with pytest.raises(SystemExit):
        g["parse_args"](["flips", "a", "--flips", "sideways"])
    assert g["load_network"]("") is None
    assert g["load_network"]("geodepth_lite.core.model:DepthNet") is model.DepthNet
    variant = tmp_path / "variant.py"
    variant.write_text("from geodepth_lite.core import model\n\n\nclass Wide(model.DepthNet):\n"
                       "    \"\"\"DepthNet, renamed.\"\"\"\n")
    wide = g["load_network"](f"{variant}:Wide")
    assert issubclass(wide, model.DepthNet)
    assert g["describe_network"]("variant.py:Wide", wide) == "variant.py:Wide: DepthNet, renamed."
    for bad in (f"{variant}:Narrow", "Wide", f"{tmp_path / 'none.py'}:Wide"):
        with pytest.raises(SystemExit, match="--network"):
            g["load_network"](bad)


def test_a_logged_row_says_which_kernel_cap_it_ran_under(tmp_path, monkeypatch):
    """append_row adds {"env": {"ONEDNN_MAX_CPU_ISA": ...}} when the cap is set, nothing otherwise."""
    g = load("tune_teach.py")
    log = tmp_path / "log.jsonl"
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    g["append_row"]({"name": "a"}, log)
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    g["append_row"]({"name": "b"}, log)
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert rows == [{"name": "a"}, {"name": "b", "env": {"ONEDNN_MAX_CPU_ISA": "AVX2"}}]


def _smoke_cfg(root):
    """One epoch of the smoke profile at 32x32 (the smallest size the encoder takes)."""
    return config.make_config("smoke", 4, 0, dataset=str(root), epochs=1, batch_size=4, image_size=32)


class MarkedDepthNet(model.DepthNet):
    """DepthNet with one more parameter, so that its checkpoint tells it apart; records its arguments."""

    built: list = []

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.marker = torch.nn.Parameter(torch.zeros(1))
        MarkedDepthNet.built.append(kwargs)


def _weights(path) -> dict:
    return torch.load(path, weights_only=False)["model"]


def test_fit_trains_the_network_it_is_given(smoke_root, tmp_path, monkeypatch):
    """A class is built with DepthNet's keyword arguments from the configuration, a callable with the
    configuration; either way the checkpoint holds that network's weights, not DepthNet's."""
    monkeypatch.setattr(MarkedDepthNet, "built", [])
    cfg = _smoke_cfg(smoke_root)
    by_class = _weights(train.fit(cfg, tmp_path / "class", progress=False, network=MarkedDepthNet))
    assert MarkedDepthNet.built == [{"encoder_weights": None, "padding": "zeros", "input_pad": 0}]
    seen = []
    by_callable = _weights(train.fit(cfg, tmp_path / "callable", progress=False,
                                     network=lambda c: seen.append(c) or MarkedDepthNet(padding=c["padding"])))
    assert len(seen) == 1 and seen[0]["seed"] == 0 and seen[0]["image_size"] == 32
    for weights in (by_class, by_callable):
        assert "marker" in weights and weights.keys() - {"marker"} == model.DepthNet().state_dict().keys()
    with pytest.raises(TypeError, match="network must be"):
        train.fit(cfg, tmp_path / "bad", progress=False, network="DepthNet")


def test_fit_without_a_network_trains_depthnet_bit_for_bit(smoke_root, tmp_path):
    """network=None is the default path, and DepthNet passed as the class gives the same weights too:
    the network is built with the same arguments at the same point of the seeded random draws."""
    cfg = _smoke_cfg(smoke_root)
    default = _weights(train.fit(cfg, tmp_path / "default", progress=False))
    for name, network in (("none", None), ("class", model.DepthNet)):
        other = _weights(train.fit(cfg, tmp_path / name, progress=False, network=network))
        assert other.keys() == default.keys()
        for k, v in default.items():
            assert torch.equal(v, other[k]), (name, k)


def test_tune_teach_trains_a_network_variant_and_scores_it_again(smoke_root, tmp_path, monkeypatch):
    """``train NAME --network FILE.py:NAME`` trains the variant and logs its validation row; its run
    loads into that variant only (DepthNet refuses its weights)."""
    g = load("tune_teach.py")
    variant = tmp_path / "variant.py"
    variant.write_text("import torch\n\nfrom geodepth_lite.core import model\n\n\nclass Marked(model.DepthNet):\n"
                       "    \"\"\"DepthNet with a marker parameter.\"\"\"\n\n"
                       "    def __init__(self, **kwargs):\n        super().__init__(**kwargs)\n"
                       "        self.marker = torch.nn.Parameter(torch.zeros(1))\n")
    log = tmp_path / "log.jsonl"
    assert g["main"](["tiny", "--case", "4", "--set", f"dataset={smoke_root}", "--set", "image_size=32",
                      "--set", "epochs=1", "--set", "batch_size=4", "--network", f"{variant}:Marked",
                      "--log", str(log)]) == 0
    (row,) = [json.loads(line) for line in log.read_text().splitlines()]
    assert row["name"] == "tiny" and row["network"] == f"{variant}:Marked: DepthNet with a marker parameter."
    assert row["settings"]["image_size"] == 32 and 0 < row["val_abs_rel"] and 0 < row["val_rmse"]
    ckpt = utils.runs_dir() / "tune" / "tiny" / checkpoint.CHECKPOINT_NAME
    assert "marker" in checkpoint.read_checkpoint(ckpt)["model"]
    net, cfg, name = g["load_run"]("tiny", g["load_network"](f"{variant}:Marked"))
    assert type(net).__name__ == "Marked" and name == "tiny" and cfg["image_size"] == 32
    with pytest.raises(ValueError, match="does not fit this network"):
        g["load_run"]("tiny")


def test_tune_teach_closeups_records_closeups_and_test_border(tmp_path, monkeypatch, smoke_root):
    """``closeups`` scores a tune run on heldout_closeup and the test split and logs one row; a run
    trained before input_pad was a setting is scored with its mirror padding; a missing run is named."""
    from conftest import save_untrained_checkpoint

    monkeypatch.setitem(config.PROFILES, "teach", dict(config.PROFILES["teach"],
                                                         closeup_overrides=config.PROFILES["smoke"]["closeup_overrides"]))
    g = load("tune_teach.py")
    run = utils.runs_dir() / "tune" / "tiny"
    run.mkdir(parents=True)
    save_untrained_checkpoint(run / "checkpoint.pt", {"image_size": 32, "case": 4, "seed": 0,
                                                      "dataset": str(smoke_root)})
    log = tmp_path / "log.jsonl"
    assert g["main"](["closeups", "tiny", "--log", str(log)]) == 0
    assert g["main"](["closeups", "tiny", "--input-pad", "16", "--log", str(log)]) == 0
    plain, padded = (json.loads(line) for line in log.read_text().splitlines())
    assert plain["name"] == "tiny_closeups" and "input_pad" not in plain["settings"]
    assert padded["settings"]["input_pad"] == 16
    for row in (plain, padded):
        assert set(row["test_border"]) == {"top", "bottom", "left", "right"}
        assert row["test_border_worst"] == max(row["test_border"].values())
        assert 0 < row["closeup_abs_rel"] and 0 < row["closeup_shading_prior_abs_rel"] < 1
    assert plain["closeup_shading_prior_abs_rel"] == padded["closeup_shading_prior_abs_rel"]
    assert plain["closeup_border_worst"] != padded["closeup_border_worst"]  # the padded network sees more
    with pytest.raises(SystemExit, match="no checkpoint at .*missing"):
        g["main"](["closeups", "missing", "--log", str(log)])


def test_tune_teach_flips_logs_one_row_per_flips_setting(tmp_path, monkeypatch, smoke_root):
    """``flips`` scores a tune run or a checkpoint path with each test-time flips setting: one row each,
    validation fields beside the recorded close-up and test fields; "none" is the network's own single
    pass, so its validation Abs Rel is score_validation's; a missing run is named."""
    from conftest import save_untrained_checkpoint

    monkeypatch.setitem(config.PROFILES, "teach", dict(config.PROFILES["teach"],
                                                         closeup_overrides=config.PROFILES["smoke"]["closeup_overrides"]))
    g = load("tune_teach.py")
    run = utils.runs_dir() / "tune" / "tiny"
    run.mkdir(parents=True)
    save_untrained_checkpoint(run / "checkpoint.pt", {"image_size": 32, "case": 4, "seed": 0,
                                                      "dataset": str(smoke_root)})
    log = tmp_path / "log.jsonl"
    assert g["main"](["flips", "tiny", str(run / "checkpoint.pt"), "--flips", "none", "hv", "--log", str(log)]) == 0
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["name"] for r in rows] == ["tiny_flips_none", "tiny_flips_hv"] * 2
    assert rows[0] | {"minutes": 0} == rows[2] | {"minutes": 0}  # by name or by path: the same run
    net, cfg = checkpoint.load_model(run / "checkpoint.pt")
    torch.set_num_threads(1)
    plain = g["score_validation"](net, cfg)
    assert rows[0]["val_abs_rel"] == plain["val_abs_rel"] and rows[0]["val_rmse"] == plain["val_rmse"]
    assert rows[1]["val_abs_rel"] != rows[0]["val_abs_rel"]
    n_test = len(evaluate.open_eval_dataset(str(smoke_root), split="test"))
    for row in rows:
        assert row["test_border_worst"] == max(row["test_border"].values()) and 0 < row["closeup_abs_rel"]
        assert row["test_frames"] == n_test
    assert g["main"](["flips", "tiny", "--flips", "none", "--tag", "t2", "--log", str(log)]) == 0
    tagged = json.loads(log.read_text().splitlines()[-1])
    same = {"name": 0, "minutes": 0}
    assert tagged["name"] == "tiny_flips_none_t2" and tagged | same == rows[0] | same
    with pytest.raises(SystemExit, match="no checkpoint at .*missing"):
        g["main"](["flips", "missing", "--log", str(log)])


def test_bench_sdf_search_compares_the_device_search_with_cktree(tmp_path, capsys):
    out = tmp_path / "search.json"
    main = load("bench_sdf.py")["main"]
    assert main(["--search", "--data", "analytic", "--batch", "3", "--size", "32", "--grid", "5", "--repeats", "1",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["search_queries"] == 3 * 125 and res["search_agree"] == res["search_queries"]
    assert res["search_device_s"] > 0 and res["search_kdtree_s"] > 0 and res["search_brute_mm_s"] > 0
    assert "agreement with cKDTree" in capsys.readouterr().out


def test_bench_many_runs_and_reports_the_four_ways(tmp_path, capsys):
    out = tmp_path / "many.json"
    main = load("bench_many.py")["main"]
    assert main(["--size", "32", "--batch", "2", "--runs", "2", "--steps", "1", "--repeats", "1",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert all(res[k] > 0 for k in ("one_step_s", "sequential_s", "stacked_s", "processes_s"))
    said = capsys.readouterr().out
    assert "one process, stacked (vmap" in said and "2 processes (1 thread each)" in said


def compare_table_rows(text: str) -> list:
    """The (former s, batched s, ratio) of each row of the batched-vs-per-image SDF table in ``text``."""
    import re

    rows = re.findall(r"^\| [^|]+ \| ([\d.]+) s \| ([\d.]+) s \| ([\d.]+)x \|$", text, flags=re.M)
    return [tuple(float(x) for x in r) for r in rows]


def stated_compare_figures_hold(text: str, rec: dict) -> bool:
    want = [(round(rec[f"compare_ref{k}_s"], 2), round(rec[f"compare_new{k}_s"], 2),
             round(rec[f"compare_ratio{k}"], 2)) for k in ("", "_cached", "_given")]
    return compare_table_rows(text) == want


def test_the_docs_state_the_recorded_sdf_loss_comparison():
    rec = json.loads((BENCHMARKS / "sdf_loss_compare_cpu.json").read_text())
    text = (BENCHMARKS.parent / "docs" / "network_and_losses.md").read_text()
    assert rec["batch"] == 20 and rec["size"] == 320 and rec["grid"] == 32 and rec["repeats"] >= 3
    for k in ("", "_cached", "_given"):  # each median is the median of its recorded repeats
        for side in ("ref", "new"):
            assert rec[f"compare_{side}{k}_s"] == sorted(rec["compare_times"][f"{side}{k}"])[rec["repeats"] // 2]
    assert stated_compare_figures_hold(text, rec)
    assert not stated_compare_figures_hold(text.replace("| 1.99x |", "| 2.99x |"), rec)  # the check can fail


def test_bench_step_precision_times_the_variants_side_by_side(tmp_path, capsys):
    """At a tiny size: float32 and channels_last on the same batch and weights, each repetition's
    ratio over float32's in the same repetition, and the channels_last network really in that format."""
    out = tmp_path / "levers.json"
    g = load("bench_step_precision.py")
    assert g["main"](["--profile", "smoke", "--case", "1", "--frames", "4", "--steps", "2", "--repeats", "2",
                      "--variants", "channels_last", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert list(rec["variants"]) == ["fp32", "channels_last"] and rec["threads"] == 1
    fp32, cl = rec["variants"]["fp32"], rec["variants"]["channels_last"]
    assert fp32["ratio"] == 1.0 and len(cl["repetitions_s"]) == 2
    assert cl["paired_ratios"] == [a / b for a, b in zip(cl["repetitions_s"], fp32["repetitions_s"])]
    assert "| channels_last |" in capsys.readouterr().out
    cfg = config.make_config("smoke", 1, 0)
    net = train.build_network(cfg)
    batch = {"image": torch.zeros(2, 3, 32, 32)}
    s = g["Stepper"](net, cfg, batch, [], False, True)
    assert s.batch["image"].is_contiguous(memory_format=torch.channels_last)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in s.net.parameters() if p.dim() == 4)
    assert not all(p.is_contiguous(memory_format=torch.channels_last) for p in net.parameters() if p.dim() == 4)


def finetune_table_problems(text: str, record: dict) -> list[str]:
    """Each row of docs/teach_recipe.md's fine-tuning table against benchmarks/real_finetune.json."""
    problems = []
    rows = [("trained from scratch (kept)", None, record["reference"])] + [
        (f"fine-tuned, candidate {n}", c["epochs"], c) for n, c in record["candidates"].items()]
    for label, epochs, r in rows:
        want = (f"| {label} | {epochs or 8}, {r['train_s']} | {r['val_abs_rel']:.4f} | {r['close_blobs']} of "
                f"{r['close_frames']}, {r['close_median_s']:.3f}, {r['close_median_r']:.3f} | {r['all_blobs']} | "
                f"{r['run']} |")
        if want not in text:
            problems.append(want)
    kept = record["decision"] == "reference (trained from scratch)"
    if not kept or any(c["qualifies"] for c in record["candidates"].values()):
        problems.append(f"the record decides {record['decision']!r}; the page keeps the model trained from scratch")
    return problems


def test_the_fine_tuning_table_states_its_record():
    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "teach_recipe.md").read_text()
    record = json.loads((BENCHMARKS / "real_finetune.json").read_text())
    assert finetune_table_problems(text, record) == []
    planted = json.loads(json.dumps(record))
    planted["candidates"]["B"]["val_abs_rel"] = 0.1094  # a candidate within the plan's bound
    assert finetune_table_problems(text, planted) == ["| fine-tuned, candidate B | 3, 470.3 | 0.1094 | 0 of 7, "
                                                      "0.001, 0.852 | 0 | case4_seed0-0cc3c494 |"]
    planted["decision"] = "B"
    assert len(finetune_table_problems(text, planted)) == 2
