"""A bug reads as a bug, a mistake as a mistake: ``cli.main`` prints one line for each, and exits 1
for a failure of geodepth-lite's own (naming the command and asking for ``--debug``) but 2 for
the user's (``UserError``) or a file the system refused (``OSError``)."""

from pathlib import Path

import numpy as np
import pytest
import torch

from geodepth_lite import cli
from geodepth_lite.apps import predict
from geodepth_lite.core import losses, metrics, sdf
from geodepth_lite.core.errors import UserError
from geodepth_lite.workbook import reproduce


def _predict_argv(tmp_path, *extra: str) -> list[str]:
    image = tmp_path / "frame.png"
    image.write_bytes(b"")  # never read: the planted failure comes first
    return ["predict", "--checkpoint", str(tmp_path / "none.pt"), "--input", str(image),
            "--out", str(tmp_path / "out"), *extra]


def _plant(monkeypatch, exc: BaseException) -> None:
    """``predict`` fails with ``exc`` where it lists its inputs, after its options were checked."""
    def fail(path):
        raise exc

    monkeypatch.setattr(predict, "list_inputs", fail)


def _stderr_lines(capsys) -> list[str]:
    return [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip()]


def test_a_planted_key_error_prints_the_bug_line_and_exits_1(tmp_path, monkeypatch, capsys):
    _plant(monkeypatch, KeyError("frame_id"))
    assert cli.main(_predict_argv(tmp_path)) == 1
    lines = _stderr_lines(capsys)
    assert len(lines) == 1, lines
    assert "bug in geodepth-lite" in lines[0] and "KeyError" in lines[0] and "frame_id" in lines[0]
    assert "'predict'" in lines[0] and "--debug" in lines[0]


def test_debug_shows_the_traceback_of_a_bug(tmp_path, monkeypatch, capsys):
    _plant(monkeypatch, KeyError("frame_id"))
    assert cli.main(["--debug", *_predict_argv(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "KeyError: 'frame_id'" in err
    assert "bug in geodepth-lite" in err.splitlines()[-1]


def test_a_plain_value_error_of_the_package_is_a_bug(tmp_path, monkeypatch, capsys):
    """A ValueError raised by the package's own code (not a UserError) is a bug now, not a mistake."""
    _plant(monkeypatch, ValueError("shapes differ"))
    assert cli.main(_predict_argv(tmp_path)) == 1
    assert "bug in geodepth-lite" in _stderr_lines(capsys)[0]


@pytest.mark.parametrize("exc", [UserError("--input x: not an image"), FileNotFoundError(2, "No such file", "x.png")])
def test_a_user_error_or_a_refused_file_still_exits_2(tmp_path, monkeypatch, capsys, exc):
    _plant(monkeypatch, exc)
    assert cli.main(_predict_argv(tmp_path)) == 2
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("error: ") and "bug" not in lines[0], lines


def test_a_user_mistake_prints_its_one_line_and_exits_2(tmp_path, capsys):
    assert cli.main(_predict_argv(tmp_path, "--batch-size", "0")) == 2
    assert _stderr_lines(capsys) == ["error: --batch-size must be at least 1, got 0"]


def test_a_plain_value_error_is_a_bug_wherever_it_is_raised():
    """Only UserError (and OSError) read as the user's mistake: a plain ValueError is a bug."""
    with pytest.raises(ValueError, match="same shape") as elsewhere:
        metrics.compute_depth_metrics(np.ones((1, 4, 4)), np.ones((1, 4, 5)))
    assert not cli.is_user_error(elsewhere.value)


@pytest.mark.parametrize("call, words", [
    (lambda: losses.border_weight_map(8, 8, -1.0), "border weight"),
    (lambda: losses.group_weights([1.0, -1.0, 0.0]), "non-negative"),
    (lambda: sdf.resolve_method("bogus", torch.device("cpu")), "unknown nearest-neighbour method"),
    (lambda: sdf.check_sdf_options("view", "sphere"), "sdf sampling"),
    (lambda: sdf.SDFOptions(sampling="sphere"), "sdf sampling"),
    (lambda: losses.LossSpec(depth_term="l2"), "depth_term"),
    (lambda: reproduce.select_notebooks(["99"], [Path("00_intro.ipynb")]), "no notebook '99'"),
])
def test_the_settings_a_user_gives_raise_user_errors(call, words):
    """Settings a configuration or a flag carries (loss weights, the SDF's options) are the user's to fix:
    UserError, one line, exit 2; a shape handed to the SDF from inside the package stays a bug."""
    with pytest.raises(UserError, match=words) as exc:
        call()
    assert cli.is_user_error(exc.value)
    with pytest.raises(ValueError, match="B x 1 x H x W") as internal:
        sdf.sdf_fields_batched(torch.ones(2, 2), torch.ones(2, 2), torch.eye(3), sdf.SDFOptions(grid=4))
    assert not isinstance(internal.value, UserError) and not cli.is_user_error(internal.value)
