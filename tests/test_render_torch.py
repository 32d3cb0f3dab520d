"""The torch renderer: analytic geometry and lighting, agreement with VTK on teach frames (and planted defects
that break it), the torch path without VTK or matplotlib, and datasets that record their renderer."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from geodepth_lite import cli
from geodepth_lite.core import camera
from geodepth_lite.data import integrity, render, synth, tube
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render_torch as rt

TINY = {"camera": {"width": 32, "height": 32}, "splits": {"train": 4, "test": 2}, "frames_per_scene": 2}
ROOT = Path(__file__).resolve().parents[1]


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("K, width, height", [
    (None, 96, 96),  # the shipped check manifest's camera
    (np.array([[41.0, 0.0, 23.7], [0.0, 52.5, 38.2], [0.0, 0.0, 1.0]]), 56, 72),  # fx != fy, off-centre
])
def test_straight_tube_depth_matches_the_analytic_cylinder(K, width, height):
    m = mf.load_manifest("check_cylinder")
    K = mf.intrinsics_of(m) if K is None else K
    tm = tube.build_tube(m["organ_presets"]["cylinder"], 0, m["resolution"])
    R, L = tm.preset["radius"], tm.length
    r = rt.TorchRenderer(width, height, K, device="cpu")
    r.set_tube(tm)
    for s in (3.0, 12.0):
        rgb, depth = r.render(render.sequence_poses(tm, 1, s, 0.0)[0])
        assert rgb.shape == (height, width, 3) and rgb.dtype == np.uint8
        assert depth.shape == (height, width) and depth.dtype == np.float32
        grid = camera.normalized_grid(K, height, width).numpy()  # (2, H, W): x and y over z
        xn, yn = grid[0], grid[1]
        with np.errstate(divide="ignore"):
            expected = R / np.sqrt(xn**2 + yn**2)
        wall = expected < 0.95 * (L - s)
        assert wall.mean() > 0.9
        assert np.abs(depth[wall] / expected[wall] - 1.0).max() < 0.005


def test_point_light_at_the_lens_has_inverse_square_falloff():
    # as tests/test_render.py for VTK: Lambertian radiance I * albedo * R / d^3 on a cylinder's wall
    tm = tube.build_tube("cylinder", 0, {"n_theta": 128, "ring_step": 1.0})
    r = rt.TorchRenderer(64, 64, camera.intrinsics(64), device="cpu")
    r.set_tube(tm, material={"ambient": 0.0, "diffuse": 1.0, "specular": 0.0})
    r.set_tint((1.0, 1.0, 1.0))
    rgb, depth = r.render(render.sequence_poses(tm, 1, 5.0, 0.0)[0], [render.Light((0.0, 0.0, 0.0), (1, 1, 1), 2.0)])
    predicted = 2.0 / np.sqrt(1.0 + depth.astype(np.float64) ** 2) ** 3 * 255.0
    lit = (depth > 0) & (predicted > 20) & (predicted < 250)
    assert lit.sum() > 200
    ratio = rgb[..., 0][lit] / predicted[lit]
    assert np.median(ratio) == pytest.approx(1.0, rel=0.05)
    assert np.percentile(np.abs(ratio / np.median(ratio) - 1), 90) < 0.05


def test_exposure_rays_meet_the_wall_where_vtk_finds_it():
    m = mf.load_manifest("scenario_smoke")
    tm = tube.build_tube(m["organ_presets"]["colon"], 3, m["resolution"])
    r = rt.TorchRenderer(32, 32, device="cpu")
    r.set_tube(tm)
    rng = np.random.default_rng(0)
    for _ in range(4):
        T, _ = render.sample_pose(tm, rng, mf.split_path(m, "train"))
        dirs = rng.normal(size=(9, 3)) * 0.3 + T[:3, 2]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        np.testing.assert_allclose(r.cast_rays(T[:3, 3], dirs), tm.cast_rays(T[:3, 3], dirs), rtol=1e-9)
    # many origins in one batch (as on a GPU) give the same bits as one origin at a time (the CPU's way)
    poses = [render.sample_pose(tm, rng, mf.split_path(m, "train"))[0] for _ in range(5)]
    origins, dirs = zip(*(render.exposure_rays(T, camera.intrinsics(32), 32, 32) for T in poses))
    one_by_one = r.cast_rays_many(np.stack(origins), np.stack(dirs))
    batched = r._cast(torch.as_tensor(np.stack(origins)), torch.as_tensor(np.stack(dirs)))
    assert np.isfinite(one_by_one).mean() > 0.9 and np.array_equal(one_by_one, batched)


def test_a_frame_is_the_same_at_one_and_two_threads():
    m = mf.load_manifest("scenario_smoke")
    tm = tube.build_tube(m["organ_presets"]["stomach"], 5, m["resolution"])
    r = rt.TorchRenderer(48, 48, device="cpu")
    r.set_tube(tm, render.make_texture(render.TEXTURES["red"], np.random.default_rng(1)))
    T, _ = render.sample_pose(tm, np.random.default_rng(2), mf.split_path(m, "train"))
    lights = [render.Light((0.1, 0.0, 0.0), (1.0, 0.9, 0.8), 3.0)]
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a = r.render(T, lights)
        torch.set_num_threads(2)
        b = r.render(T, lights)
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


# ----------------------------------------------------------------------------- agreement with VTK


class _Shifted(rt.TorchRenderer):
    """Planted defect: the camera's principal point half a pixel off."""

    def __init__(self, w, h, K, **kw):
        K = np.array(K, dtype=np.float64)
        K[0, 2] += 0.5
        super().__init__(w, h, K, **kw)


class _LightMoved(rt.TorchRenderer):
    """Planted defect: every light a tenth of a unit further to the side than asked."""

    def render(self, T, lights=None):
        moved = [render.Light((lt.offset[0] + 0.1, lt.offset[1], lt.offset[2]), lt.color, lt.intensity)
                 for lt in lights]
        return super().render(T, moved)


class _RayLength(rt.TorchRenderer):
    """Planted defect: depth as the distance along the ray instead of the z-depth."""

    def render(self, T, lights=None):
        rgb, depth = super().render(T, lights)
        xn, yn = camera.normalized_grid(self.K, self.height, self.width).numpy()
        return rgb, (depth * np.sqrt(1 + xn**2 + yn**2)).astype(np.float32)


@pytest.fixture(scope="module")
def teach_frames():
    from geodepth_lite.data import render_agreement as ra

    m = mf.load_manifest("scenario_teach")
    c = m["camera"]
    inputs = ra.frame_inputs(m, "train", 6)
    with render.Renderer(c["width"], c["height"], mf.intrinsics_of(m), near=c["near"], far=c["far"]) as r:
        vtk_frames = ra.render_with(r, inputs)
    return m, inputs, vtk_frames


def _rows(teach_frames, cls):
    from geodepth_lite.data import render_agreement as ra

    m, inputs, vtk_frames = teach_frames
    c = m["camera"]
    r = cls(c["width"], c["height"], mf.intrinsics_of(m), near=c["near"], far=c["far"], device="cpu")
    return ra.agreement(inputs, vtk_frames, ra.render_with(r, inputs))


def test_torch_frames_agree_with_vtk_on_teach_frames(teach_frames):
    from geodepth_lite.data import render_agreement as ra

    rows = _rows(teach_frames, rt.TorchRenderer)
    assert len(rows) == 6 and len({r["organ"] for r in rows}) == 3
    assert ra.within_bounds(rows) == []
    assert min(r["depth_share"] for r in rows) >= 0.99


@pytest.mark.parametrize("cls, measure", [(_Shifted, "mad_raw"), (_LightMoved, "mad_raw"),
                                          (_RayLength, "depth_share")])
def test_the_agreement_bounds_catch_a_wrong_renderer(teach_frames, cls, measure):
    from geodepth_lite.data import render_agreement as ra

    problems = ra.within_bounds(_rows(teach_frames, cls))
    assert any(f": {measure} " in p for p in problems), problems


# ----------------------------------------------------------------------------- datasets


def test_torch_datasets_are_byte_identical_record_their_renderer_and_verify(tmp_path):
    m = mf.load_manifest("scenario_smoke", TINY)
    a = synth.generate(m, tmp_path / "a", progress=False, renderer="torch", device="cpu")
    b = synth.generate(m, tmp_path / "b", progress=False, renderer="torch", device="cpu", workers=1, processes=1)
    assert _files(a) == _files(b)
    assert integrity.verify(a) == []
    assert integrity.renderer_of(a)["renderer"] == "torch" and integrity.renderer_of(a)["device"] == "cpu"
    assert (a / "checksums.sha256").read_text().splitlines()[1].endswith("  renderer.json")
    rec = json.loads((a / "train" / "frames.jsonl").read_text().splitlines()[0])
    depth = np.load(a / rec["depth"])
    assert depth.dtype == np.float32 and depth.shape == (32, 32) and (depth > 0).mean() > 0.5
    # a changed renderer record is caught; so is one added to a dataset that never had it
    (a / "renderer.json").write_text(json.dumps({"renderer": "vtk"}))
    assert "changed: renderer.json" in integrity.verify(a)


def test_a_folder_never_mixes_two_renderers(tmp_path):
    m = mf.load_manifest("scenario_smoke", TINY)
    out = synth.generate(m, tmp_path / "d", progress=False, renderer="vtk")
    assert integrity.renderer_of(out) == {"renderer": "vtk"} and not (out / "renderer.json").exists()
    assert not any("renderer.json" in ln for ln in (out / "checksums.sha256").read_text().splitlines())
    before = _files(out)
    with pytest.raises(FileExistsError, match="made by the vtk renderer"):
        synth.generate(m, out, progress=False, renderer="torch", device="cpu")
    assert _files(out) == before  # nothing lost
    (out / "renderer.json").write_text(json.dumps({"renderer": "torch"}))  # planted: a VTK dataset claims torch
    assert any(p.startswith("changed: renderer.json") for p in integrity.verify(out))
    (out / "renderer.json").unlink()
    synth.generate(m, out, progress=False, renderer="torch", device="cpu", overwrite=True)
    assert integrity.verify(out) == [] and integrity.renderer_of(out)["renderer"] == "torch"
    assert integrity.is_complete_by(out, m, "torch") and not integrity.is_complete_by(out, m, "vtk")


def test_cli_renderer_and_device_flags(tmp_path, capsys):
    path = tmp_path / "m.json"
    path.write_text(json.dumps(mf.load_manifest("scenario_smoke", TINY)))
    out = tmp_path / "d"
    assert cli.main(["synth", "--manifest", str(path), "--out", str(out), "--renderer", "torch", "--device", "cpu",
                     "--no-progress"]) == 0
    assert "with the torch renderer on cpu" in capsys.readouterr().out
    assert cli.main(["verify", str(out)]) == 0
    assert "made by the torch renderer on cpu" in capsys.readouterr().out
    for device in ("gpu7", "cuda:0" if not torch.cuda.is_available() else "nonsense"):
        assert cli.main(["synth", "--manifest", str(path), "--out", str(tmp_path / "e"), "--renderer", "torch",
                         "--device", device]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --device") and err.count("\n") == 1
    assert not (tmp_path / "e").exists()


BLOCKED = textwrap.dedent("""
    import importlib.abc, sys

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("vtk", "vtkmodules", "pyvista", "matplotlib"):
                raise ImportError(f"{name} is blocked in this test")
            return None

    sys.meta_path.insert(0, Block())
""")


def test_the_torch_path_needs_neither_vtk_nor_matplotlib(tmp_path):
    script = BLOCKED + textwrap.dedent(f"""
        import json
        from geodepth_lite import cli
        from geodepth_lite.data import integrity, synth
        from geodepth_lite.data import manifest as mf

        assert synth.resolve_renderer("auto") == "torch"
        m = mf.load_manifest("scenario_smoke", {TINY!r})
        out = synth.generate(m, {str(tmp_path / 'a')!r}, progress=False, device="cpu")  # auto: torch here
        assert integrity.verify(out) == [] and integrity.renderer_of(out)["renderer"] == "torch"
        path = {str(tmp_path / 'm.json')!r}
        open(path, "w").write(json.dumps(m))
        assert cli.main(["synth", "--manifest", path, "--out", {str(tmp_path / 'b')!r}, "--no-progress"]) == 0
        blocked = [k for k in sys.modules if k.split(".")[0] in ("vtk", "vtkmodules", "pyvista", "matplotlib")]
        assert not blocked, blocked
        print("torch path ok")
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={"PYTHONPATH": str(ROOT), "PATH": "", "OMP_NUM_THREADS": "1", "HOME": str(tmp_path)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "torch path ok" in proc.stdout
    assert _files(tmp_path / "a") == _files(tmp_path / "b")


def test_the_benchmark_scripts_run_at_tiny_sizes(capsys):
    import runpy

    bench = ROOT / "benchmarks"
    main = runpy.run_path(str(bench / "render_agreement.py"), run_name="benchmark_under_test")["main"]
    assert main(["--manifest", "scenario_smoke", "--frames", "2"]) == 0
    out = capsys.readouterr().out
    assert "| all (2) |" in out and "within bounds" in out
    main = runpy.run_path(str(bench / "bench_render_torch.py"), run_name="benchmark_under_test")["main"]
    before = torch.get_num_threads()
    try:
        assert main(["--manifest", "scenario_smoke", "--scenes", "1", "--vtk"]) == 0
    finally:
        torch.set_num_threads(before)
    assert "torch render / VTK render" in capsys.readouterr().out
