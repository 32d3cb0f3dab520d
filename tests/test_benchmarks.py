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
