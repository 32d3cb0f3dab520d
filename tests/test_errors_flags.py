"""One line, exit status 2, for flags and files that used to end in a traceback or pass unchecked:
``--device bogus``, a student release with git missing from PATH, a conversion rerun after a full
disk, and ``verify`` on a dataset whose ``frames.jsonl`` names files outside it.
"""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error

from geodepth_lite import cli, utils
from geodepth_lite.data import integrity
from geodepth_lite.training import checkpoint

# --------------------------------------------------------------------------- --device


def _device_argv(command: str, device: str, tmp: Path, ckpt: Path, data: Path) -> list[str]:
    return {
        "predict": ["predict", "--checkpoint", str(ckpt), "--input", str(data / "test" / "rgb"),
                    "--out", str(tmp / "out"), "--no-progress"],
        "evaluate": ["evaluate", "--checkpoint", str(ckpt), "--dataset", str(data), "--out", str(tmp / "out"),
                     "--no-progress", "--no-verify"],
        "train": ["train", "--profile", "smoke", "--dataset", str(data), "--run-dir", str(tmp / "out"),
                  "--no-progress", "--no-verify", "--epochs", "1", "--image-size", "32"],
        "gpu-check": ["gpu-check", "--out", str(tmp / "out"), "--tiny"],
    }[command] + ["--device", device]


@pytest.mark.parametrize("command", ["predict", "evaluate", "train", "gpu-check"])
@pytest.mark.parametrize("device", ["bogus", "cuda\n", "meta"])
def test_a_bad_device_is_one_line_before_any_work(smoke_root, untrained_checkpoint, tmp_path, capsys, command, device):
    assert cli.main(_device_argv(command, device, tmp_path, untrained_checkpoint, smoke_root)) == 2
    one_line_error(capsys, "--device", repr(device), "cpu, cuda or cuda:N")
    assert not (tmp_path / "out").exists()


def test_the_devices_a_run_names_are_parsed():
    assert utils.parse_device("cpu") == torch.device("cpu")
    assert utils.parse_device("cuda:1") == torch.device("cuda", 1)  # parsed only: whether it exists is CUDA's to say
    assert utils.parse_device(torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(ValueError, match="--gpu 'cuda:x' is not a device"):
        utils.parse_device("cuda:x", flag="--gpu")


# --------------------------------------------------------------------------- exercises without git


def test_no_git_on_path_refuses_a_release_inside_a_checkout(tmp_path, monkeypatch, capsys):
    """Without git the tracked-file check cannot run: a folder inside anything holding .git is refused."""
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    docs = repo / "docs"
    docs.mkdir()
    (docs / "guide.md").write_text("tracked by the project\n")
    monkeypatch.setenv("PATH", str(tmp_path / "empty-bin"))  # no git (nor anything else) on PATH
    assert cli.main(["exercises", "--out", str(docs), "--force"]) == 2
    one_line_error(capsys, str(docs), f"lies in the checkout {repo}", "git could not list")
    assert sorted(p.name for p in docs.iterdir()) == ["guide.md"]
    assert (docs / "guide.md").read_text() == "tracked by the project\n"
    # the same folder outside any checkout passes the check (here: refused only for not being empty)
    (repo / ".git").rmdir()
    assert cli.main(["exercises", "--out", str(docs)]) == 2
    one_line_error(capsys, str(docs), "not empty")


# --------------------------------------------------------------------------- convert-checkpoint rerun


def test_a_conversion_that_failed_on_a_full_disk_runs_again(tmp_path, monkeypatch, capsys):
    path = tmp_path / "checkpoint.pt"
    torch.save({"model": {"w": torch.arange(4.0)}, "cfg": {"image_size": 32}, "epoch": 1,
                "rng": {"numpy": ("MT19937", np.arange(624, dtype=np.uint32), 3, 0, 0.0)}}, path)
    original = path.read_bytes()
    real = utils.write_bytes_atomic

    def full_disk(target, data):
        if Path(target) == path:
            raise utils.FileProblem(f"cannot write {target}: no space left on device", target)
        real(target, data)

    monkeypatch.setattr(utils, "write_bytes_atomic", full_disk)
    assert cli.main(["convert-checkpoint", str(path)]) == 2
    one_line_error(capsys, str(path), "no space left on device")
    kept = tmp_path / f"checkpoint.pt{checkpoint.OLD_SUFFIX}"
    assert path.read_bytes() == original and kept.read_bytes() == original  # the kept copy is the original
    monkeypatch.setattr(utils, "write_bytes_atomic", real)  # space freed: the same command again
    assert cli.main(["convert-checkpoint", str(path)]) == 0
    assert kept.read_bytes() == original
    assert checkpoint.read_checkpoint(path)["format"] == checkpoint.FORMAT


# --------------------------------------------------------------------------- verify and frames.jsonl


def _dataset(root: Path, rgb: str) -> Path:
    """A dataset folder of one frame whose record names ``rgb``; checksums.sha256 lists every file in it."""
    (root / "test").mkdir(parents=True)
    (root / "test" / "0.png").write_bytes(b"png")
    (root / "test" / "0.npy").write_bytes(b"npy")
    record = {"rgb": rgb, "depth": "test/0.npy", "organ": "colon", "group": "a", "index": 0,
              "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    (root / "test" / "frames.jsonl").write_text(json.dumps(record) + "\n")
    lines = [f"{hashlib.sha256((root / rel).read_bytes()).hexdigest()}  {rel}"
             for rel in ("test/0.png", "test/0.npy", "test/frames.jsonl")]
    (root / "checksums.sha256").write_text("\n".join(lines) + "\n")
    return root


def test_verify_reads_frames_jsonl_as_train_does(tmp_path, capsys):
    good = _dataset(tmp_path / "good", "test/0.png")
    assert integrity.verify(good) == []  # a record naming files inside, listed: no problem
    (tmp_path / "outside.png").write_bytes(b"png")
    bad = _dataset(tmp_path / "bad", "../outside.png")
    problems = integrity.verify(bad)
    assert len(problems) == 1 and problems[0].startswith("unreadable: test/frames.jsonl ("), problems
    assert "line 1" in problems[0] and "../outside.png" in problems[0]
    assert cli.main(["verify", str(bad)]) == 1  # verify's status for a dataset with problems
    out = capsys.readouterr().out
    assert "verify: ok" not in out and "unreadable: test/frames.jsonl" in out
    with pytest.raises(ValueError, match="test/frames.jsonl"):  # train's and evaluate's check says the same
        integrity.check_dataset(bad, ("test",))
