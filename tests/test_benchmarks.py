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


def test_symmetric_downsampling_samples_both_edges_alike():
    """The experiment's encoder has DepthNet's parameters; with left-right symmetric kernels it
    maps a mirrored image to mirrored features (known answer), which the package's stride-2
    encoder does not: its windows sit at columns 0, 2, ..., W-2."""
    import torch

    from geodepth_lite import model

    def mirror_symmetric(net):
        for m in net.modules():
            if isinstance(m, torch.nn.Conv2d):
                m.weight.data = (m.weight.data + m.weight.data.flip(-1)) / 2
        return net.eval()

    torch.manual_seed(0)
    sym = mirror_symmetric(load("exp_symmetric_downsampling.py")["SymmetricDepthNet"]())
    base = mirror_symmetric(model.DepthNet())
    assert sum(p.numel() for p in sym.parameters()) == sum(p.numel() for p in base.parameters())
    x = torch.rand(1, 3, 64, 64, dtype=torch.float64)
    sym, base = sym.double(), base.double()
    with torch.no_grad():
        for net, equivariant in ((sym, True), (base, False)):
            f, f_mirror = net.encode(x)[-1], net.encode(x.flip(-1))[-1]
            gap = float((f_mirror - f.flip(-1)).abs().max()) / float(f.abs().max())
            assert (gap < 1e-9) if equivariant else (gap > 1e-3), gap


def test_partial_padding_gives_a_constant_image_the_same_response_at_the_border():
    """Known answer: a 3x3 all-ones kernel on a constant image c sums 9c under every window once the
    border outputs are rescaled (zero padding gives 4c at the corners, 6c on the edges). The
    network variant keeps DepthNet's parameters and rescales every zero-padded convolution."""
    import torch

    from geodepth_lite import model

    g = load("exp_partial_padding.py")
    conv = g["PartialConv2d"](1, 1, 3, padding=1, bias=False)
    plain = torch.nn.Conv2d(1, 1, 3, padding=1, bias=False)
    conv.weight.data.fill_(1.0)
    plain.weight.data.fill_(1.0)
    x = torch.full((1, 1, 6, 5), 2.0)
    with torch.no_grad():
        assert torch.equal(conv(x), torch.full((1, 1, 6, 5), 18.0))
        edge = plain(x)[0, 0]
        assert edge[0, 0] == 8.0 and edge[0, 2] == 12.0 and edge[2, 2] == 18.0
        # stride 2 with the 7x7 stem's padding: windows over the top-left corner see 16 of 49 inputs
        stem = g["PartialConv2d"](1, 1, 7, stride=2, padding=3, bias=True)
        stem.weight.data.fill_(1.0)
        stem.bias.data.fill_(0.5)
        assert torch.allclose(stem(torch.ones(1, 1, 8, 8)), torch.full((1, 1, 4, 4), 49.5))
    net, base = g["PartialPaddingDepthNet"](), model.DepthNet()
    assert sum(p.numel() for p in net.parameters()) == sum(p.numel() for p in base.parameters())
    padded = [m for m in base.modules() if isinstance(m, torch.nn.Conv2d) and any(p > 0 for p in m.padding)]
    assert sum(type(m).__name__ == "PartialConv2d" for m in net.modules()) == len(padded) > 20


def test_coordinate_channels_and_a_coordconv_net_that_starts_as_depthnet():
    """Known answer: pixel centres of a 2 x 4 image at x = -0.75, -0.25, 0.25, 0.75 and y = -0.5, 0.5.
    The experiment's network has DepthNet's parameters plus two zero-initialised input channels, so
    with DepthNet's weights copied in it predicts exactly what DepthNet predicts."""
    import torch

    from geodepth_lite import model

    g = load("exp_coord_channels.py")
    xy = g["coordinate_channels"](3, 2, 4, torch.zeros(1, dtype=torch.float64))
    assert xy.shape == (3, 2, 2, 4)
    assert torch.equal(xy[0, 0, 1], torch.tensor([-0.75, -0.25, 0.25, 0.75], dtype=torch.float64))
    assert torch.equal(xy[2, 1, :, 0], torch.tensor([-0.5, 0.5], dtype=torch.float64))
    torch.manual_seed(0)
    base = model.DepthNet().double().eval()
    torch.manual_seed(1)
    coord = g["CoordDepthNet"]().double().eval()
    state = base.state_dict()
    w = torch.zeros(64, 5, 7, 7, dtype=torch.float64)
    w[:, :3] = state["encoder.conv1.weight"]
    coord.load_state_dict(dict(state, **{"encoder.conv1.weight": w}))
    x = torch.rand(2, 3, 64, 64, dtype=torch.float64)
    with torch.no_grad():
        assert torch.allclose(coord(x), base(x), rtol=1e-12, atol=0)
        coord.encoder.conv1.weight[:, 3:] = 0.1  # once the coordinates count, the output changes
        assert not torch.allclose(coord(x), base(x), rtol=1e-6, atol=0)


def test_border_context_windows_put_the_crops_edge_where_asked():
    """A 96 px crop of a 128 px frame, 32 px in from each side: its band (outer 10%, 10 px) covers
    frame columns 32-41 for the left side; median scaling makes a prediction of 2 x gt error-free."""
    import numpy as np

    g = load("exp_border_context.py")
    win = g["crop_windows"](128, 128, 96, 32)
    assert win["left"] == (slice(16, 112), slice(32, 128))
    assert win["right"] == (slice(16, 112), slice(0, 96))
    assert win["top"] == (slice(32, 128), slice(16, 112)) and win["bottom"] == (slice(0, 96), slice(16, 112))
    cols = np.arange(128)[win["left"][1]][g["regions"](96, "left")["band"][1]]
    assert cols[0] == 32 and cols[-1] == 41
    gt = np.random.default_rng(0).uniform(1, 5, (8, 8))
    assert np.allclose(g["abs_log_error"](2 * gt, gt, np.ones((8, 8), bool)), 0)


def test_every_evidence_row_is_a_logged_run():
    """The tables that justify the teach recipe (config.TEACH_EVIDENCE, LAMBDA_SEARCH, VIEW_EVIDENCE;
    notebook 04 and the README show them) quote benchmarks/tuning_log.jsonl: each row's validation
    Abs Rel and RMSE are those of a logged run of its name, and its close-up score that of the run or
    of its "<run>_closeups" scoring row."""
    from geodepth_lite import config

    log = [json.loads(line) for line in (BENCHMARKS / "tuning_log.jsonl").read_text().splitlines()]
    rows = [*config.TEACH_EVIDENCE, *config.LAMBDA_SEARCH, *config.VIEW_EVIDENCE]
    assert len(rows) > 20
    for row in rows:
        runs = [r for r in log if r["name"] == row["run"]]
        assert any(abs(r.get("val_abs_rel", -1) - row["abs_rel"]) <= 5e-4
                   and abs(r.get("val_rmse", -1) - row["rmse"]) <= 5e-4 for r in runs), row
        if row.get("closeup_abs_rel") not in (None, ""):
            scored = [r.get("closeup_abs_rel", -1) for r in log if r["name"] in (row["run"], row["run"] + "_closeups")]
            assert any(abs(c - row["closeup_abs_rel"]) <= 5e-4 for c in scored), row


def test_padded_training_experiment_builds_the_packages_mirrored_network():
    """The experiment's network is DepthNet with input_pad forced on, whatever the caller passes:
    the same parameters and, with the same weights, the same depth as DepthNet(input_pad=16)."""
    import torch

    from geodepth_lite import model

    g = load("exp_padded_training.py")
    torch.manual_seed(0)
    net = g["padded_network"](16)(padding="zeros").eval()
    ref = model.DepthNet(input_pad=16).eval()
    ref.load_state_dict(net.state_dict())
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert net.input_pad == 16 and torch.equal(net(x), ref(x))
        plain = model.DepthNet().eval()
        plain.load_state_dict(net.state_dict())
        assert not torch.allclose(net(x), plain(x))  # the mirrored border changes the depth


def test_a_logged_row_says_which_kernel_cap_it_ran_under(tmp_path, monkeypatch):
    """append_row adds {"env": {"ONEDNN_MAX_CPU_ISA": ...}} when the cap is set, nothing otherwise."""
    g = load("network_experiment.py")
    log = tmp_path / "log.jsonl"
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    g["append_row"]({"name": "a"}, log)
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    g["append_row"]({"name": "b"}, log)
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert rows == [{"name": "a"}, {"name": "b", "env": {"ONEDNN_MAX_CPU_ISA": "AVX2"}}]


def test_score_run_records_closeups_and_test_border(tmp_path, monkeypatch, smoke_root):
    """score_run.py scores a tune run on heldout_closeup and the test split and logs one row; a run
    of exp_padded_training.py is scored with its mirror padding; a missing run is named."""
    import pytest
    from conftest import save_untrained_checkpoint

    from geodepth_lite import config, utils

    monkeypatch.setitem(config.PROFILES, "teach", dict(config.PROFILES["teach"],
                                                         closeup_overrides=config.PROFILES["smoke"]["closeup_overrides"]))
    g = load("score_run.py")
    run = utils.runs_dir() / "tune" / "tiny"
    run.mkdir(parents=True)
    save_untrained_checkpoint(run / "checkpoint.pt", {"image_size": 32, "case": 4, "seed": 0,
                                                      "dataset": str(smoke_root)})
    log = tmp_path / "log.jsonl"
    assert g["main"](["tiny", "--log", str(log)]) == 0
    assert g["main"](["tiny", "--input-pad", "16", "--log", str(log)]) == 0
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
        g["main"](["missing", "--log", str(log)])


def test_score_flips_logs_one_row_per_flips_setting(tmp_path, monkeypatch, smoke_root):
    """score_flips.py scores a tune run or a checkpoint path with each test-time flips setting: one row
    each, validation fields beside the recorded close-up and test fields; "none" is the network's own
    single pass, so its validation Abs Rel is score_validation's; a missing run is named."""
    import pytest
    import torch
    from conftest import save_untrained_checkpoint

    from geodepth_lite import checkpoint, config, utils

    monkeypatch.setitem(config.PROFILES, "teach", dict(config.PROFILES["teach"],
                                                         closeup_overrides=config.PROFILES["smoke"]["closeup_overrides"]))
    g = load("score_flips.py")
    run = utils.runs_dir() / "tune" / "tiny"
    run.mkdir(parents=True)
    save_untrained_checkpoint(run / "checkpoint.pt", {"image_size": 32, "case": 4, "seed": 0,
                                                      "dataset": str(smoke_root)})
    log = tmp_path / "log.jsonl"
    assert g["main"](["tiny", str(run / "checkpoint.pt"), "--flips", "none", "hv", "--log", str(log)]) == 0
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["name"] for r in rows] == ["tiny_flips_none", "tiny_flips_hv"] * 2
    assert rows[0] | {"minutes": 0} == rows[2] | {"minutes": 0}  # by name or by path: the same run
    net, cfg = checkpoint.load_model(run / "checkpoint.pt")
    torch.set_num_threads(1)
    plain = load("network_experiment.py")["score_validation"](net, cfg)
    assert rows[0]["val_abs_rel"] == plain["val_abs_rel"] and rows[0]["val_rmse"] == plain["val_rmse"]
    assert rows[1]["val_abs_rel"] != rows[0]["val_abs_rel"]
    from geodepth_lite import evaluate
    n_test = len(evaluate.open_eval_dataset(str(smoke_root), split="test"))
    for row in rows:
        assert row["test_border_worst"] == max(row["test_border"].values()) and 0 < row["closeup_abs_rel"]
        assert row["test_frames"] == n_test
    assert g["main"](["tiny", "--flips", "none", "--tag", "t2", "--log", str(log)]) == 0
    tagged = json.loads(log.read_text().splitlines()[-1])
    same = {"name": 0, "minutes": 0}
    assert tagged["name"] == "tiny_flips_none_t2" and tagged | same == rows[0] | same
    with pytest.raises(SystemExit, match="no checkpoint at .*missing"):
        g["main"](["missing", "--log", str(log)])


def test_border_anatomy_known_answers_and_a_logged_row(tmp_path, smoke_root):
    """A prediction with twice the true log-depth contrast: its median-scaled log error is exactly
    log gt - median log gt, so each region's |e| equals its spread of true log depth, each band whose
    depths all lie beyond the median is wrong as a whole (coherence 1), and a per-frame contrast fit
    leaves nothing. The script then logs one row for a checkpoint, every test frame counted."""
    import numpy as np
    import pytest
    from conftest import save_untrained_checkpoint

    from geodepth_lite import evaluate

    g = load("exp_border_anatomy.py")
    H = W = 40
    yy, xx = np.mgrid[:H, :W]
    # flat over the centre (the middle half), farther toward the border, as in a wall-facing view: every
    # band pixel lies beyond the frame's median depth
    gt = np.exp(0.05 * np.maximum(0.0, np.maximum(abs(yy - 19.5), abs(xx - 19.5)) - 10.0))
    s = g["frame_stats"](gt**2, gt, gt)
    m = np.median(np.log(gt))
    for region, (rows, cols) in evaluate.band_regions(H, W).items():
        assert s[region]["abs"] == pytest.approx(np.abs(np.log(gt[rows, cols]) - m).mean())
        assert s[region]["spread"] == pytest.approx(s[region]["abs"])
        assert s[region]["contrast"] == pytest.approx(0.0, abs=1e-9) and s[region]["floor"] == 0.0
    row = g["summarize"]([s, s])
    assert row["ratio"] == pytest.approx(row["spread"]) and row["frames"] == 2 and row["floor_share"] == 0.0
    assert row["coherence"] == pytest.approx(1.0)  # the bands' depths all lie beyond the median
    # a prediction right up to scale has no error, whatever the depth range
    assert g["frame_stats"](3.0 * gt, gt, gt)["left"]["abs"] == pytest.approx(0.0, abs=1e-9)

    ckpt = save_untrained_checkpoint(tmp_path / "checkpoint.pt", {"image_size": 32, "case": 4, "seed": 0,
                                                                  "dataset": str(smoke_root)})
    log = tmp_path / "log.jsonl"
    assert g["main"]([str(ckpt), "--flips", "none", "--name", "tiny", "--log", str(log)]) == 0
    (logged,) = [json.loads(line) for line in log.read_text().splitlines()]
    n = len(evaluate.open_eval_dataset(str(smoke_root), split="test"))
    assert logged["name"] == "tiny_border_anatomy_test" and logged["all"]["frames"] == n
    assert sum(r["frames"] for r in logged["by_view"].values()) == n
