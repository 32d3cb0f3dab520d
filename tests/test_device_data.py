"""A CUDA run's data kept on its device, the model chosen on the validation split, channels_last.

The device path is checked on CPU tensors (``fit(device_data=True)``): it must give the run the
loader gives (same batches, order, random draws), so on CUDA it changes the time, not the model.
"""

import math

import pytest
import torch

from geodepth_lite.core.model import DepthNet
from geodepth_lite.data import datasets
from geodepth_lite.training import checkpoint, config, inference, train, train_many


def _cfg(root, **kw):
    kw.setdefault("epochs", 2)
    kw.setdefault("batch_size", 4)
    kw.setdefault("image_size", 32)
    return config.make_config("smoke", 4, 0, dataset=str(root), **kw)


def _load(path):
    return torch.load(path, weights_only=False, map_location="cpu")


def _rng_equal(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_rng_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_rng_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return torch.equal(a, b)
    return bool(a == b) if not hasattr(a, "shape") else bool((a == b).all())


def test_data_on_the_device_trains_the_same_run_as_the_loader(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, train_frames=10)  # 10 frames, batch 4: a last batch of 2 as well
    runs = {}
    for on in (False, True):
        datasets.MEMORY_CACHE.clear()
        runs[on] = _load(train.fit(cfg, tmp_path / f"d{int(on)}", progress=False, device="cpu", device_data=on))
    a, b = runs[False], runs[True]
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    assert _rng_equal(a["rng"], b["rng"])  # the loader generator's draws included: resume sees the same state
    keys = [k for k in a["history"][0] if k.startswith(("train_", "val_")) and "per_s" not in k]
    assert [[r[k] for k in keys] for r in a["history"]] == [[r[k] for k in keys] for r in b["history"]]
    sessions = checkpoint.read_log_file(tmp_path / "d1")["provenance"]
    assert sessions[-1]["device_data"] is True
    assert checkpoint.read_log_file(tmp_path / "d0")["provenance"][-1]["device_data"] is False


def test_a_device_split_batch_is_the_loaders_batch(smoke_root):
    ds = datasets.load_split(smoke_root, "train", 32, cache=False)
    split = datasets.DeviceSplit(ds, "cpu", threads=3, chunk=5)  # chunks of 5: a partial last chunk
    idx = [6, 0, 3, 10]
    want = inference.collate([ds[i] for i in idx])
    got = split.batch(idx)
    assert list(got) == list(want)
    for k, v in want.items():
        assert torch.equal(got[k], v) if isinstance(v, torch.Tensor) else got[k] == v, k
    assert len(split) == len(ds) and split.nbytes(2, 32) == 2 * 5 * 32 * 32 * 4
    # a wrong gather (the frames of the next indices) is caught by the same comparison
    off = split.batch([i + 1 for i in idx])
    assert not torch.equal(off["image"], want["image"])


def test_device_batches_follow_the_sampler_and_draw_like_a_loader(smoke_root):
    ds = datasets.load_split(smoke_root, "train", 32, cache=False)
    split = datasets.DeviceSplit(ds, "cpu")
    sampler = torch.utils.data.DistributedSampler(ds, num_replicas=1, rank=0, shuffle=True, seed=3)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    loader = torch.utils.data.DataLoader(ds, batch_size=5, sampler=sampler, collate_fn=inference.collate,
                                         generator=g1)
    mine = datasets.DeviceBatches(split, sampler, 5, g2)
    assert len(mine) == len(loader)
    for x, y in zip(loader, mine, strict=True):
        assert x["index"].tolist() == y["index"].tolist()
        assert torch.equal(x["depth"], y["depth"])
    assert torch.equal(g1.get_state(), g2.get_state())


class _Run:
    """The parts of a Trainer that ``keep_best`` reads: a history and a checkpoint just written."""

    def __init__(self, folder):
        self.run_dir, self.ckpt_path, self.history = folder, folder / "checkpoint.pt", []

    def epoch(self, abs_rel):
        self.history.append({"val_abs_rel": abs_rel})
        self.ckpt_path.write_bytes(f"epoch {len(self.history)}".encode())
        train.Trainer.keep_best(self)


def test_best_pt_is_the_epoch_of_least_validation_abs_rel(tmp_path):
    run = _Run(tmp_path)
    best = tmp_path / train.BEST_NAME
    for score, want in ((0.30, "epoch 1"), (0.20, "epoch 2"), (0.25, "epoch 2"), (0.20, "epoch 2"),
                        (math.nan, "epoch 2"), (0.19, "epoch 6")):
        run.epoch(score)
        assert best.read_bytes().decode() == want, (score, run.history)


def test_keep_best_writes_the_checkpoint_of_the_best_epoch(smoke_root, tmp_path):
    train.fit(_cfg(smoke_root, epochs=3), tmp_path / "r", progress=False, device="cpu", keep_best=True)
    rows = checkpoint.read_log(tmp_path / "r")
    scores = [r["val_abs_rel"] for r in rows]
    best = _load(tmp_path / "r" / train.BEST_NAME)
    assert best["epoch"] == 1 + scores.index(min(scores))
    assert best["history"] == _load(tmp_path / "r" / "checkpoint.pt")["history"][:best["epoch"]]
    model, _ = checkpoint.load_model(tmp_path / "r" / train.BEST_NAME, "cpu")  # a checkpoint like any other
    assert isinstance(model, DepthNet)


def test_channels_last_is_the_same_network_in_another_layout():
    torch.manual_seed(0)
    net = DepthNet().train()
    x = torch.rand(2, 3, 64, 64)
    a = net(x)
    a.mean().backward()
    ga = {n: p.grad.clone() for n, p in net.named_parameters()}
    net.zero_grad()
    net = net.to(memory_format=torch.channels_last)
    b = net(x.contiguous(memory_format=torch.channels_last))
    b.mean().backward()
    assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    worst = max(float((ga[n] - p.grad).abs().max() / (ga[n].abs().max() + 1e-12)) for n, p in net.named_parameters())
    assert worst < 1e-3


@pytest.mark.parametrize("flags", [[], ["--keep-best"], ["--channels-last"], ["--keep-best", "--channels-last"]])
def test_train_many_passes_the_run_options_to_each_run(flags):
    import argparse

    parser = argparse.ArgumentParser()
    train_many.add_arguments_train_many(parser)
    argv = train_many.settings_argv(parser.parse_args(["--out", "x", *flags]))
    assert [f for f in argv if f in ("--keep-best", "--channels-last")] == flags
