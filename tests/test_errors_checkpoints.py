"""Checkpoints and bundles from elsewhere: a record deflated inside the checkpoint's own zip, an
expanded view of one number, a pickle that asks for a huge buffer, a first-format file that
converts to gigabytes, a bundled checkpoint that does not fit the network.

Every such file is refused in one ``error:`` line naming it, exit status 2, before a record is
read or a tensor used; the commands run in a subprocess under an address-space limit (``CAP``,
which a normal run stays well within) and their peak resident memory is read back with
``os.wait4``. The files are built here, byte by byte where torch.save cannot write them.
"""

import collections
import hashlib
import io
import json
import os
import pickle
import resource
import struct
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import one_line_error

from geodepth_lite import cli
from geodepth_lite.data import bounds
from geodepth_lite.training import checkpoint

CAP = 2 * 2**30  # address space of a command: torch and a normal predict run fit (about 1.5 GiB suffices)
RSS_MAX = 2**30  # the resident memory no crafted file may make a command exceed
ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- crafting


class _Storage:
    """Pickles as torch.save's reference to record ``data/<key>`` holding ``numel`` floats."""

    def __init__(self, key: str, numel: int):
        self.key, self.numel = key, numel


class _View:
    """Pickles as torch.save pickles a tensor: a view of ``storage`` with any size and stride."""

    def __init__(self, storage: _Storage, size: tuple, stride: tuple):
        self.storage, self.size, self.stride = storage, size, stride

    def __reduce__(self):
        return torch._utils._rebuild_tensor_v2, (self.storage, 0, self.size, self.stride, False,
                                                 collections.OrderedDict())


class _Call:
    """Pickles as a call of ``fn`` with ``args``."""

    def __init__(self, fn, *args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if isinstance(obj, _Storage):
            return ("storage", torch.FloatStorage, obj.key, "cpu", obj.numel)
        return None


def _pickled(obj) -> bytes:
    buf = io.BytesIO()
    _Pickler(buf, protocol=2).dump(obj)
    return buf.getvalue()


def _stored(name: str, data: bytes) -> tuple:
    return name, data, 0, zlib.crc32(data), len(data)


def _zip(path: Path, members: list[tuple]) -> Path:
    """A zip file of ``(name, bytes as stored, method, crc32, unpacked size)`` members, written by hand so
    that a member can hold a deflate stream made without unpacking it."""
    out, central = bytearray(), bytearray()
    for name, data, method, crc, size in members:
        raw = name.encode()
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0, crc, len(data), size,
                               len(raw), 0, 0, 0, 0, 0, len(out)) + raw
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0, crc, len(data), size, len(raw), 0)
        out += raw + data
    n = len(members)
    path.write_bytes(bytes(out + central + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central),
                                                       len(out), 0)))
    return path


def _torch_file(path: Path, obj, records: list[tuple]) -> Path:
    """A checkpoint in torch.save's zip layout: the pickle of ``obj`` and the given data records."""
    return _zip(path, [_stored("archive/data.pkl", _pickled(obj)), _stored("archive/byteorder", b"little"),
                       *records, _stored("archive/version", b"3\n")])


def _zeros_deflated(mib: int) -> tuple[bytes, int]:
    """(a raw deflate stream of ``mib`` MiB of zeros, their CRC-32), made from one compressed MiB repeated:
    each piece ends in a full flush, so it stands alone."""
    z = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = z.compress(bytes(2**20)) + z.flush(zlib.Z_FULL_FLUSH)
    crc, zero = 0, bytes(2**20)
    for _ in range(mib):
        crc = zlib.crc32(zero, crc)
    return piece * mib + b"\x03\x00", crc  # 03 00: an empty final block


BOMB_MIB = 2000  # about 2 GB unpacked, about 2 MB packed


@pytest.fixture(scope="module")
def bomb():
    return _zeros_deflated(BOMB_MIB)


def _key() -> str:
    return next(iter(checkpoint.network_sizes()))  # a weight name of the network


def deflated_checkpoint(path: Path, bomb, first_format: bool = False) -> Path:
    """A checkpoint whose one weight record is a deflate stream of about 2 GB of zeros (torch.save never
    compresses; torch's reader unpacks it all the same). ``first_format``: numpy RNG keys as numpy objects."""
    stream, crc = bomb
    numel = BOMB_MIB * 2**20 // 4
    obj = {"model": {_key(): _View(_Storage("0", numel), (numel,), (1,))}, "cfg": {"image_size": 32}, "epoch": 1}
    if first_format:
        obj["rng"] = {"numpy": ("MT19937", np.arange(624, dtype=np.uint32), 3, 0, 0.0)}
    return _torch_file(path, obj, [("archive/data/0", stream, 8, crc, numel * 4)])


def expanded_checkpoint(path: Path) -> Path:
    """A checkpoint of a few hundred bytes holding a 3 x 10^9-element expanded view of one float."""
    view = _View(_Storage("0", 1), (3 * 10**9,), (0,))
    return _torch_file(path, {"model": {_key(): view}, "cfg": {"image_size": 32}, "epoch": 1},
                       [_stored("archive/data/0", struct.pack("<f", 1.0))])


def buffer_checkpoint(path: Path) -> Path:
    """A checkpoint whose pickle asks for a 10 GB bytearray (a global that torch's weights-only loader allows)."""
    return _torch_file(path, {"model": {_key(): _Call(bytearray, 10**10)}, "cfg": {"image_size": 32}}, [])


def hidden_buffer_checkpoint(path: Path) -> Path:
    """``buffer_checkpoint``'s pickle as a second ``data.pkl`` behind a harmless first one: a check that
    reads the first record of that name passes the file, and torch.load reads the second."""
    benign = _pickled({"model": {}, "cfg": {"image_size": 32}})
    evil = _pickled({"model": {_key(): _Call(bytearray, 10**10)}, "cfg": {"image_size": 32}})
    return _zip(path, [_stored("archive/data.pkl", benign), _stored("archive/data.pkl", evil),
                       _stored("archive/byteorder", b"little"), _stored("archive/version", b"3\n")])


def bundle_of(path: Path, ckpt: Path, run: str = "case4_seed0-crafted") -> Path:
    """A class bundle (bundle.json with checksums) holding ``ckpt`` as its one run's checkpoint."""
    name = f"checkpoints/{run}/checkpoint.pt"
    data = ckpt.read_bytes()
    index = {"format": 1, "profile": "smoke", "runs": [run], "files": {name: hashlib.sha256(data).hexdigest()}}
    return _zip(path, [_stored(name, data), _stored("bundle.json", json.dumps(index).encode())])


# --------------------------------------------------------------------------- running under a bound


def _bounded(argv: list[str], cwd: Path, home: Path, timeout: float = 300) -> tuple[int, str, float]:
    """(exit status, stderr, peak resident MiB) of ``python -m geodepth_lite <argv>`` run under ``CAP``."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (CAP, CAP))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "GEODEPTH_LITE_HOME": str(home), "OMP_NUM_THREADS": "1"}
    err = cwd / "stderr.txt"
    with open(err, "wb") as sink:
        proc = subprocess.Popen([sys.executable, "-m", "geodepth_lite", *argv], cwd=cwd, env=env,
                                stdout=subprocess.DEVNULL, stderr=sink, preexec_fn=limit)
    end = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if time.monotonic() > end:
            proc.kill()
            pid, status, usage = os.wait4(proc.pid, 0)
            break
        time.sleep(0.05)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, err.read_text(), usage.ru_maxrss / 1024


def _assert_one_line(rc: int, err: str, rss: float, *needles) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), (rc, err[-2000:])
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])
    assert rss < RSS_MAX / 2**20, f"peak resident memory {rss:.0f} MiB"
    return lines[0]


def _commands(ckpt: Path, tmp: Path, smoke_root: Path) -> dict[str, tuple[list[str], Path]]:
    """Each command that reads a checkpoint: its argv, and the file its error line must name."""
    bundled = bundle_of(tmp / "class.zip", ckpt)
    return {
        "predict": (["predict", "--checkpoint", str(ckpt), "--input", str(smoke_root / "test" / "rgb"),
                     "--out", str(tmp / "pred"), "--no-progress"], ckpt),
        "evaluate": (["evaluate", "--checkpoint", str(ckpt), "--dataset", str(smoke_root), "--out",
                      str(tmp / "eval"), "--no-progress", "--no-verify"], ckpt),
        "unbundle": (["unbundle", str(bundled)], bundled),
    }


def _nothing_written(tmp: Path, home: Path) -> None:
    assert not (tmp / "pred").exists() and not (tmp / "eval").exists()
    assert not (home / "runs").exists() or not any(p.is_file() for p in (home / "runs").rglob("*"))


# --------------------------------------------------------------------------- 1. gigabytes from a checkpoint


@pytest.mark.parametrize("command", ["predict", "evaluate", "unbundle"])
def test_a_record_deflated_inside_the_checkpoint_is_refused_before_it_is_unpacked(
        smoke_root, tmp_path, bomb, command):
    ckpt = deflated_checkpoint(tmp_path / "checkpoint.pt", bomb)
    assert ckpt.stat().st_size < 3 * 2**20  # about 2 MB on disk, about 2 GB unpacked
    argv, named = _commands(ckpt, tmp_path, smoke_root)[command]
    rc, err, rss = _bounded(argv, tmp_path, tmp_path / "home")
    _assert_one_line(rc, err, rss, named, "compressed")
    _nothing_written(tmp_path, tmp_path / "home")


@pytest.mark.parametrize("command", ["predict", "evaluate", "unbundle"])
def test_an_expanded_view_of_one_number_is_refused_before_it_is_used(smoke_root, tmp_path, command):
    ckpt = expanded_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt.stat().st_size < 2000
    view = torch.load(ckpt, weights_only=True)["model"][_key()]  # torch rebuilds it without allocating
    assert view.numel() == 3 * 10**9 and view.untyped_storage().nbytes() == 4
    argv, named = _commands(ckpt, tmp_path, smoke_root)[command]
    rc, err, rss = _bounded(argv, tmp_path, tmp_path / "home")
    _assert_one_line(rc, err, rss, named, "expanded or overlapping view", "12000000000 bytes")
    _nothing_written(tmp_path, tmp_path / "home")


def test_a_pickle_asking_for_a_huge_buffer_is_refused_unread(smoke_root, tmp_path):
    ckpt = buffer_checkpoint(tmp_path / "checkpoint.pt")
    assert "builtins.bytearray" not in torch.serialization.get_unsafe_globals_in_checkpoint(ckpt)  # torch allows it
    with pytest.raises(ValueError, match="builtins.bytearray"):
        checkpoint.read_checkpoint(ckpt)
    argv, _ = _commands(ckpt, tmp_path, smoke_root)["predict"]
    rc, err, rss = _bounded(argv, tmp_path, tmp_path / "home")
    _assert_one_line(rc, err, rss, ckpt, "refused", "builtins.bytearray")


@pytest.mark.parametrize("command", ["predict", "unbundle"])
def test_a_second_pickle_behind_a_harmless_one_is_refused_unread(smoke_root, tmp_path, command):
    ckpt = hidden_buffer_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt.stat().st_size < 2000
    with pytest.raises(ValueError, match="archive/data.pkl is there twice"):
        checkpoint.read_checkpoint(ckpt)
    argv, named = _commands(ckpt, tmp_path, smoke_root)[command]
    rc, err, rss = _bounded(argv, tmp_path, tmp_path / "home")
    _assert_one_line(rc, err, rss, named, "there twice")
    _nothing_written(tmp_path, tmp_path / "home")


def test_convert_checkpoint_bounds_its_own_process_and_its_output(tmp_path, bomb):
    """The first-format reader's child was bounded; its parent received and wrote whatever the child
    unpacked (1.4 GB from a 1.4 MB file). Now the archive is checked before the child starts."""
    ckpt = deflated_checkpoint(tmp_path / "checkpoint.pt", bomb, first_format=True)
    assert set(torch.serialization.get_unsafe_globals_in_checkpoint(ckpt)) <= set(checkpoint.NUMPY_ARRAY_GLOBALS)
    before = ckpt.read_bytes()
    rc, err, rss = _bounded(["convert-checkpoint", str(ckpt)], tmp_path, tmp_path / "home")
    _assert_one_line(rc, err, rss, ckpt, "compressed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "stderr.txt"]
    assert ckpt.read_bytes() == before


def test_the_converted_bytes_are_received_only_up_to_the_bound(tmp_path, monkeypatch):
    """A child that hands back more than a checkpoint of the network holds is not listened to."""
    path = tmp_path / "checkpoint.pt"
    torch.save({"model": {"w": torch.arange(4.0)}, "cfg": {"image_size": 32},
                "rng": {"numpy": ("MT19937", np.arange(624, dtype=np.uint32), 3, 0, 0.0)}}, path)
    limits = checkpoint.Limits(record=2**20, total=2**20)
    assert checkpoint.read_old_checkpoint(path, limits)  # within the bound: converted
    monkeypatch.setattr(checkpoint, "_read_old_in_child", lambda p, lim: bytes(limits.total + 2**25))
    with pytest.raises(ValueError, match=f"cannot be converted: its conversion is over {limits.total + 2**24} bytes"):
        checkpoint.read_old_checkpoint(path, limits)


def test_a_training_checkpoint_of_the_network_is_within_the_bounds(tmp_path):
    """The bounds are not tighter than a real checkpoint: DepthNet's weights, Adam's two moments after one
    step, every random state and a history, as train.fit saves them, loads (the control of the tests above)."""
    from geodepth_lite.core.model import DepthNet

    model = DepthNet()
    opt = torch.optim.Adam(model.parameters())
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    opt.step()
    path = tmp_path / "checkpoint.pt"
    checkpoint.save_checkpoint(path, {"model": model.state_dict(), "optimizer": opt.state_dict(),
                                      "cfg": {"image_size": 32}, "epoch": 1, "history": [{"loss": 1.0}],
                                      "rng": checkpoint.rng_state(torch.Generator())})
    del model, opt
    limits = checkpoint.network_limits()
    assert limits.total / 2 < path.stat().st_size < limits.total  # the file is most of what the bound allows
    ckpt = checkpoint.read_checkpoint(path)
    assert ckpt["optimizer"]["state"] and checkpoint.tensor_problem(ckpt, limits) is None
    # the planted defect: the same file under a bound a tensor smaller is refused, naming the record
    tight = checkpoint.Limits(record=limits.record - 1, total=limits.total)
    with pytest.raises(ValueError, match=r"declares \d+ bytes, over the"):
        checkpoint.read_checkpoint(path, limits=tight)


def test_unbundle_refuses_a_checkpoint_that_does_not_fit_the_network(tmp_path, monkeypatch, capsys):
    ckpt = tmp_path / "checkpoint.pt"
    torch.save({"model": {"w": torch.arange(4.0)}, "cfg": {"image_size": 32}, "epoch": 1, "complete": True}, ckpt)
    bundled = bundle_of(tmp_path / "class.zip", ckpt)
    monkeypatch.setenv("GEODEPTH_LITE_HOME", str(tmp_path / "home"))
    assert cli.main(["unbundle", str(bundled)]) == 2
    one_line_error(capsys, bundled, "does not fit this network", "unexpected tensor(s), first w")
    _nothing_written(tmp_path, tmp_path / "home")


# --------------------------------------------------------------------------- zip directories, bounded unread


def test_the_zip_directory_is_read_from_its_end_record(tmp_path):
    """Known answers: the hand-made zip's directory is 46 bytes and the name per member; a zip of more
    than 65535 members keeps its counts in the ZIP64 end record, which is read instead."""
    made = _zip(tmp_path / "three.zip", [_stored(f"m{i}", b"x" * i) for i in range(3)])
    assert bounds.zip_directory(made) == (3, 3 * (46 + 2))
    big = tmp_path / "zip64.zip"
    with zipfile.ZipFile(big, "w") as zf:
        for i in range(70_000):
            zf.writestr(f"{i:05d}", b"")
    with zipfile.ZipFile(big) as zf:
        assert len(zf.infolist()) == 70_000
    entries, directory = bounds.zip_directory(big)
    assert entries == 70_000 and directory == 70_000 * (46 + 5)
    (tmp_path / "plain.txt").write_bytes(b"not a zip")
    assert bounds.zip_directory(tmp_path / "plain.txt") is None


def _directory_liar(path: Path, members: int, declared: int, name_len: int = 7) -> Path:
    """A zip of ``members`` empty members (names of ``name_len`` characters) whose end record declares
    ``declared`` of them."""
    _zip(path, [_stored(f"m{i:06d}".ljust(name_len, "x"), b"") for i in range(members)])
    data = bytearray(path.read_bytes())
    data[-12:-8] = struct.pack("<HH", declared, declared)
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("members, declared, name_len", [(10_001, 10_001, 7), (2_600, 1, 4_000)])
def test_unbundle_refuses_a_directory_over_its_bound_before_zipfile_reads_it(tmp_path, monkeypatch, capsys,
                                                                             members, declared, name_len):
    """More members than a bundle holds, or a directory far larger than the members it declares: refused
    from the end record, before ``zipfile`` builds the directory in memory (millions of members: GBs)."""
    from geodepth_lite import cli
    from geodepth_lite.apps import bundle

    path = _directory_liar(tmp_path / "class.zip", members, declared, name_len)

    def never(*args, **kwargs):
        raise AssertionError("zipfile read the directory")

    monkeypatch.setattr(bundle.zipfile, "ZipFile", never)
    monkeypatch.setenv("GEODEPTH_LITE_HOME", str(tmp_path / "home"))
    assert cli.main(["unbundle", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"bundle {path} is refused: its zip directory declares {declared} members" in err[0]
    assert not (tmp_path / "home").exists()


def test_a_checkpoint_directory_over_its_bound_is_refused_before_zipfile_reads_it(tmp_path, monkeypatch):
    limits = checkpoint.network_limits()
    path = _directory_liar(tmp_path / "checkpoint.pt", limits.members + 1, limits.members + 1)
    monkeypatch.setattr(checkpoint.zipfile, "ZipFile", lambda *a, **k: pytest.fail("zipfile read the directory"))
    with pytest.raises(ValueError, match=f"its zip directory declares {limits.members + 1} members"):
        checkpoint.check_archive(path, limits)
    assert limits.members > 471  # a training run's checkpoint holds 471 records
