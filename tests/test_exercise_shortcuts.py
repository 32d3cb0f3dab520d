"""Checks that test the skill: for every exercise of notebooks 01-07, the shortcut and a plausible wrong
answer both lose the points, and the solution keeps them.

- A **shortcut** gets the answer without the skill: it calls the package function that the prompt asks
  the student to write (or the check's own reference), or, where the prompt forbids nothing, it is an
  answer that meets the visible check only. It passes the visible check (so it is a real threat) and fails
  the full check, hidden tests included, as ``nbgrader autograde`` runs it.
- A **wrong answer** is a plausible mistake; the visible check alone rejects it, so a student sees it.
- An **open-ended** exercise is graded by hand (``exercises.grade_by_hand``: its check carries no points);
  its visible check still rejects a placeholder answer.

The answers are the exercise's answer cell with its solution regions replaced; each runs with its check
in a fresh namespace (``exercises.run_exercise``), in-process.
"""

import ast
import collections
import contextlib
import copy
import json
import re
import sys
import tempfile
import textwrap
from unittest import mock

import pytest

from geodepth_lite.workbook import exercises as E
from geodepth_lite.workbook import grading, review

NOTEBOOKS = {p.name: json.loads(p.read_text()) for p in E.notebook_paths()}
EXERCISES = {ex.ident: ex for nb in NOTEBOOKS.values() for ex in E.notebook_exercises(nb).values()}


def _manual() -> set:
    marked = set()
    for nb in NOTEBOOKS.values():
        marked.update(E.grade_by_hand(copy.deepcopy(nb)))
    return marked


OPEN = _manual()

# Each answer is a tuple of replacements, one per solution region of the answer cell, in order (None keeps
# the solution of that region). Code is written unindented; it takes the indentation of its region.

SHORTCUTS = {  # exercise -> answers that avoid the skill (the first is the one the prompt names)
    "01-1": [("""
        import re
        from geodepth_lite.data import manifest
        my_fields = {}
        for letter, edit in edits.items():
            try:
                manifest.load_manifest("scenario_smoke", edit)
            except ValueError as err:
                my_fields[letter] = re.search(r"(?:field|key|split) '([^']+)'", str(err)).group(1)
        """,)],
    "01-2": [("""
        my_report = integrity.verify(root)
        my_counts = integrity.frame_counts(root, m)
        """,)],
    "01-3": [("""  # meets the visible check (a > 0) only: the sign of a is lost
        xn, yn = camera.normalized_grid(K, height, width).numpy()
        q = xn * xn + yn * yn
        half_b = abs(a) * xn
        return (half_b + np.sqrt(half_b * half_b + q * (radius * radius - a * a))) / q
        """,)],
    "02-1": [("""
        from geodepth_lite.core import model as M
        _shapes = M.feature_shapes(M.DepthNet().eval(), 64, 96)
        my_encoder, my_decoder = _shapes["encoder"], _shapes["decoder"]
        my_heights_250, my_failing_scale = [125, 63, 32, 16, 8], 2
        """,), ("""
        import torch
        from geodepth_lite.core import model as M
        my_encoder = [(64, 32, 48), (64, 16, 24), (128, 8, 12), (256, 4, 6), (512, 2, 3)]
        my_decoder = [(256, 4, 6), (128, 8, 12), (64, 16, 24), (32, 32, 48), (16, 64, 96)]
        _e = M.ResNet18Encoder().eval()
        with torch.no_grad():
            _f = [_e.relu(_e.bn1(_e.conv1(torch.zeros(1, 3, 250, 64))))]
            _f.append(_e.layer1(_e.maxpool(_f[0])))
            for _layer in (_e.layer2, _e.layer3, _e.layer4):
                _f.append(_layer(_f[-1]))
        my_heights_250, my_failing_scale = [f.shape[-2] for f in _f], 2
        """,)],
    "02-2": [("""
        from geodepth_lite.core import model as M
        return M.count_parameters(M.DepthDecoder(enc_ch, dec_ch))
        """, """
        from geodepth_lite.core import model as M
        my_sab_params = M.count_parameters(M.SpatialAttention())
        """), (None, """  # a module of torch's own is a module too
        import torch
        my_sab_params = sum(p.numel() for p in torch.nn.Conv2d(2, 1, 7, bias=False).parameters())
        """)],
    "02-3": [("""
        from geodepth_lite.core import model as M
        block = M.SpatialAttention(kernel_size=weight.shape[-1])
        with torch.no_grad():
            block.conv.weight.copy_(weight)
        return block(x)
        """,)],
    "03-1": [("""  # meets the visible check (sections 1, 3 and 5) only
        offset_blind = {"grad", "normal"}
        """,)],
    "03-2": [("""
        from geodepth_lite.core import losses
        return losses.smoothness_loss(pred, image)
        """,), ("""  # the function smoothness_loss delegates to
        from geodepth_lite.core import losses
        sx, sy = losses.smoothness_maps(pred, image)
        return sx.mean() + sy.mean()
        """,)],
    "03-3": [("""
        import torch
        from geodepth_lite.core import camera, sdf
        D = torch.full((H, W), float(d), dtype=torch.float64)
        points = camera.backproject(D, K).reshape(-1, 3)
        return sdf.signed_distance(points, torch.as_tensor(q), depth=D, K=K).numpy()
        """,)],
    "04-1": [("""
        n_valid = int(metrics.eval_mask(gt).sum())
        ratio = float(metrics.compute_depth_metrics(pred, gt)["ratios"][0])
        """,)],
    "04-2": [("""
        from geodepth_lite.core import metrics
        return metrics.compute_depth_metrics(pred, gt)
        """,), ("""  # the solution's loop, with the package's per-frame metrics
        from geodepth_lite.core import metrics
        for p, g in zip(pred, gt):
            with np.errstate(invalid="ignore"):
                keep = np.isfinite(g) & (g > 1e-3) & (g < 100.0)
            if keep.any():
                g, p = g[keep], p[keep]
                per_frame.append(metrics.frame_metrics(np.clip(p * np.median(g) / np.median(p), 1e-3, 100.0), g))
        return {key: float(np.mean([f[key] for f in per_frame])) for key in per_frame[0]}
        """,)],
    "04-3": [("""
        spec = losses.LossSpec(lambdas=lambdas, depth_term="silog", border_weight=2.0,
                               sdf=losses.SDFOptions(grid=sdf_grid))
        return losses.total_loss(pred, gt, image, K, spec)[0]
        """,)],
    "05-1": [("""
        from geodepth_lite.evaluation import ablation
        _res = {"seeds": [0, 1, 2], "scores": {}}
        for _s in range(3):
            _res["scores"][(1, _s)] = {"test split": {"rmse": float(CASE1[_s])}}
            _res["scores"][(3, _s)] = {"test split": {"rmse": float(CASE3[_s])}}
        _q = ablation.paired(_res, "rmse", "test split", 3, level=LEVEL)
        r, rel, p, rel_low, rel_high = _q["rel_diffs"], _q["rel"], _q["p"], _q["rel_low"], _q["rel_high"]
        """,)],
    "05-2": [("""
        from geodepth_lite.evaluation import ablation
        return ablation.holm(pvalues, alpha)
        """,)],
    "05-3": [("""
        verdicts = {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(toy_result)}
        """,)],
    "06-1": [("""
        from geodepth_lite.evaluation import border
        bands, ratios = border.border_bands(np.nan_to_num(abs_mean) * count, count)
        worst = max(ratios, key=ratios.get)
        """,)],
    "06-2": [("""
        from geodepth_lite.evaluation import evaluate
        _rows = [dict(metrics.compute_depth_metrics(p, g), organ=o) for g, p, o in zip(test_gt, test_pred, test_organ)]
        _colon = evaluate.summarize(_rows, by="organ")["colon"]
        _held = evaluate.summarize([metrics.compute_depth_metrics(p, g) for g, p in zip(heldout_gt, heldout_pred)])
        change_abs_rel = 100 * (_held["abs_rel"] / _colon["abs_rel"] - 1)
        change_rmse = 100 * (_held["rmse"] / _colon["rmse"] - 1)
        """,)],
    "07-1": [("""
        from geodepth_lite.core import camera
        depth = np.full((int(v) + 1, int(u) + 1), float(z))
        return camera.backproject(depth, np.asarray(K, dtype=float))[int(v), int(u)]
        """,)],
    "07-2": [("""  # meets the visible check (square pixels) only: fx serves for y too
        v, u = np.nonzero(depth > 0)
        z = depth[v, u]
        x, y = z * (u - K[0, 2]) / K[0, 0], z * (v - K[1, 2]) / K[0, 0]
        (c1, c2, c3), *_ = np.linalg.lstsq(np.column_stack([x, y, np.ones_like(x)]), x * x + y * y, rcond=None)
        return float(np.sqrt(c3 + c1 * c1 / 4 + c2 * c2 / 4)), float(c1 / 2), float(c2 / 2)
        """,)],
    "07-3": [("""
        from geodepth_lite.views import recon
        frame_ratios = recon.median_scale_ratios(pred_frames, gt_frames)
        ratio_cv = float(np.std(frame_ratios) / np.mean(frame_ratios))
        """,)],
}

WRONG = {  # exercise -> a plausible mistake that the visible check rejects
    "01-1": ("""  # the edited field, not the one the error names
        my_fields = {"a": "camera.fov_x_deg", "b": "camera.near", "c": "camera.focal",
                     "d": "organ_presets.colon.fold_depth", "e": "splits.validation", "f": "camera_path.views"}
        """,),
    "01-2": ("""  # an image copied over itself has a new date, not new contents
        my_report = ["changed: manifest.json", "changed: train/depth/000001.npy", "changed: train/rgb/000000.png",
                     "missing: test/depth/000000.npy"]
        my_counts = {"train": (2, 2), "test": (0, 1)}
        """,),
    "01-3": ("""  # the on-axis formula
        xn, yn = camera.normalized_grid(K, height, width).numpy()
        return radius / np.hypot(xn, yn)
        """,),
    "01-4": ("""  # cap and cup swapped
        xn, yn = camera.normalized_grid(K, height, width).numpy()
        bowl = {"cap": -(xn**2 + yn**2), "cup": xn**2 + yn**2, "ridge": xn**2, "saddle": xn**2 - yn**2}[kind]
        return 2.0 + 0.8 * bowl
        """,),
    "02-1": ("""  # the max pooling without its padding
        my_encoder = [(64, 32, 48), (64, 16, 24), (128, 8, 12), (256, 4, 6), (512, 2, 3)]
        my_decoder = [(256, 4, 6), (128, 8, 12), (64, 16, 24), (32, 32, 48), (16, 64, 96)]
        my_heights_250, my_failing_scale = [125, 62, 31, 16, 8], 1
        """,),
    "02-2": ("""  # BatchNorm's weight and bias forgotten
        total = 9 * dec_ch[0] + 1
        for i in range(4, -1, -1):
            c_from_below = enc_ch[4] if i == 4 else dec_ch[i + 1]
            c_skip = enc_ch[i - 1] if i > 0 else 0
            total += 9 * c_from_below * dec_ch[i] + 9 * (dec_ch[i] + c_skip) * dec_ch[i]
        return total
        """, None),
    "02-3": ("""  # the two pooled maps in the wrong order
        pooled = torch.cat([x.max(dim=1, keepdim=True).values, x.mean(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(F.conv2d(pooled, weight, padding=weight.shape[-1] // 2))
        """,),
    "02-4": ("""  # padded at the bottom and right...
        H, W = image.shape[-2:]
        return F.pad(image, (0, (-W) % 32, 0, (-H) % 32), mode="reflect")
        """, """  # ...but cropped from the middle
        top, left = (depth.shape[-2] - height) // 2, (depth.shape[-1] - width) // 2
        return depth[..., top:top + height, left:left + width]
        """),
    "03-1": ("""  # only what section 3 says outright
        offset_blind = {"grad"}
        """,),
    "03-2": ("""  # the colour differences summed over the channels, not averaged
        ix = (image[..., :, 1:] - image[..., :, :-1]).abs().sum(dim=1, keepdim=True)
        iy = (image[..., 1:, :] - image[..., :-1, :]).abs().sum(dim=1, keepdim=True)
        dx = pred[..., :, 1:] - pred[..., :, :-1]
        dy = pred[..., 1:, :] - pred[..., :-1, :]
        return (torch.exp(-ix) * dx).pow(2).mean() + (torch.exp(-iy) * dy).pow(2).mean()
        """,),
    "03-3": ("""  # the fallback sign rule everywhere
        col = np.clip(np.rint(fx * q[:, 0] / d + cx), 0, W - 1)
        row = np.clip(np.rint(fy * q[:, 1] / d + cy), 0, H - 1)
        nearest = np.column_stack((d * (col - cx) / fx, d * (row - cy) / fy, np.full(len(q), float(d))))
        to_wall = nearest - q
        return np.sign(np.einsum("ij,ij->i", to_wall, nearest)) * np.linalg.norm(to_wall, axis=1)
        """,),
    "03-4": ("""  # a smaller scale error: better for every loss, the normal loss included
        pred = 1.05 * gt
        why = "A smaller scale error than the reference is better for the depth and gradient losses."
        """,),
    "04-1": ("""  # means instead of medians
        scored = np.isfinite(gt) & (gt > 1e-3) & (gt < 100.0)
        n_valid = int(scored.sum())
        ratio = float(np.mean(gt[scored]) / np.mean(pred[scored]))
        """,),
    "04-2": ("""  # the scaled prediction not clamped
        for p, g in zip(pred, gt):
            with np.errstate(invalid="ignore"):
                keep = np.isfinite(g) & (g > 1e-3) & (g < 100.0)
            if not keep.any():
                continue
            g, p = g[keep], p[keep]
            p = p * np.median(g) / np.median(p)
            worst = np.maximum(g / p, p / g)
            per_frame.append({"abs_rel": np.mean(np.abs(g - p) / g), "sq_rel": np.mean((g - p) ** 2 / g),
                              "rmse": np.sqrt(np.mean((g - p) ** 2)),
                              "rmse_log": np.sqrt(np.mean((np.log(g) - np.log(p)) ** 2)),
                              "a1": np.mean(worst < 1.25), "a2": np.mean(worst < 1.25 ** 2),
                              "a3": np.mean(worst < 1.25 ** 3)})
        return {key: float(np.mean([f[key] for f in per_frame])) for key in per_frame[0]}
        """,),
    "04-3": ("""  # the border weight forgotten
        group1 = losses.silog_depth_loss(pred, gt) + losses.smoothness_loss(pred, image)
        group2 = losses.gradient_loss(pred, gt) + losses.normal_loss(pred, gt)
        return lambda1 * group1 + lambda2 * group2 + lambda3 * losses.sdf_loss(pred, gt, K,
                                                                               losses.SDFOptions(grid=sdf_grid))
        """,),
    "04-4": ("""  # the perfect prediction: better in both metrics
        pred = gt.copy()
        why = "A perfect prediction has no error at all, so it should be better than the constant one."
        """,),
    "05-1": ("""  # a 95% interval instead of the level LEVEL
        r = 100 * (CASE3 / CASE1 - 1)
        rel = r.mean()
        se = r.std(ddof=1) / np.sqrt(r.size)
        p = 2 * stats.t.sf(abs(rel / se), r.size - 1)
        half = stats.t.ppf(0.975, r.size - 1) * se
        rel_low, rel_high = rel - half, rel + half
        """,),
    "05-2": ("""  # no stopping rule: every p-value against its own level
        pv = np.asarray(pvalues, dtype=float)
        m = pv.size
        rejected = np.zeros(m, dtype=bool)
        for k, i in enumerate(np.argsort(pv, kind="stable")):
            rejected[i] = pv[i] <= alpha / (m - k)
        return [bool(x) for x in rejected]
        """,),
    "05-3": ("""  # Holm's rule over each metric separately
        verdicts = {}
        for metric in ("abs_rel", "rmse"):
            keys = [(metric, c) for c in (2, 3, 4)]
            comps = {k: ablation.paired(toy_result, k[0], "test split", k[1], level=1 - 0.05 / 6) for k in keys}
            for k, d in zip(keys, ablation.holm([comps[k]["p"] for k in keys], 0.05)):
                verdicts[k] = ablation.size_verdict(comps[k]["rel_low"], comps[k]["rel_high"], comps[k]["rel"],
                                                    ablation.PAPER_REDUCTION[k[1]][k[0]], d)
        """,),
    "05-4": ("""  # a one-sided test
        return float(stats.nct.sf(stats.t.ppf(1 - alpha, n - 1), n - 1, effect * np.sqrt(n) / sd))
        """, None, None),
    "06-1": ("""  # rows and columns swapped
        bh, bw = max(1, round(0.1 * W)), max(1, round(0.1 * H))
        regions = {"top": (slice(0, bh), slice(None)), "bottom": (slice(H - bh, H), slice(None)),
                   "left": (slice(None), slice(0, bw)), "right": (slice(None), slice(W - bw, W)),
                   "centre": (slice(H // 4, H - H // 4), slice(W // 4, W - W // 4))}
        err_sum = np.nan_to_num(abs_mean) * count
        bands = {k: err_sum[s].sum() / count[s].sum() for k, s in regions.items()}
        ratios = {k: bands[k] / bands["centre"] for k in ("top", "bottom", "left", "right")}
        worst = max(ratios, key=ratios.get)
        """,),
    "06-2": ("""  # against the whole test split, not its colon frames
        _ref = metrics.compute_depth_metrics(np.stack(test_pred), np.stack(test_gt))
        _grp = metrics.compute_depth_metrics(np.stack(heldout_pred), np.stack(heldout_gt))
        change_abs_rel = 100 * (_grp["abs_rel"] / _ref["abs_rel"] - 1)
        change_rmse = 100 * (_grp["rmse"] / _ref["rmse"] - 1)
        """,),
    "06-3": ("""  # both view kinds with a hard right border: the pooled map shows it
        abs_err = np.full((4, 20, 20), 0.1)
        abs_err[:, :, 18:] = 0.2
        views = ["wall", "wall", "lumen", "lumen"]
        """,),
    "07-1": ("""  # u and v swapped
        fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
        return np.array([z * (v - cx) / fx, z * (u - cy) / fy, z], dtype=float)
        """,),
    "07-2": ("""  # the invalid pixels kept
        pts = camera.backproject(np.asarray(depth, dtype=float), K).reshape(-1, 3)
        x, y = pts[:, 0], pts[:, 1]
        (c1, c2, c3), *_ = np.linalg.lstsq(np.column_stack([x, y, np.ones_like(x)]), x * x + y * y, rcond=None)
        return float(np.sqrt(c3 + c1 * c1 / 4 + c2 * c2 / 4)), float(c1 / 2), float(c2 / 2)
        """,),
    "07-3": ("""  # the sample standard deviation
        frame_ratios = np.array([np.median(g[g > 0]) / np.median(q[g > 0]) for g, q in zip(gt_frames, pred_frames)])
        ratio_cv = float(np.std(frame_ratios, ddof=1) / np.mean(frame_ratios))
        """,),
    "07-4": ("""  # the ratio used as the factor that multiplies the prediction
        ramp = np.arange(len(gts), dtype=float)
        wanted = 1.0 + cv * (ramp - ramp.mean()) / ramp.std()
        return [np.asarray(g, dtype=float) * r for g, r in zip(gts, wanted)]
        """,),
}

PLACEHOLDERS = {  # open-ended exercise -> an answer that fills in the blanks with nothing of substance
    "01-4": ("return np.full((height, width), 2.0)",),
    "02-4": ("return torch.zeros(image.shape[0], 3, -(-image.shape[-2] // 32) * 32, -(-image.shape[-1] // 32) * 32)",
             "return torch.zeros(depth.shape[0], 1, height, width)"),
    "03-4": ('pred, why = gt.clone(), ""',),
    "04-4": ('pred, why = np.ones((8, 8)), ""',),
    "05-4": ("return 0.0", "return 2", "n_plan = 2"),
    "06-3": ('abs_err, views = np.ones((4, 10, 10)), ["wall", "wall", "lumen", "lumen"]',),
    "07-4": ("return [np.asarray(g, dtype=float).copy() for g in gts]",),
}


def answer_with(answer: str, replacements) -> str:
    """The answer cell with its solution regions replaced, in order (None keeps a region's solution); the
    markers go, as in a student's notebook."""
    out, region, inside = [], -1, False
    for line in answer.splitlines(keepends=True):
        stripped = line.strip()
        if stripped == E.SOLUTION_MARKERS[0]:
            region, inside = region + 1, True
            code = replacements[region] if region < len(replacements) else None
            if code is not None:
                indent = line[: len(line) - len(line.lstrip())]
                note, _, body = code.partition("\n")  # a note on the opening line: what the answer is
                text = (note.strip() + "\n" if note.strip() else "") + textwrap.dedent(body).strip("\n") + "\n"
                out.append(textwrap.indent(text, indent))
            continue
        if stripped == E.SOLUTION_MARKERS[1]:
            inside = False
            continue
        code = replacements[region] if inside and region < len(replacements) else None
        if not inside or code is None:
            out.append(line)
    assert region + 1 == len(replacements), f"{region + 1} solution regions, {len(replacements)} replacements"
    return "".join(out)


def outcome(answer: str, check: str) -> BaseException | None:
    """What running the answer then the check raises (None: the check passes)."""
    try:
        E.run_exercise(answer, check)
    except Exception as exc:  # noqa: BLE001 - reported by the callers
        return exc
    return None


def outcome_in(namespace: dict, answer: str, check: str) -> BaseException | None:
    """What running the answer then the check raises in ``namespace`` (None: the check passes)."""
    try:
        with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp):
            E.run_cell(answer, namespace, "<answer>")
            E.run_cell(check, namespace, "<check>")
    except Exception as exc:  # noqa: BLE001 - reported by the callers
        return exc
    return None


def _ids():
    return sorted(EXERCISES)


def test_every_exercise_has_its_answers():
    """A new exercise needs a wrong answer, and a shortcut (or, open-ended, a placeholder)."""
    assert len(EXERCISES) >= 27
    missing = [i for i in EXERCISES if i not in WRONG or (i not in SHORTCUTS and i not in PLACEHOLDERS)]
    assert not missing, f"exercises without their answers in this file: {missing}"
    assert set(PLACEHOLDERS) == OPEN, "the placeholders are for the open-ended (hand-graded) exercises"
    assert set(SHORTCUTS) | OPEN == set(EXERCISES) and not set(WRONG) - set(EXERCISES)


@pytest.mark.parametrize("ident", _ids())
def test_shortcut_and_wrong_answer_lose_the_points(ident):
    ex = EXERCISES[ident]
    assert ident in WRONG, f"exercise {ident}: add a wrong answer (and a shortcut or placeholder) to this file"
    visible = E.visible_check(ex.check)
    assert outcome(ex.answer, ex.check) is None, f"{ident}: the solution fails its own check"

    wrong = outcome(answer_with(ex.answer, WRONG[ident]), visible)
    assert isinstance(wrong, AssertionError), f"{ident}: the visible check does not reject the wrong answer ({wrong!r})"

    for shortcut in SHORTCUTS.get(ident, []):
        answer = answer_with(ex.answer, shortcut)
        assert outcome(answer, visible) is None, f"{ident}: the shortcut is no threat, the visible check rejects it"
        failed = outcome(answer, ex.check)
        assert isinstance(failed, AssertionError), f"{ident}: the full check passes the shortcut ({failed!r})"
        if not any("meets the visible check" in (code or "") for code in shortcut):  # it calls what is forbidden
            assert isinstance(failed, grading.ForbiddenCall), f"{ident}: failed for another reason: {failed!r}"
            assert str(failed).startswith("this exercise asks you to ") and "is not allowed" in str(failed)


@pytest.mark.parametrize("ident", sorted(OPEN))
def test_open_ended_exercises_are_graded_by_hand_and_reject_a_placeholder(ident):
    ex = EXERCISES[ident]
    nb = copy.deepcopy(next(nb for nb in NOTEBOOKS.values() if ident in E.notebook_exercises(nb)))
    assert ident in E.grade_by_hand(nb)
    graded = E.notebook_exercises(nb)[ident]
    answer, check = graded.cells["answer"]["metadata"]["nbgrader"], graded.cells["check"]["metadata"]["nbgrader"]
    assert check["points"] == 0 and answer["points"] == ex.points > 0 and answer["grade"] and answer["solution"]
    placeholder = outcome(answer_with(ex.answer, PLACEHOLDERS[ident]), E.visible_check(ex.check))
    assert isinstance(placeholder, AssertionError), f"{ident}: the placeholder is not rejected ({placeholder!r})"


def test_an_explanation_of_mere_words_earns_no_points_automatically():
    """03-4 and 04-4 ask for an explanation: a string of eight words still passes their check cells (which
    only ask that one is there), but those cells carry no points in the course; a person grades the answer."""
    for ident in ("03-4", "04-4"):
        ex = EXERCISES[ident]
        words = ex.answer.replace("why = (", 'why = "x x x x x x x x"\n_unused = (', 1)
        assert outcome(words, ex.check) is None
        assert ident in OPEN


# ------------------------------------------------------------------------------------------ grading.forbid
def test_forbid_replaces_every_binding_and_restores_them():
    from geodepth_lite.evaluation import ablation, study

    original = ablation.holm
    namespace = {"holm_alias": ablation.holm, "other": len}
    with grading.forbid(ablation.holm, task="write holm yourself", namespace=namespace):
        for call in (lambda: ablation.holm([0.01]), lambda: namespace["holm_alias"]([0.01]),
                     lambda: study.ablation.holm([0.01])):
            with pytest.raises(grading.ForbiddenCall, match=r"^this exercise asks you to write holm yourself; "
                               r"calling geodepth_lite\.evaluation\.ablation\.holm is not allowed$"):
                call()
        assert namespace["other"] is len
    assert ablation.holm is original and namespace["holm_alias"] is original and ablation.holm([0.01]) == [True]
    assert sys.getprofile() is None


def test_forbid_catches_a_reference_taken_before_the_block():
    from geodepth_lite.evaluation import ablation

    def sneaky(p, _kept=ablation.holm):  # a default argument keeps the original function
        return _kept(p)

    with grading.forbid(ablation.holm, task="write holm yourself"):
        with pytest.raises(grading.ForbiddenCall):
            sneaky([0.01])
    assert sneaky([0.2]) == [False]


def test_forbid_a_class_stops_building_and_running_it_and_a_module_stops_all_its_functions():
    import torch

    from geodepth_lite.core import losses
    from geodepth_lite.core import model as M

    built = M.SpatialAttention(3)
    x = torch.rand(1, 2, 4, 4)
    with grading.forbid(M.SpatialAttention, task="write the block yourself"):
        with pytest.raises(grading.ForbiddenCall, match="building geodepth_lite.core.model.SpatialAttention"):
            M.SpatialAttention(3)
        with pytest.raises(grading.ForbiddenCall, match="SpatialAttention.forward"):
            built(x)
    with grading.forbid(losses, task="use torch only"):
        with pytest.raises(grading.ForbiddenCall, match="smoothness_maps"):
            losses.smoothness_maps(torch.rand(1, 1, 4, 4), torch.rand(1, 3, 4, 4))
    assert built(x).shape == x.shape and float(losses.grad_x(torch.ones(1, 1, 2, 2)).abs().sum()) == 0


def test_rerun_answer_needs_the_history_and_every_name_set_again():
    with pytest.raises(AssertionError, match="cannot find the answer cell"):
        grading.rerun_answer({}, ["x"])
    namespace = E.new_namespace()
    E.run_cell("x = 1\nprint('hidden')", namespace)
    E.run_cell("pass", namespace)
    assert grading.rerun_answer(namespace, ["x"])["x"] == 1
    E.run_cell("z = 3", namespace)  # the cell before the check does not set y
    E.run_cell("pass", namespace)
    with pytest.raises(AssertionError, match="does not set y"):
        grading.rerun_answer(namespace, ["y"])


def test_rerun_answer_in_a_kernel_without_history_runs_nothing_and_with_history_needs_the_cell(monkeypatch):
    """nbval runs cells with store_history=False: the execution count stays 1 and nothing is run again;
    a kernel that counts its cells but lost the answer cell from its history fails the check."""
    from types import SimpleNamespace

    shell = SimpleNamespace(execution_count=1, history_manager=SimpleNamespace(input_hist_parsed=[""]))
    monkeypatch.setattr(grading, "_shell", lambda: shell)
    assert grading.rerun_answer({"x": 1}, ["x"]) == {"x": 1}
    shell.execution_count = 7
    with pytest.raises(AssertionError, match="cannot find the answer cell"):
        grading.rerun_answer({"x": 1}, ["x"])
    shell.history_manager.input_hist_parsed += ["x = 2", "check"]
    assert grading.rerun_answer({"In": []}, ["x"])["x"] == 2


# Correct answers written with ``@torch.no_grad()``: the decorator's wrapper is the same code for every
# function it decorates, the package's forbidden ones among them, so the guard must not watch it.
NO_GRAD_ANSWERS = {
    "02-1": ("""
        import torch


        @torch.no_grad()
        def _out(h, k, s, p):  # floor((h + 2p - k) / s) + 1
            return (h + 2 * p - k) // s + 1


        my_encoder = [(64, 32, 48), (64, 16, 24), (128, 8, 12), (256, 4, 6), (512, 2, 3)]
        my_decoder = [(256, 4, 6), (128, 8, 12), (64, 16, 24), (32, 32, 48), (16, 64, 96)]
        my_heights_250 = [_out(250, 7, 2, 3)]
        my_heights_250.append(_out(my_heights_250[-1], 3, 2, 1))
        for _ in range(3):
            my_heights_250.append(_out(my_heights_250[-1], 3, 2, 1))
        my_failing_scale = 2
        """,),
    "03-3": ("""
        import torch


        @torch.no_grad()
        def _nearest_lattice_point(q):
            col = np.clip(np.rint(fx * q[:, 0] / d + cx), 0, W - 1)
            row = np.clip(np.rint(fy * q[:, 1] / d + cy), 0, H - 1)
            return np.column_stack((d * (col - cx) / fx, d * (row - cy) / fy, np.full(len(q), float(d))))


        nearest = _nearest_lattice_point(q)
        to_wall = nearest - q
        fallback = np.sign(np.einsum("ij,ij->i", to_wall, nearest))
        z_safe = np.where(q[:, 2] > 0, q[:, 2], 1.0)
        u_seen = np.rint(fx * q[:, 0] / z_safe + cx)
        v_seen = np.rint(fy * q[:, 1] / z_safe + cy)
        seen = (q[:, 2] > 0) & (u_seen >= 0) & (u_seen <= W - 1) & (v_seen >= 0) & (v_seen <= H - 1)
        return np.where(seen, np.sign(d - q[:, 2]), fallback) * np.linalg.norm(to_wall, axis=1)
        """,),
}


@pytest.mark.parametrize("ident", sorted(NO_GRAD_ANSWERS))
def test_a_correct_answer_decorated_with_no_grad_passes_the_full_check(ident):
    """02.1 and 03.3 forbid package functions that are themselves decorated with ``@torch.no_grad()``."""
    ex = EXERCISES[ident]
    answer = answer_with(ex.answer, NO_GRAD_ANSWERS[ident])
    assert "@torch.no_grad()" in answer
    assert outcome(answer, ex.check) is None


def test_forbid_still_catches_a_kept_reference_to_a_decorated_function():
    """The guard watches the code the decorator wraps: a reference to a forbidden ``@torch.no_grad()``
    function taken before the block still fails inside it, and an own decorated function runs."""
    import torch

    from geodepth_lite.core import model as M

    kept = M.feature_shapes

    @torch.no_grad()
    def own(x):
        return x + 1

    with grading.forbid(M.feature_shapes, task="work out the shapes"):
        with pytest.raises(grading.ForbiddenCall, match="calling geodepth_lite.core.model.feature_shapes"):
            kept(None, 64, 96)
        assert float(own(torch.ones(1))) == 2.0


# ------------------------------------------------------------------------------ a student who shares the kernel
# The student's answer and the checks run in one process. Every family of shortcut that this allows is played
# against an exercise of every kind: a function to write (05.2 Holm's rule; 02.2 where it returns a value), a
# value to compute (05.3's verdicts), a set (03.1) and an open answer graded by hand (04.4). Each either loses
# its points (the checks, exact types included, reject it) or is flagged by the static review
# (``review.review_notebook``, as ``course autograde`` runs it), which sends the exercise to manual grading.
KINDS = {"function": {"05-2", "02-2", "07-2"}, "value": {"05-3", "06-1"}, "set": {"03-1"}, "open": {"04-4"}}
FAMILIES = ("grader's files", "guard off", "out of the guard's sight", "package source", "equal to anything",
            "pasted values", "fished reference", "edited history", "the checks' tools or inputs changed")
def _pasted_verdicts() -> str:
    """05.3's verdicts as the visible check's message prints them after a failed run."""
    from geodepth_lite.evaluation import ablation

    namespace = E.new_namespace()
    E.run_cell(answer_with(EXERCISES["05-3"].answer, ("verdicts = {}",)), namespace)
    want = {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(namespace["toy_result"])}
    return f"verdicts = {want!r}"


FAMILY_SHORTCUTS = {  # (family, kind) -> (exercise, its answer's regions, the rule that flags it; None: it fails)
    ("grader's files", "function"): ("05-2", ("""
        import sqlite3
        with sqlite3.connect("../../../gradebook.db") as db:  # the hidden tests' text
            rows = db.execute("select source from grade_cells").fetchall()
        return [bool(p <= alpha) for p in pvalues]
        """,), "grader-files"),
    ("guard off", "function"): ("05-2", ("""
        global _kept
        import sys
        from geodepth_lite.evaluation import ablation
        try:
            _kept
        except NameError:  # the first call, in the visible check, is not guarded
            _kept = [ablation.holm]  # in a list: the guard replaces the notebook's names bound to holm itself
        sys.setprofile(None)  # the guard's hook, watching the kept function's code, is gone
        return _kept[0](pvalues, alpha)
        """,), "guard"),
    ("out of the guard's sight", "function"): ("05-2", ("""
        global _kept
        from concurrent.futures import ThreadPoolExecutor
        from geodepth_lite.evaluation import ablation
        try:
            _kept
        except NameError:  # the first call, in the visible check, is not guarded
            _kept = [ablation.holm]  # in a list: the guard replaces the notebook's names bound to holm itself
        with ThreadPoolExecutor(1) as pool:  # the guard's hook watches its own thread only
            return pool.submit(_kept[0], pvalues, alpha).result()
        """,), "concurrency"),
    ("package source", "function"): ("05-2", ("""
        from geodepth_lite.evaluation import ablation
        copy = {}
        exec(open(ablation.__file__).read(), copy)  # a fresh copy of the module: its code is not watched
        return copy["holm"](pvalues, alpha)
        """,), "package-source"),
    ("equal to anything", "function"): ("02-2", ("""
        class Always(int):  # equal to whatever the check expects
            def __eq__(self, other):
                return True

            __hash__ = int.__hash__

        return Always(0)
        """, None), "special-method"),
    ("pasted values", "function"): ("05-2", ("""  # the visible check's cases, answered one by one
        seen = {(0.04,): [True], (0.2,): [False], (0.001, 0.02, 0.04): [True, True, True],
                (0.01, 0.04, 0.03, 0.005): [True, False, False, True], (0.03, 0.2, 0.006): [True, False, True],
                (0.012, 0.002, 0.3, 0.011): [False, True, False, False], (0.02, 0.02, 0.02): [False, False, False]}
        return seen.get(tuple(pvalues), [False] * len(pvalues))
        """,), None),
    ("fished reference", "function"): ("05-2", ("""
        import sys
        return list(sys._getframe(1).f_globals.get("_want", []))  # the hidden test's expected answer
        """,), "introspection"),
    ("edited history", "function"): ("02-2", (None, """
        from geodepth_lite.core import model as M
        my_sab_params = M.count_parameters(M.SpatialAttention())
        In[-1] = In[-1].replace("M.count_parameters(M.SpatialAttention())", str(my_sab_params))  # run again
        """), "kernel-history"),
    ("grader's files", "value"): ("05-3", ("""
        import json
        with open("../../../source/05_statistics/05_statistics.ipynb") as f:  # the lecturer's solution
            _solution = json.load(f)
        verdicts = {}
        """,), "grader-files"),
    ("guard off", "value"): ("05-3", ("""
        try:
            _kept
        except NameError:  # the first run, before the hidden test, is not guarded
            _kept = [ablation.comparisons]
        import sys
        ablation.comparisons = _kept[0]  # put back what the guard replaced
        sys.setprofile(None)
        verdicts = {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(toy_result)}
        """,), "guard"),
    ("out of the guard's sight", "value"): ("05-3", ("""
        try:
            _kept
        except NameError:  # the first run, before the hidden test, is not guarded
            _kept = [ablation.comparisons]
        import threading
        _out = {}
        _t = threading.Thread(target=lambda: _out.update({(m, c): q["verdict"] for _, m, c, q in _kept[0](toy_result)}))
        _t.start()
        _t.join()
        verdicts = _out
        """,), "concurrency"),
    ("package source", "value"): ("05-3", ("""
        import inspect
        _copy = {}
        exec(inspect.getsource(ablation), _copy)  # the module rebuilt from its source
        verdicts = {(m, c): q["verdict"] for _, m, c, q in _copy["comparisons"](toy_result)}
        """,), "introspection"),
    ("equal to anything", "value"): ("05-3", ("""
        class Word(str):  # equal to whatever verdict the check expects
            def __eq__(self, other):
                return True

            def __ne__(self, other):
                return False

            __hash__ = str.__hash__


        verdicts = {(m, c): Word("no effect detected") for m in ("abs_rel", "rmse") for c in (2, 3, 4)}
        """,), "special-method"),
    ("pasted values", "value"): ("05-3", ("PASTED",), "literal-answer"),
    ("fished reference", "value"): ("05-3", ("""
        verdicts = dict(globals().get("_want", {}))  # the visible check's reference, there when the cell runs again
        """,), "namespace"),
    ("edited history", "value"): ("05-3", ("""
        verdicts = {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(toy_result)}
        In[-1] = f"verdicts = {verdicts!r}"  # the hidden test runs this again, not the call
        """,), "kernel-history"),
    ("grader's files", "set"): ("03-1", ("""
        try:
            _tests = open("../../../gradebook.db", "rb").read()  # the hidden tests, to read the set off
        except OSError:
            _tests = b""
        offset_blind = {"smooth", "grad", "normal"}
        """,), "grader-files"),
    ("guard off", "set"): ("03-1", ("""
        import sys
        sys.settrace(None)
        offset_blind = {"smooth", "grad", "normal"}
        """,), "guard"),
    ("out of the guard's sight", "set"): ("03-1", ("""
        import subprocess
        import sys
        _code = "from geodepth_lite.core import losses; print(losses.term_names())"
        _names = subprocess.run([sys.executable, "-c", _code], capture_output=True, text=True).stdout
        offset_blind = {"smooth", "grad", "normal"}
        """,), "concurrency"),
    ("package source", "set"): ("03-1", ("""
        from pathlib import Path
        from geodepth_lite.core import losses
        _text = Path(losses.__file__).read_text()  # which terms read neighbouring differences only
        offset_blind = {name for name in ("smooth", "grad", "normal") if name in _text}
        """,), "package-source"),
    ("equal to anything", "set"): ("03-1", ("""
        class AnySet(set):  # equal to whatever set the check expects
            def __eq__(self, other):
                return True

            __hash__ = None


        offset_blind = AnySet({"grad", "normal"})
        """,), "special-method"),
    ("pasted values", "set"): ("03-1", ("""  # the two terms the visible check's messages name
        offset_blind = {"grad", "normal"}
        """,), None),
    ("fished reference", "set"): ("03-1", ("""
        class Lazy(set):  # compares with the hidden test's own set
            def __eq__(self, other):
                return set(globals().get("_unchanged", self)) == set(other)

            __hash__ = None


        offset_blind = Lazy({"grad", "normal"})
        """,), "namespace"),
    ("edited history", "set"): ("03-1", ("""
        offset_blind = {"smooth", "grad", "normal"}
        _ih[-1] = "offset_blind = set()"
        """,), "kernel-history"),
    ("grader's files", "open"): ("04-4", ("""
        from pathlib import Path
        _theirs = Path("../../../submitted/ana/04_training/04_training.ipynb")  # another student's answer
        pred = np.full((8, 8), 1.5)
        why = "copied"
        """,), "grader-files"),
    ("guard off", "open"): ("04-4", ("""
        import sys
        sys.setprofile(None)
        pred = np.full((8, 8), 1.5)
        why = ""
        """,), "guard"),
    ("out of the guard's sight", "open"): ("04-4", ("""
        from multiprocessing import Pool
        pred = np.full((8, 8), 1.5)
        why = ""
        """,), "concurrency"),
    ("package source", "open"): ("04-4", ("""
        from pathlib import Path
        _metrics = Path("geodepth_lite/core/metrics.py").read_text()
        pred = np.full((8, 8), 1.5)
        why = ""
        """,), "package-source"),
    ("equal to anything", "open"): ("04-4", ("""
        class Score(float):
            def __gt__(self, other):
                return True
        pred = np.full((8, 8), 1.5)
        why = ""
        """,), "special-method"),
    ("pasted values", "open"): ("04-4", ("PASTED",), "literal-answer"),
    ("fished reference", "open"): ("04-4", ("""
        import sys
        pred = sys._getframe(0).f_globals.get("_p", np.ones((8, 8)))
        why = ""
        """,), "introspection"),
    ("edited history", "open"): ("04-4", ("""
        pred = np.full((8, 8), 1.5)
        why = " ".join(In)
        """,), "kernel-history"),
    ("the checks' tools or inputs changed", "function"): ("07-2", """
        _real_tube = tube_depth
        _asked = []


        def tube_depth(K, H, W, radius, a, b, far=30.0):  # the check's test data, recorded as it is made
            _asked.append((radius, a, b))
            return _real_tube(K, H, W, radius, a, b, far)


        def fit_tube(depth, K):
            return _asked[-1]
        """, "given-inputs"),
    ("the checks' tools or inputs changed", "value"): ("06-1", ("""
        bands = dict.fromkeys(["top", "bottom", "left", "right", "centre"], 1.0)
        ratios = dict.fromkeys(["top", "bottom", "left", "right"], 1.0)
        worst = "top"
        abs = lambda x: 0.0  # every difference the checks measure is 0
        max = lambda *args, **kwargs: "top"  # and the worst band is the one named
        """,), "shadowed-builtin"),
    ("the checks' tools or inputs changed", "set"): ("03-1", ("""
        def isinstance(obj, kind):
            return True


        offset_blind = {"grad", "normal"}
        """,), "shadowed-builtin"),
    ("the checks' tools or inputs changed", "open"): ("04-4", ("""
        float = lambda x: 1.0
        pred = np.full((8, 8), 1.5)
        why = ""
        """,), "shadowed-builtin"),
}


def _pasted(family_kind) -> tuple:
    """The pasted answers, made as a student would: from what the visible check printed."""
    if family_kind == ("pasted values", "value"):
        return (_pasted_verdicts(),)
    namespace = E.new_namespace()  # 04.4: the solution's pred, written out number by number
    E.run_cell(solution("04-4"), namespace)
    return (f"pred = {namespace['pred'].tolist()!r}\nwhy = {namespace['why']!r}",)


def family_answer(family_kind) -> tuple[str, str, str | None]:
    ident, regions, rule = FAMILY_SHORTCUTS[family_kind]
    if isinstance(regions, str):  # code added after the solution, outside its regions
        return ident, solution(ident) + "\n" + textwrap.dedent(regions), rule
    if regions == ("PASTED",):
        regions = _pasted(family_kind)
    return ident, answer_with(EXERCISES[ident].answer, regions), rule


def solution(ident: str) -> str:
    """The exercise's answer cell as the solution answers it (its markers removed)."""
    return "\n".join(ln for ln in EXERCISES[ident].answer.splitlines() if ln.strip() not in E.SOLUTION_MARKERS)


def reviewed(ident: str, answer: str) -> list:
    """The static review of ``answer`` as exercise ``ident``'s answer cell, as ``course autograde`` runs it:
    the lecturer's notebook against the returned one."""
    from geodepth_lite.workbook import review

    name = next(n for n, nb in NOTEBOOKS.items() if ident in E.notebook_exercises(nb))
    returned = copy.deepcopy(NOTEBOOKS[name])
    E.notebook_exercises(returned)[ident].cells["answer"]["source"] = answer
    return review.review_notebook(NOTEBOOKS[name], returned).get(ident, [])


def test_every_family_of_shortcut_is_played_against_every_kind_of_exercise():
    assert set(FAMILY_SHORTCUTS) == {(f, k) for f in FAMILIES for k in KINDS}
    assert all(FAMILY_SHORTCUTS[f, k][0] in KINDS[k] for f, k in FAMILY_SHORTCUTS)
    assert KINDS["open"] <= OPEN and not (KINDS["function"] | KINDS["value"] | KINDS["set"]) & OPEN
    for ident in KINDS["function"]:  # a function to write: its solution region sits inside a def
        assert re.search(r"def \w+\(.*\):\n(.*\n)*?\s+### BEGIN SOLUTION", EXERCISES[ident].answer), ident
    assert "offset_blind = {" in solution("03-1")  # the set


@pytest.mark.parametrize("family, kind", sorted(FAMILY_SHORTCUTS))
def test_each_shortcut_loses_its_points_or_is_flagged_with_its_reason(family, kind):
    from geodepth_lite.workbook import review

    ident, answer, rule = family_answer((family, kind))
    found = reviewed(ident, answer)
    if rule is None:  # not flagged: the checks must take its points
        failed = outcome(answer, EXERCISES[ident].check)
        assert isinstance(failed, Exception) and ident not in OPEN, f"{ident}: {family} passes unflagged"
    else:
        assert rule in {f.rule for f in found}, f"{ident}: {family} not flagged as {rule}: {found}"
        assert all(f.text().endswith(review.RULES[f.rule]) and f.text().startswith(f"line {f.line}: ")
                   for f in found)


# the shortcuts that pass every check when run: without the review they would score silently
PASS_THE_CHECKS = [("guard off", "function"), ("out of the guard's sight", "function"), ("edited history", "function"),
                   ("guard off", "value"), ("edited history", "value"), ("pasted values", "value")]
# the shortcuts that once passed every check, and now pass the visible checks only: the answer keys fail them
# (06.1's and 03.1's by their exact types and values; 07.2's because its hidden tube is not made by tube_depth)
MISS_THE_KEYS = [("the checks' tools or inputs changed", "value"), ("equal to anything", "set"),
                 ("the checks' tools or inputs changed", "function")]


@pytest.mark.parametrize("family, kind", PASS_THE_CHECKS)
def test_the_flag_is_needed_where_the_shortcut_passes_the_checks(family, kind):
    ident, answer, rule = family_answer((family, kind))
    assert outcome(answer, EXERCISES[ident].check) is None and rule is not None
    assert sys.getprofile() is None  # the guard put back what the shortcut turned off


@pytest.mark.parametrize("family, kind", MISS_THE_KEYS)
def test_a_shortcut_that_passes_the_visible_checks_misses_the_answer_key(family, kind):
    ident, answer, rule = family_answer((family, kind))
    check = EXERCISES[ident].check
    assert outcome(answer, check.split("### BEGIN HIDDEN TESTS")[0]) is None and rule is not None
    assert isinstance(outcome(answer, check), AssertionError)


@pytest.mark.parametrize("family, kind", [("equal to anything", "function"), ("equal to anything", "value")])
def test_an_answer_equal_to_anything_fails_the_exact_types(family, kind, monkeypatch):
    """A subclass overriding ``==`` fails where the checks see the answer through the package (a function
    under ``grading.forbid``, a value through ``grading.rerun_answer``); without that type check each still
    fails its answer key (02.2's counts, 05.3's verdicts), which checks the exact types itself, and passes
    where the key's type check is taken out too."""
    ident, answer, _ = family_answer((family, kind))
    failed = outcome(answer, EXERCISES[ident].check)
    assert isinstance(failed, AssertionError) and "compare types as well as values" in str(failed), failed
    assert ("Always (a subclass of int)" if kind == "function" else "Word (a subclass of str)") in str(failed)
    monkeypatch.setattr(grading, "foreign_value", lambda value, budget=None: None)
    without = outcome(answer, EXERCISES[ident].check)
    assert isinstance(without, AssertionError) and "compare types" not in str(without), without
    typed = "_b.type(_n) is _b.int" if kind == "function" else "and _b.type(_v) is _b.str for _k, _v in"
    untyped = "True" if kind == "function" else "for _k, _v in"
    assert EXERCISES[ident].check.count(typed) == 1
    assert outcome(answer, EXERCISES[ident].check.replace(typed, untyped)) is None


def test_the_solutions_and_ordinary_constructs_pass_the_review_clean():
    from geodepth_lite.workbook import review

    assert {ident: reviewed(ident, solution(ident)) for ident in EXERCISES} == dict.fromkeys(EXERCISES, [])
    for ident, regions in NO_GRAD_ANSWERS.items():
        assert reviewed(ident, answer_with(EXERCISES[ident].answer, regions)) == [], ident
    ordinary = textwrap.dedent("""
        import math
        import numpy as np
        import torch
        import torch.nn.functional as F
        from scipy import signal, stats
        from geodepth_lite.core import camera, losses


        class Block(torch.nn.Module):
            def __init__(self, k):
                super().__init__()
                self.conv = torch.nn.Conv2d(2, 1, k, bias=False)

            def forward(self, x):
                return x * torch.sigmoid(self.conv(x))

            def __repr__(self):
                return f"{type(self).__name__}()"


        @torch.no_grad()
        def shade(x, K):
            grid = camera.normalized_grid(K, 4, 4)
            return [float(v) for v in F.relu(torch.as_tensor(x)).flatten()] + [math.pi, grid.shape[0]]


        with torch.no_grad():
            values = {k: np.mean(v) for k, v in {"a": [1.0, 2.0]}.items()}
        model = Block(3).eval()
        model.training = False
        table = {}
        table["x"] = stats.norm.ppf(0.5) + len(signal.windows.hann(4))
        """)
    assert review.review_cell(ordinary) == []


# each rule of the review: an answer it must flag, and a near miss (an honest answer much like it) it must not
GIVEN = review.given_inputs("CASE1 = np.array([1.0])\nr = None\n### BEGIN SOLUTION\nr = CASE1\n### END SOLUTION",
                            "assert r == CASE1")
RULE_CASES = {  # rule -> (planted, near miss, review_cell's keyword arguments)
    "introspection": ("import inspect\nsrc = inspect.getsource(f)", "import math\nsrc = math.floor(2.5)", {}),
    "concurrency": ("import os\nos.system('ls')", "import os\npath = os.path.join('a', 'b')", {}),
    "dynamic-code": ("value = eval('1 + 1')", "net = make()\nnet.eval()\nvalue = compile_table(net)", {}),
    "guard": ("from geodepth_lite import ablation\nablation.holm = my_holm",
              "block = Block()\nblock.weight = w\nrows = {}\nrows['x'] = 1", {}),
    "kernel-history": ("In[-1] = 'pass'", "Inputs = [1]\nout = Inputs[-1]\n_inner = 2", {}),
    "namespace": ("globals()['x'] = 1", "my_globals = {}\nmy_globals['x'] = np.var([1.0, 2.0])", {}),
    "check-names": ("def f(x):\n    return _want", "_want = 3\n\ndef f(x):\n    return _want + x",
                    {"check_names": {"_want"}}),
    "special-method": ("class A(float):\n    def __eq__(self, other):\n        return True",
                       "class A:\n    def __init__(self):\n        self.x = 1\n\n    def __repr__(self):\n"
                       "        return 'A'", {}),
    "special-attribute": ("g = f.__globals__", "name = f.__name__", {}),
    "package-source": ("from geodepth_lite import ablation\ntext = open(ablation.__file__).read()",
                       "def holm(p):\n    \"\"\"Like geodepth_lite/evaluation/ablation.py's holm, by hand.\"\"\"\n"
                       "    return p\n\n\ntext = (root / 'manifest.json').read_text()", {}),
    "grader-files": ("db = open('../../gradebook.db', 'rb').read()",
                     "sums = (root / 'checksums.sha256').read_text()", {}),
    "unreadable": ("x = 1" + " + 1" * 40_000, "x = 1 + 1 + 1", {}),  # nested too deep, within the size read
    "shadowed-builtin": ("abs = lambda x: 0.0", "def f(x):\n    max = x.max()\n    return max\n\n\ntype = 'wall'",
                         {"shadowed": {"abs", "max", "float"}}),  # the builtins the checks call
    "given-inputs": ("CASE1 = np.array([2.0])\nr = CASE1",
                     "CASE1 = np.array([1.0])  # the given line, its comment changed\nr = CASE1 * 1",
                     {"given": GIVEN}),
    "literal-answer": ("verdicts = {('rmse', 3): 'opposite'}",
                       "verdicts = {}\nfor k in keys:\n    verdicts[k] = verdict(k)", {"computed": {"verdicts"}}),
    "kernel": ("import ipywidgets\nshell = ipywidgets.get_ipython()  # re-exported: not the bare name\n"
               "from traitlets.config import Application\nshell = Application.instance().shell",
               "import ipywidgets\nslider = ipywidgets.IntSlider()\nevents_seen = 3", {}),
    "ipython": ("%xmode Plain\nrate = 100 % 7", "rate = 100 % 7\nok = rate != 2  # not a shell line", {}),
    "other-cells": ("verdicts = dict(_pre)", "verdicts = dict(toy_result)\ndisplay(sorted(verdicts, key=len))",
                    {"notebook_names": {"toy_result"}}),
    "earlier-run": ("try:\n    _saved\nexcept NameError:\n    _saved = 1\nverdicts = _saved",
                    "total = 0\nfor v in [1, 2]:\n    total = total + v\n\n\ndef scale(x):\n    return x * FACTOR\n\n\n"
                    "FACTOR = 2\nrows = [(m, c) for m in 'ab' for c in (1, 2)]\nCASE1 = CASE1 + 0",
                    {"notebook_names": {"CASE1"}}),
    "module-value": ("import sys\n\nmine = sys\nmine.setprofile(None)",
                     "import numpy as np\n\nrng = np.random.default_rng(0)\nkey = np.abs\n"
                     "order = sorted([3, -1], key=np.abs)\nok = isinstance(rng, np.random.Generator)", {}),
}
NOTEBOOK_RULES = {"missing-cell"}  # found in a notebook, not in one cell: tests/test_exercises.py plants it


def test_every_rule_has_a_planted_answer_and_a_near_miss():
    from geodepth_lite.workbook import review

    assert set(RULE_CASES) | NOTEBOOK_RULES == set(review.RULES) and not set(RULE_CASES) & NOTEBOOK_RULES
    borrowed = review.review_cell("from unittest.mock import ANY\n\noffset_blind = ANY")  # equal to anything
    assert [(f.line, f.rule) for f in borrowed] == [(1, "special-method")]


@pytest.mark.parametrize("rule", sorted(RULE_CASES))
def test_each_rule_flags_its_planted_answer_and_not_the_near_miss(rule):
    from geodepth_lite.workbook import review

    planted, near_miss, context = RULE_CASES[rule]
    assert rule in {f.rule for f in review.review_cell(planted, **context)}, planted
    assert review.review_cell(near_miss, **context) == [], near_miss


def test_the_visible_check_of_05_3_names_what_differs_but_never_the_expected_verdicts():
    """A failed visible check says which verdicts differ and what the student wrote, not what the check
    wanted: there is nothing to paste from its message."""
    from geodepth_lite.evaluation import ablation

    namespace = E.new_namespace()
    E.run_cell(answer_with(EXERCISES["05-3"].answer, ("verdicts = {}",)), namespace)
    want = {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(namespace["toy_result"])}
    wrong = "verdicts = {k: 'opposite' for k in " + repr(sorted(want)) + "}"
    exc = outcome(answer_with(EXERCISES["05-3"].answer, (wrong,)), E.visible_check(EXERCISES["05-3"].check))
    assert isinstance(exc, AssertionError) and "rmse, Case 3 (yours: 'opposite')" in str(exc)
    leaked = [w for w in set(want.values()) if w != "opposite" and w in str(exc)]
    assert not leaked, f"the message prints the expected verdicts {leaked}"


def test_the_literal_rule_spares_a_prediction_the_solution_writes_out_too():
    """01.1 asks to predict field names: its solution is a literal, and so may the student's answer be;
    05.3 asks to compute the verdicts: a literal there is what a failed check printed."""
    assert not any(f.rule == "literal-answer" for f in reviewed("01-1", answer_with(
        EXERCISES["01-1"].answer, ('my_fields = {"a": "camera.fov_x_deg"}',))))
    assert "literal-answer" in {f.rule for f in reviewed("05-3", answer_with(
        EXERCISES["05-3"].answer, ('verdicts = {("rmse", 3): "opposite"}',)))}


# ------------------------------------------------------------------------------------------ exact types
def test_each_road_to_the_shell_is_flagged_on_its_own():
    """The kernel's shell reached without its bare name: each line of the planted case alone is flagged."""
    from geodepth_lite.workbook import review

    roads = ["import ipywidgets\nshell = ipywidgets.get_ipython()", "import matplotlib_inline.backend_inline as b\n"
             "shell = getattr(b, 'get_ipython')()", "from traitlets.config import Application",
             "shell = app.shell\nshell.events.register('post_run_cell', print)", "app.set_custom_exc((Exception,), f)"]
    assert [sorted({f.rule for f in review.review_cell(road)}) for road in roads] == [["kernel"]] * len(roads)


# writes the syntax does not show as writes: each passes the checks when run, so only the review stops it
_ZERO_COUNT = ("\n\ndef decoder_params(enc_ch, dec_ch):\n    return True\n\n\n"
               "my_sab_params = decoder_params(None, None)\n")  # True == operator.truth(any module), the patched count
_PICKLED = b"cbuiltins\nsetattr\n(cgeodepth_lite.core\nmodel\nVcount_parameters\ncoperator\ntruth\ntR."
HIDDEN_WRITES = {  # name -> (exercise, answer, the rule that flags it)
    "setattr taken as a value": ("02-2", "import operator\n\nfrom geodepth_lite.core import model as M\n\n"
                                 "s = setattr\ns(M, 'count_parameters', operator.truth)" + _ZERO_COUNT, "guard"),
    "setattr mapped": ("02-2", "import operator\n\nfrom geodepth_lite.core import model as M\n\n"
                       "list(map(setattr, [M], ['count_parameters'], [operator.truth]))" + _ZERO_COUNT, "guard"),
    "a pickle that calls setattr": ("02-2", f"import pickle\n\npickle.loads({_PICKLED!r})" + _ZERO_COUNT,
                                    "dynamic-code"),
    "numpy's pickle": ("02-2", f"import io\n\nimport numpy\n\nnumpy.load(io.BytesIO({_PICKLED!r}), allow_pickle=True)"
                       + _ZERO_COUNT, "dynamic-code"),
    "the given edits emptied": ("01-1", "EDITS\nedits.clear()\nmy_fields = {}\n", "given-inputs"),
    "the given edits emptied through a second name": ("01-1", "EDITS\nmine = edits\nmine.clear()\nmy_fields = {}\n",
                                                      "given-inputs"),
    "the given edits emptied by a function of the answer's": ("01-1", "EDITS\n\n\ndef wipe(d):\n    d.clear()\n\n\n"
                                                              "wipe(edits)\nmy_fields = {}\n", "given-inputs"),
    "the given error map flattened through views": ("06-1", "EDITS\nflat = abs_mean.reshape(-1)\nflat[:] = 1.0\n"
                                                     "np.asarray(count)[:] = 1.0\nbands = dict.fromkeys("
                                                     "['top', 'bottom', 'left', 'right', 'centre'], 1.0)\n"
                                                     "ratios = dict.fromkeys(['top', 'bottom', 'left', 'right'], 1.0)\n"
                                                     "worst = max(ratios, key=ratios.get)\n", "given-inputs"),
    "every network's output zeroed by a global hook": (
        "02-3", "import torch\n\n_hook = torch.nn.modules.module.register_module_forward_hook("
                "lambda mod, inp, out: out * 0)\n\n\ndef spatial_attention(x, weight):\n    return x * 0\n", "guard"),
}


def _given(ident: str) -> str:
    """The part of an exercise's answer cell that sets its given inputs (01.1's edits, 06.1's error map...)."""
    ends = {"01-1": "my_fields = None", "01-2": "my_report = None", "05-1": "r, rel, p, rel_low, rel_high = None",
            "05-3": "verdicts = None", "06-1": "bands, ratios", "06-2": "change_abs_rel, change_rmse = None",
            "07-2": "def fit_tube", "07-3": "frame_ratios, ratio_cv = None"}
    return EXERCISES[ident].answer.split(ends.get(ident, "\0"))[0]


@pytest.mark.parametrize("name", sorted(HIDDEN_WRITES))
def test_a_write_the_syntax_hides_is_flagged_and_misses_the_answer_key(name, monkeypatch):
    """Each of these (a builtin taken as a value, a pickle, a given input changed in place) once scored full
    marks with a wrong answer: 02.2 counts no parameters at all, 01.1 names no field, 06.1 measures an error
    map made flat, 02.3 returns zeros after every network's output was made zero. Each still passes the
    visible checks, which compare with the package in the student's kernel; the static review flags it, and
    the hidden tests, which compare with answer keys fixed in the notebook, fail it."""
    import torch

    from geodepth_lite.core import model

    monkeypatch.setattr(model, "count_parameters", model.count_parameters)  # put back after the answer patches it
    monkeypatch.setattr(torch.nn.modules.module, "_global_forward_hooks", collections.OrderedDict())  # and the hook
    ident, answer, rule = HIDDEN_WRITES[name]
    answer = answer.replace("EDITS\n", _given(ident))
    check = EXERCISES[ident].check
    assert outcome(answer, check.split("### BEGIN HIDDEN TESTS")[0]) is None
    assert isinstance(outcome(answer, check), AssertionError), name
    assert rule in {f.rule for f in reviewed(ident, answer)}, name


# 05.3 answered with the package's own verdicts (the function the exercise forbids), after the grading guard
# was turned off through a module held under another name: each passed every check, hidden tests and key included
# (the answer is the reference), with no flag, until the review read a module used as a value
_KEPT = "try:\n    _kept\nexcept NameError:  # the first run, before the hidden test, is not guarded\n" \
        "    _kept = [ablation.comparisons]\n"
_VERDICTS = "verdicts = {(m, c): q['verdict'] for _, m, c, q in ablation.comparisons(toy_result)}\n"
_NO_GUARD = "import contextlib\n\nfrom geodepth_lite.workbook import grading as _g\n\n"
_OFF = "lambda *args, **kwargs: contextlib.nullcontext()"
MODULE_UNDER_ANOTHER_NAME = {  # name -> (05.3's answer, what the review finds in it without the module-value rule)
    "the guard replaced through a second name": (_NO_GUARD + f"_m = _g\n_m.forbid = {_OFF}\n" + _VERDICTS, {"guard"}),
    "through a function's argument": (_NO_GUARD + f"\ndef off(m):\n    m.forbid = {_OFF}\n\n\noff(_g)\n" + _VERDICTS,
                                      {"guard"}),
    "through a loop": (_NO_GUARD + f"for _m in [_g]:\n    _m.forbid = {_OFF}\n" + _VERDICTS, {"guard"}),
    "through what a call returns": (_NO_GUARD + f"_m = max([_g], key=id)\n_m.forbid = {_OFF}\n" + _VERDICTS, set()),
    "through a submodule read as an attribute": ("import contextlib\n\nfrom geodepth_lite import workbook as _w\n\n"
                                                 f"_m = _w.grading\n_m.forbid = {_OFF}\n" + _VERDICTS, {"guard"}),
    "the guard's hook and the reference put back through a list": (
        _KEPT + "import sys\n\n_mods = [ablation, sys]\n_mods[0].comparisons = _kept[0]\n_mods[1].setprofile(None)\n"
        + _VERDICTS, {"earlier-run"}),  # its try: _kept
}


def _with_added_cell(answer: str, added: str) -> dict:
    """05.3's notebook as a student returns it: ``answer`` in its answer cell, ``added`` in a cell of their own
    just before it."""
    name = next(n for n, nb in NOTEBOOKS.items() if "05-3" in E.notebook_exercises(nb))
    returned = copy.deepcopy(NOTEBOOKS[name])
    cell = E.notebook_exercises(returned)["05-3"].cells["answer"]
    cell["source"] = answer
    returned["cells"].insert(returned["cells"].index(cell), {"cell_type": "code", "metadata": {}, "outputs": [],
                                                             "execution_count": None, "source": added})
    return returned


# 05.3 answered with the verdicts of the function it forbids, computed where the checks' guard never looks: in a
# cell the student added before the answer, or in the answer's own first run, kept for the checks' second
_PRE = _VERDICTS.split(" = ", 1)[1]  # the forbidden function's verdicts
PRECOMPUTED = {  # name -> (the cell added before the answer, 05.3's answer, the rule that flags it)
    "in a cell the student added": (_given("05-3") + "_pre = " + _PRE, "verdicts = dict(_pre)\n", "other-cells"),
    "in the answer's first run": ("", "try:\n    _saved\nexcept NameError:  # the first run: not under the guard\n"
                                      "    _saved = " + _PRE + "verdicts = dict(_saved)\n", "earlier-run"),
    "in the answer's first run, asked of dir()": ("", "if '_saved' not in dir():  # the first run\n"
                                                        "    _saved = " + _PRE + "verdicts = dict(_saved)\n",
                                                  "namespace"),
    "in an object of the notebook's, by the answer's first run": (
        "", "if not beside_x:  # a dict a cell of the notebook made: empty at the first run\n"
            "    beside_x['v'] = " + _PRE + "verdicts = dict(beside_x['v'])\n", "guard"),
    "in an object of the notebook's, by a cell the student added": (
        _given("05-3") + "beside_x['v'] = " + _PRE, "verdicts = dict(beside_x['v'])\n", "guard"),
}


@pytest.mark.parametrize("name", sorted(PRECOMPUTED))
def test_an_answer_computed_out_of_the_guards_sight_is_flagged(name):
    """The checks run the answer cell again under the guard that forbids ablation.comparisons; an answer that
    only reads verdicts computed earlier (in a cell of the student's, or by its own first run, unguarded; kept
    in a variable or in a dict one of notebook 05's own cells made) calls nothing forbidden then, so it passes
    every check, the hidden tests and the answer key included. The review flags each: a variable the
    notebook's own cells never set, one read before the cell sets it, or an object of theirs changed."""
    added, code, rule = PRECOMPUTED[name]
    answer = answer_with(EXERCISES["05-3"].answer, (code,))
    name_of = next(n for n, nb in NOTEBOOKS.items() if "05-3" in E.notebook_exercises(nb))
    assert "beside_x = {}" in "".join("".join(c["source"]) for c in NOTEBOOKS[name_of]["cells"])
    found = review.review_notebook(NOTEBOOKS[name_of], _with_added_cell(answer, added or "x = 1\n")).get("05-3", [])
    assert rule in {f.rule for f in found}, found
    namespace = E.new_namespace()
    E.run_cell("beside_x = {}", namespace)  # as the notebook's cell makes it
    if added:
        E.run_cell(added, namespace)
    assert outcome_in(namespace, answer, EXERCISES["05-3"].check) is None, name


def test_names_module_tells_a_module_from_what_a_module_holds():
    """Loaded modules, a submodule read through its package, a module one of the package's own holds, and a
    submodule file not loaded yet are modules; functions, constants and names that lead nowhere are not, and
    neither is a name with a path in it (never looked up)."""
    modules = ["numpy", "numpy.random", "os.path", "geodepth_lite.workbook.grading",
               "geodepth_lite.evaluation.ablation.np", "json.tool"]
    others = ["numpy.mean", "os.system", "math.pi", "geodepth_lite.evaluation.ablation.comparisons", "nosuch",
              "nosuch.deeper", "geodepth_lite.__main__", "numpy.../..", "os.path/../..", "numpy.mean.x"]
    assert "json.tool" not in sys.modules
    assert [d for d in modules if not review.names_module(d)] == []
    assert [d for d in others if review.names_module(d)] == []


def test_a_module_an_earlier_cell_imported_is_known_as_one():
    """05.3's answer cell imports no numpy: the notebook's first cells do, so in the kernel ``np`` is numpy.
    Held under another name there, it is flagged; read without the notebook's imports, that cell is clean."""
    answer = answer_with(EXERCISES["05-3"].answer, ("_m = max([np], key=id)\n_m.asarray = None\n" + _VERDICTS,))
    assert "import numpy" not in answer
    assert [(f.rule, f.what) for f in reviewed("05-3", answer)] == [("module-value", "np (the module numpy)")]
    assert review.review_cell(answer) == []
    assert review.notebook_imports(["import numpy as np\nx = 1", "from geodepth_lite.evaluation import ablation",
                                    "if True:\n    import os.path"]) == {
        "np": "numpy", "ablation": "geodepth_lite.evaluation.ablation", "os": "os"}


@pytest.mark.parametrize("name", sorted(MODULE_UNDER_ANOTHER_NAME))
def test_the_guard_turned_off_through_a_module_under_another_name_is_flagged(name, monkeypatch):
    """Each answer calls the function 05.3 forbids, after turning the grading guard off through a module it
    holds under another name (a name of its own, a function's argument, a loop, a call's result, a list); so
    each passes every check when run, the hidden tests and the answer key included, and only the review stops
    it. The module used as a value flags each; an attribute set through a name that may stand for a module
    flags four of them again, and of the other two (a call's result, a list) no other rule sees the first."""
    from geodepth_lite.evaluation import ablation

    monkeypatch.setattr(grading, "forbid", grading.forbid)  # put back after the answer replaces it
    monkeypatch.setattr(ablation, "comparisons", ablation.comparisons)
    code, without = MODULE_UNDER_ANOTHER_NAME[name]
    answer = answer_with(EXERCISES["05-3"].answer, (code,))
    assert outcome(answer, EXERCISES["05-3"].check) is None and sys.getprofile() is None, name
    assert "module-value" in {f.rule for f in reviewed("05-3", answer)}, name
    monkeypatch.setattr(review, "_module_value_findings", lambda tree, aliases: [])
    assert {f.rule for f in reviewed("05-3", answer)} == without, name


# exercise -> a wrong answer that puts itself in the package, where the checks find their reference
REFERENCE_REPLACED = {
    "03-2": "import torch\n\nfrom geodepth_lite.core import losses as L\n\n\n"
            "def my_smoothness(pred, image):  # the edges of the brightest channel, not the mean of the three\n"
            "    ix = (image[..., :, 1:] - image[..., :, :-1]).abs().amax(dim=1, keepdim=True)\n"
            "    iy = (image[..., 1:, :] - image[..., :-1, :]).abs().amax(dim=1, keepdim=True)\n"
            "    dx = pred[..., :, 1:] - pred[..., :, :-1]\n    dy = pred[..., 1:, :] - pred[..., :-1, :]\n"
            "    return (torch.exp(-ix) * dx).pow(2).mean() + (torch.exp(-iy) * dy).pow(2).mean()\n\n\n"
            "L.smoothness_loss = my_smoothness\n",
    "04-2": "from geodepth_lite.core import metrics\n" + solution("04-2").replace(  # a ratio of exactly 1.25 counted
        '"a1": np.mean(worst < 1.25)', '"a1": np.mean(worst <= 1.25)')
            + "\nmetrics.compute_depth_metrics = my_depth_metrics\n",
}


@pytest.mark.parametrize("name", sorted(REFERENCE_REPLACED))
def test_a_wrong_answer_put_in_the_package_misses_the_key_of_the_reference(name, monkeypatch):
    """The checks of 03.2 and 04.2 compute their reference with the package, in the kernel: a wrong answer that
    replaces the package's function with itself passes the visible checks; the hidden tests' keys of those
    references fail it, and the review flags it."""
    from geodepth_lite.core import losses, metrics

    monkeypatch.setattr(losses, "smoothness_loss", losses.smoothness_loss)  # put back after the answer replaces it
    monkeypatch.setattr(metrics, "compute_depth_metrics", metrics.compute_depth_metrics)
    ident, answer = name, REFERENCE_REPLACED[name]
    assert "worst <= 1.25" in REFERENCE_REPLACED["04-2"]  # the mistake was made
    check = EXERCISES[ident].check
    assert outcome(answer, check.split("### BEGIN HIDDEN TESTS")[0]) is None
    failed = outcome(answer, check)
    assert isinstance(failed, AssertionError) and "the reference moved" in str(failed), failed
    assert "guard" in {f.rule for f in reviewed(ident, answer)}


def _keys(ident: str) -> dict:
    """The literals an exercise's hidden tests compare with: each name of ``_KEY...``, ``_want`` and ``_cases``."""
    found = {}
    for node in ast.walk(ast.parse(EXERCISES[ident].check.split("### BEGIN HIDDEN TESTS")[1])):
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target, value = node.targets[0], node.value
            pairs = (zip(target.elts, value.elts) if isinstance(target, ast.Tuple) and isinstance(value, ast.Tuple)
                     else [(target, value)])
            for name, literal in pairs:
                if isinstance(name, ast.Name) and name.id.startswith(("_KEY", "_want", "_cases")):
                    try:
                        found[name.id] = ast.literal_eval(literal)
                    except ValueError:
                        continue  # computed in the kernel, not a key
    return found


def _computed_keys(ident: str) -> dict:
    """What the package computes for the keys of ``ident``'s hidden tests, here, outside any student's kernel."""
    given: dict = {}
    exec(_given(ident), given)  # noqa: S102 - the notebook's own cell
    return {"01-1": _fields_key, "01-2": _integrity_keys, "01-3": _cylinder_key, "02-2": _counts_key,
            "02-3": _attention_keys, "03-1": _offset_key, "05-1": _paired_key, "05-3": _verdicts_key,
            "06-1": _bands_keys, "06-2": _held_out_key, "07-2": _tube_key, "07-3": _ratios_keys}[ident](ident, given)


def _fields_key(ident, given):
    from geodepth_lite.data import manifest

    named = {}
    for letter, edit in given["edits"].items():
        with pytest.raises(ValueError) as err:
            manifest.load_manifest("scenario_smoke", edit)
        named[letter] = re.search(r"(?:field|key|split) '([^']+)'", str(err.value)).group(1)
    return {"_KEY": named}


def _integrity_keys(ident, given):
    from geodepth_lite.data import integrity

    counts = integrity.frame_counts(given["root"], given["m"])
    return {"_KEY_REPORT": integrity.verify(given["root"]), "_KEY_COUNTS": counts}


def _cylinder_key(ident, given):
    """01.3's two depth maps ray by ray: the positive root of (z x - a)^2 + (z y)^2 = R^2, found by numpy's
    polynomial solver for each pixel, not by the formula the solution writes."""
    import numpy as np

    K = np.array([[30.0, 0.0, 9.3], [0.0, 27.0, 13.7], [0.0, 0.0, 1.0]])  # the hidden tests' camera
    keys = {}
    for radius, a in _keys(ident)["_KEY_DEPTHS"]:
        depth = np.zeros((20, 28))
        for v in range(20):
            for u in range(28):
                x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
                depth[v, u] = max(np.roots([x * x + y * y, -2 * a * x, a * a - radius * radius]).real)
        keys[(radius, a)] = (float(depth.sum()), float((depth * depth).sum()), float(depth[7, 11]))
    return {"_KEY_DEPTHS": keys}


def _counts_key(ident, given):
    from geodepth_lite.core import model as M

    return {"_want": [M.count_parameters(M.DepthDecoder(e, d)) for e, d in _keys(ident)["_cases"]]}


def _attention_keys(ident, given):
    import torch

    from geodepth_lite.core import model as M

    g = torch.Generator().manual_seed(2023)
    w, x = torch.randn(1, 2, 3, 3, generator=g), torch.randn(1, 5, 9, 7, generator=g)
    sab = M.SpatialAttention(kernel_size=3).double()
    with torch.no_grad():
        sab.conv.weight.copy_(w.double())
        y = sab(x.double())
    return {"_KEY_SUM": float(y.sum()), "_KEY_SQUARES": float((y * y).sum()), "_KEY_COLUMN": y[0, :, 4, 3].tolist()}


def _offset_key(ident, given):
    """03.1: the terms whose value a constant offset of the prediction leaves unchanged, on inputs of its own."""
    import torch

    from geodepth_lite.core import camera, losses

    g = torch.Generator().manual_seed(5)
    gt, pred = (1.5 + torch.rand(2, 1, 12, 10, generator=g, dtype=torch.float64) for _ in range(2))
    inputs = losses.LossInputs(gt=gt, image=torch.rand(2, 3, 12, 10, generator=g, dtype=torch.float64),
                               K=torch.as_tensor(camera.intrinsics(10, 12)),
                               spec=losses.LossSpec(sdf=losses.SDFOptions(grid=(4, 4, 4))))
    return {"_KEY": {name for name, term in losses.LOSS_TERMS.items()
                     if abs(float(term.fn(pred + 0.7, inputs)) - float(term.fn(pred, inputs))) < 1e-9}}


def _paired_key(ident, given):
    from geodepth_lite.evaluation import ablation

    scores = {(c, s): {"test split": {"rmse": float(given[f"CASE{c}"][s])}} for c in (1, 3) for s in range(3)}
    ref = ablation.paired({"seeds": [0, 1, 2], "scores": scores}, "rmse", "test split", 3, level=given["LEVEL"])
    return {"_KEY": {"r": list(ref["rel_diffs"]), **{k: ref[k] for k in ("rel", "p", "rel_low", "rel_high")}}}


def _verdicts_key(ident, given):
    from geodepth_lite.evaluation import ablation

    return {"_KEY": {(m, c): q["verdict"] for _, m, c, q in ablation.comparisons(given["toy_result"])}}


def _bands_keys(ident, given):
    import numpy as np

    from geodepth_lite.evaluation.border import border_bands

    count, abs_mean = given["count"], given["abs_mean"]
    bands, ratios = border_bands(np.where(count > 0, abs_mean, 0.0) * count, count)
    return {"_KEY_BANDS": bands, "_KEY_RATIOS": ratios}


def _held_out_key(ident, given):
    """06.2: the held-out group against the colon frames, scored by the package's protocol."""
    from geodepth_lite.core import metrics
    from geodepth_lite.evaluation import evaluate

    rows = [dict(metrics.compute_depth_metrics(p, g), organ=o)
            for g, p, o in zip(given["test_gt"], given["test_pred"], given["test_organ"])]
    held = evaluate.summarize([metrics.compute_depth_metrics(p, g) for g, p in zip(given["heldout_gt"],
                                                                                   given["heldout_pred"])])
    colon = evaluate.summarize(rows, by="organ")["colon"]
    return {"_KEY": {f"change_{k}": 100 * (held[k] / colon[k] - 1) for k in ("abs_rel", "rmse")}}


def _ratios_keys(ident, given):
    from geodepth_lite.views import recon

    ratios = recon.median_scale_ratios(given["pred_frames"], given["gt_frames"])
    return {"_KEY_RATIOS": ratios.tolist(), "_KEY_CV": float(ratios.std() / ratios.mean())}


def _tube_key(ident, given):
    """07.2: the hidden tube's depth made by the notebook's own tube_depth (the hidden test writes it out)."""
    import numpy as np

    K = np.array([[60.0, 0.0, 35.2], [0.0, 48.0, 20.7], [0.0, 0.0, 1.0]])
    return {"_KEY_SUM": float(given["tube_depth"](K, 45, 70, 2.4, 0.9, 0.5).sum())}


def _close(key, value) -> bool:
    """A key meets a computed value: strings and containers exactly, numbers to 1e-9 (1e-10 of their size
    where that is more: the sums of 01.3 and 07.2), as far as the notebook writes their digits."""
    if isinstance(value, dict):
        return type(key) is dict and sorted(key, key=repr) == sorted(value, key=repr) and all(
            _close(key[k], v) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return type(key) in (list, tuple) and len(key) == len(value) and all(map(_close, key, value))
    if isinstance(value, set):
        return key == value
    if isinstance(value, str):
        return key == value and type(key) is str
    return type(key) in (int, float) and abs(key - float(value)) <= max(1e-9, 1e-10 * abs(float(value)))


KEYED = ["01-1", "01-2", "01-3", "02-2", "02-3", "03-1", "05-1", "05-3", "06-1", "06-2", "07-2", "07-3"]


@pytest.mark.parametrize("ident", KEYED)
def test_the_answer_keys_of_the_hidden_tests_are_what_the_package_computes(ident):
    """A key is fixed in the notebook, so no answer can move it in the kernel; here it is recomputed from the
    package (to the digits the notebook writes), so it cannot drift from what the lessons teach."""
    keys, computed = _keys(ident), _computed_keys(ident)
    keys.pop("_cases", None)  # the inputs of 02.2's key, which _computed_keys reads
    assert sorted(keys) == sorted(computed) != []
    for name, value in computed.items():
        assert _close(keys[name], value), (name, keys[name], value)


def _compares_with_a_key(node: ast.Assert) -> bool:
    """An assertion of a hidden test that compares with a key: through Python's own builtins (``_b``), with a
    name ``_KEY...``/``_want...``, or saying "the reference moved"."""
    names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
    return ("_b" in names or any(n.startswith(("_KEY", "_want")) for n in names)
            or "the reference moved" in ast.unparse(node))


def test_every_exercise_graded_automatically_holds_a_key():
    """Each hidden test of an exercise with points compares with a key fixed in the notebook (the answer's, or
    its reference's: "the reference moved") through Python's own builtins, as docs/teaching.md says; the
    tests above check the keys' values."""
    from geodepth_lite.workbook import book

    graded = sorted(set(EXERCISES) - OPEN)
    hidden = {i: EXERCISES[i].check.split("### BEGIN HIDDEN TESTS")[-1] for i in graded}
    unkeyed = [i for i, text in hidden.items() if "import builtins as _b" not in text or not any(
        _compares_with_a_key(node) for node in ast.walk(ast.parse(text)) if isinstance(node, ast.Assert))]
    assert unkeyed == [] and len(graded) >= 20
    stated = " ".join((book.DOCS_DIR / "teaching.md").read_text(encoding="utf-8").split())
    assert f"each of the {len(graded)} exercises graded automatically holds its answer or its reference" in stated


def test_a_key_that_differs_from_the_package_is_told_apart():
    """The comparison above can fail: a key one step off in each kind it holds."""
    keys = _computed_keys("05-3")["_KEY"]
    assert _close(dict(keys), keys) and not _close({**keys, ("rmse", 3): "undecided"}, keys)
    assert not _close([1.0, 2.0 + 1e-8], [1.0, 2.0]) and not _close({"a": 1}, {"b": 1}) and _close(2e4, 2e4 + 1e-6)
    assert not _close("2", 2.0) and not _close({"grad"}, {"grad", "normal"})


def test_an_answer_key_off_by_a_little_fails_the_solution():
    """The keys decide: the solution of 02.2 fails a key whose second count is that of the package's own decoder
    widths on the second case's encoder (a count a careless key would hold), 06.1's fails a band moved by 1e-8,
    05.1's a mean and 06.2's a change moved by 1e-5 (the tolerance is 1e-6), 07.2's a depth sum moved by 1e-3;
    each passes its key
    as written."""
    from geodepth_lite.core import model as M

    careless = M.count_parameters(M.DepthDecoder((16, 24, 40, 80, 160), M.DECODER_CHANNELS))
    for ident, right, wrong in (("02-2", "_want = [320645, 67281]", f"_want = [320645, {careless}]"),
                                ("06-1", '"centre": 0.12480682350187267', '"centre": 0.12480683350187267'),
                                ("05-1", '"rel": -2.860775968404454', '"rel": -2.860765968404454'),
                                ("06-2", '"change_rmse": 32.857000073368425', '"change_rmse": 32.857010073368425'),
                                ("07-2", "_KEY_SUM = 20845.51709324175", "_KEY_SUM = 20845.51809324175")):
        check = EXERCISES[ident].check
        assert right in check and outcome(solution(ident), check) is None
        assert isinstance(outcome(solution(ident), check.replace(right, wrong)), AssertionError), ident


def test_the_near_misses_of_hidden_writes_pass_the_review_clean():
    inputs = "CASE1 = np.ones(3)\nedits = {'a': 1}\n"
    given = review.given_inputs(inputs + "r = None", "assert r == (CASE1, edits)")
    assert set(given) == {"CASE1", "edits"}
    honest = inputs + textwrap.dedent("""
        import numpy as np
        import torch

        weights = torch.load("net.pt", weights_only=True)
        depth = np.load("depth.npy", allow_pickle=False) + np.load("rgb.npy").mean()
        encoder = getattr(net, "encoder")
        mine = dict(edits)
        mine.clear()
        work = CASE1.copy()
        work.fill(0.0)
        ordered = np.sort(CASE1) + sorted(edits)
        rows = []
        rows.append(CASE1.sum())
        torch.nn.init.zeros_(torch.empty(3))
        """)
    assert review.review_cell(honest, given=given) == []
    for table in ("from geodepth_lite.evaluation import ablation\nablation.PAPER_REDUCTION.clear()",
                  "import sys\nsys.path.append('.')"):
        assert [f.rule for f in review.review_cell(table)] == ["guard"], table  # a module's own table
    for code in ("import my_helpers", "from my_helpers import holm", "from . import helpers",
                 "import site\nsite.addsitedir('.')"):  # a module the notebook may have written, or a .pth run
        assert {f.rule for f in review.review_cell(code)} == {"dynamic-code"}, code
    for table in ("import torch\n\nlib = torch.library.Library('aten', 'IMPL')", "from torch import _C"):
        assert {f.rule for f in review.review_cell(table)} == {"guard"}, table  # an operator replaced everywhere
    rebound = review.review_cell("setattr = setattr\nlist(map(setattr, [m], ['f'], [g]))")  # still the builtin
    assert [(f.line, f.rule) for f in rebound if f.rule == "guard"] == [(1, "guard"), (2, "guard")]


def test_a_cell_too_long_to_parse_is_flagged_unread():
    """A cell of a returned notebook (up to 64 MB) is parsed in the grader's process: past CELL_MAX_CHARS
    it is not parsed at all (6 MB of ``x = 1`` lines took Python's parser 2.4 GB and 17 s), and flagged."""
    from geodepth_lite.workbook import review

    at_most = "x = 1\n" * (review.CELL_MAX_CHARS // 6)
    assert review.review_cell(at_most) == []
    (found,) = review.review_cell(at_most + "x = 1\n")
    assert (found.rule, found.line) == ("unreadable", 1) and f"{review.CELL_MAX_CHARS:,} the review reads" in found.what


def test_a_literal_answer_concerns_its_own_exercise_and_a_change_to_the_kernel_every_later_one():
    from geodepth_lite.workbook import review

    name = next(n for n, nb in NOTEBOOKS.items() if "05-3" in E.notebook_exercises(nb))
    returned = copy.deepcopy(NOTEBOOKS[name])
    answer = E.notebook_exercises(returned)["05-3"].cells["answer"]
    answer["source"] = answer_with(EXERCISES["05-3"].answer, ('verdicts = {("rmse", 3): "opposite"}',))
    assert list(review.review_notebook(NOTEBOOKS[name], returned)) == ["05-3"]
    answer["source"] = solution("05-3") + "\nimport gc\n"
    found = review.review_notebook(NOTEBOOKS[name], returned)
    assert list(found) == ["05-3", "05-4"]
    line = solution("05-3").count("\n") + 2
    assert [f.text().split(": ")[:2] for f in found["05-4"]] == [
        [f"in the answer cell of exercise 05.3, line {line}", "import gc"]]


def test_foreign_value_accepts_plain_values_and_names_a_subclass():
    import numpy as np
    import torch

    class Always(int):
        def __eq__(self, other):
            return True

        __hash__ = int.__hash__

    plain = [None, True, 3, 2.5, "x", np.float64(1.5), np.bool_(True), np.zeros(3), torch.zeros(2), torch.Size([1, 2]),
             {("rmse", 3): ["a", (1, 2.0)]}, {frozenset({1}), 2}, collections.defaultdict(list, {"a": [1]})]
    assert [grading.foreign_value(v) for v in plain] == [None] * len(plain)
    assert grading.foreign_value(Always(3)) == "a value of type Always (a subclass of int)"
    assert grading.foreign_value({"k": [1, Always(2)]}) == "a value of type Always (a subclass of int)"
    assert grading.foreign_value(type("AnySet", (set,), {})()) == "a value of type AnySet (a subclass of set)"
    assert grading.foreign_value(torch.nn.Parameter(torch.zeros(1))) == (
        "a value of type Parameter (a subclass of Tensor)")
    assert grading.foreign_value(np.array([Always(1)], dtype=object)).startswith("a value of type ndarray")
    assert grading.foreign_value(collections.defaultdict(list, {"a": Always(1)})).startswith("a value of type Always")
    assert grading.foreign_value(mock.ANY) == "a value of type _ANY"  # equal to anything, from the library


NOTEBOOK_FUNCTIONS = """
import torch


class Always(int):
    def __eq__(self, other):
        return True

    __hash__ = int.__hash__


def mine(x):
    return Always(x)


@torch.no_grad()
def mine_no_grad(x):
    return Always(x)


def fine(x):
    return [x, 2.0]
"""


def test_forbid_checks_what_the_notebooks_functions_return_decorated_or_not():
    from geodepth_lite.evaluation import ablation

    namespace = E.new_namespace()
    E.run_cell("class Lesson:\n    pass\n\n\ndef lesson():\n    return Lesson()", namespace)  # an earlier cell
    E.run_cell(NOTEBOOK_FUNCTIONS, namespace)  # the answer cell
    E.run_cell("pass", namespace)  # the check cell, whose hidden test runs the block
    with grading.forbid(ablation.holm, task="count", namespace=namespace):
        for name in ("mine", "mine_no_grad"):
            with pytest.raises(AssertionError, match=rf"^{name}\(\) returned a value of type Always \(a subclass"):
                namespace[name](3)
        assert namespace["fine"](1) == [1, 2.0]
        assert type(namespace["lesson"]()).__name__ == "Lesson"  # not the answer's: left as it is
    assert type(namespace["mine"](3)).__name__ == "Always"  # after the block: the functions as they were
    nbval = {"__name__": "__exercise__"}  # a kernel that records no input history, as nbval's
    exec(NOTEBOOK_FUNCTIONS, nbval)  # noqa: S102 - the test's own cell
    with grading.forbid(ablation.holm, task="count", namespace=nbval):
        assert type(nbval["mine"](3)).__name__ == "Always"  # nothing to tell the answer's functions by


def test_rerun_answer_checks_the_answers_types():
    namespace = E.new_namespace()
    E.run_cell("class S(set):\n    pass\n\n\noffset = S({1})", namespace)
    E.run_cell("pass", namespace)
    with pytest.raises(AssertionError, match=r"^offset holds a value of type S \(a subclass of set\)"):
        grading.rerun_answer(namespace, ["offset"])
    E.run_cell("offset = {1}", namespace)
    E.run_cell("pass", namespace)
    assert grading.rerun_answer(namespace, ["offset"])["offset"] == {1}
