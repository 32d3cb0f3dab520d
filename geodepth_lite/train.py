"""Supervised training of the depth network (paper Section 4.1), checkpoints, resume, DDP.

The paper trains DepthNet fully supervised on its Scenario dataset with Adam
(betas 0.9/0.999, weight decay 0.01, lr 1e-4), batch 20, 18 epochs, 320x320
frames. ``fit`` runs that loop for any profile of ``config.PROFILES``:

- device chosen automatically (CUDA when present, else CPU); mixed precision
  (``torch.autocast``) on CUDA only; the losses are always computed in float32;
- one checkpoint per epoch, written atomically, holding the model, optimizer,
  grad scaler, every RNG state (torch, numpy, python, the sampler seed and the
  DataLoader generator) and the per-epoch log, so a run killed at any point and
  continued with ``resume=True`` ends with the same weights as one that never
  stopped (on the CPU, same seed, same machine);
- launched by ``torchrun --nproc_per_node N -m geodepth_lite train ...`` it uses
  DistributedDataParallel and a DistributedSampler (gloo on CPU, nccl on CUDA);
- per-epoch training/validation losses (each term), validation metrics, the
  time per epoch and the share of step time spent waiting for data go to
  ``log.csv`` and ``log.json`` in the run directory.

Small datasets are decoded and resized once and kept in memory (``cache``);
large ones stream through DataLoader workers seeded by ``utils.worker_init``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import hashlib
import io
import json
import math
import os
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from geodepth_lite import config, utils
from geodepth_lite.dataset import resize_image

CHECKPOINT_NAME = "checkpoint.pt"
LOG_CSV = "log.csv"
LOG_JSON = "log.json"
METRIC_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
LOSS_KEYS = ("depth", "smooth", "grad", "normal", "sdf", "total")

# Settings that change the trained weights: a checkpoint is reused or resumed only
# when all of these match. Runtime-only options (progress bar, workers, device) do not.
IDENTITY_KEYS = (
    "dataset", "dataset_overrides", "image_size", "epochs", "batch_size", "lr",
    "weight_decay", "betas", "sdf_grid", "lambdas", "seed", "train_frames", "val_frames", "encoder_weights",
    "threads", "lr_schedule", "optimizer", "depth_term", "augment", "padding",
)
LR_SCHEDULES = ("constant", "cosine")
OPTIMIZERS = ("adam", "adamw")  # adam: L2 coupled into the gradient (the paper, torch.optim.Adam); adamw: decoupled
AUGMENTS = ("none", "flip", "flip_color", "camera", "crop")  # training-time augmentation (see augment_batch)
CROP_SCALE = (0.5, 1.0)  # augment="crop": the crop's side as a share of the frame's, uniform in this range
# augment="camera": the appearance effects that are cheaper to add to a training image than to
# render (appearance.py), drawn afresh every time a frame is seen; ranges beyond the datasets'.
CAMERA_AUGMENT = {"exposure_stops": [-1.0, 1.0], "gamma": [0.8, 1.3], "color_cast": [-1.0, 1.0],
                  "vignetting": [0.0, 0.5], "specular_flecks": [0, 10], "noise": [0.0, 0.04],
                  "p_blur": 0.3, "blur_px": [0.5, 2.0], "p_jpeg": 0.3, "jpeg_quality": [30, 95]}

# Datasets decoded at the network size stay in memory below this many bytes (per process).
CACHE_LIMIT_BYTES = 2 * 1024**3


# --------------------------------------------------------------------------- config


def make_config(profile: str = "teach", case: int = 4, seed: int = 0, **overrides: Any) -> dict:
    """The training configuration of ablation ``case`` (1-4, Section 4.3) under ``profile``.

    ``overrides`` replace single entries (``epochs=2``, ``lr=3e-4``,
    ``dataset="scenario_smoke"``, ``dataset_overrides={...}``, ``train_frames=40``...).
    """
    p = config.get_profile(profile)
    if case not in config.ABLATION_CASES:
        raise ValueError(f"case must be one of {sorted(config.ABLATION_CASES)}, got {case!r}")
    cfg = {
        "profile": profile,
        "case": int(case),
        "dataset": p["dataset"],
        "dataset_overrides": p.get("dataset_overrides"),
        "image_size": p["image_size"],
        "epochs": p["epochs"],
        "batch_size": p["batch_size"],
        "lr": p["lr"],
        "lr_schedule": p.get("lr_schedule", "constant"),  # constant (the paper) | cosine (decay to 0 per step)
        "weight_decay": p["weight_decay"],
        "betas": [0.9, 0.999],
        "sdf_grid": p["sdf_grid"],
        "lambdas": config.case_lambdas(case, p.get("geo_weights")),
        "optimizer": p.get("optimizer", "adam"),
        "depth_term": p.get("depth_term", "l1"),
        "augment": p.get("augment", "none"),
        "padding": p.get("padding", "zeros"),   # the network's convolution padding (model.PADDINGS)
        "seed": int(seed),
        "train_frames": p.get("train_frames"),  # N evenly spaced training frames (None = all)
        "val_frames": p.get("val_frames"),      # N evenly spaced validation frames (None = all)
        "encoder_weights": None,
        "threads": p.get("threads"),            # CPU threads (fixed: results depend on it); None = torch's
    }
    for key, value in overrides.items():
        if key not in cfg:
            raise ValueError(f"unknown training setting {key!r}: choose from {', '.join(cfg)}")
        if value is not None or key in ("dataset_overrides", "train_frames", "val_frames", "encoder_weights", "threads"):
            cfg[key] = value
    return validate_config(cfg)


def validate_config(cfg: dict) -> dict:
    """Check a training configuration; a clear error naming the field. Returns a normalised copy."""
    cfg = dict(cfg)
    for key in ("dataset_overrides", "train_frames", "val_frames", "encoder_weights", "threads"):
        cfg.setdefault(key, None)
    cfg.setdefault("betas", [0.9, 0.999])
    cfg.setdefault("lr_schedule", "constant")
    cfg.setdefault("optimizer", "adam")
    cfg.setdefault("depth_term", "l1")
    cfg.setdefault("augment", "none")
    cfg.setdefault("padding", "zeros")
    from geodepth_lite.losses import DEPTH_TERMS
    from geodepth_lite.model import PADDINGS

    for key, allowed in (("optimizer", OPTIMIZERS), ("depth_term", tuple(DEPTH_TERMS)), ("augment", AUGMENTS),
                         ("padding", PADDINGS)):
        if cfg[key] not in allowed:
            raise ValueError(f"{key} must be one of {', '.join(allowed)}, got {cfg[key]!r}")
    if cfg["lr_schedule"] not in LR_SCHEDULES:
        raise ValueError(f"lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got {cfg['lr_schedule']!r}")
    missing = [k for k in IDENTITY_KEYS if k not in cfg]
    if missing:
        raise ValueError(f"training config is missing {', '.join(missing)}")

    def positive_int(key):
        v = cfg[key]
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{key} must be a positive integer, got {v!r}")
        cfg[key] = int(v)

    for key in ("epochs", "batch_size", "sdf_grid"):
        positive_int(key)
    positive_int("image_size")
    if cfg["image_size"] % 32:
        raise ValueError(f"image_size must be a multiple of 32 (the encoder downsamples 5 times), got {cfg['image_size']}")
    for key in ("train_frames", "val_frames", "threads"):
        if cfg.get(key) is not None:
            positive_int(key)
    for key in ("lr", "weight_decay"):
        v = cfg[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0 or (key == "lr" and v == 0):
            raise ValueError(f"{key} must be a {'positive' if key == 'lr' else 'non-negative'} number, got {v!r}")
        cfg[key] = float(v)
    betas = cfg["betas"]
    if not (isinstance(betas, (list, tuple)) and len(betas) == 2 and all(0 <= float(b) < 1 for b in betas)):
        raise ValueError(f"betas must be two numbers in [0, 1), got {betas!r}")
    cfg["betas"] = [float(b) for b in betas]
    lam = cfg["lambdas"]
    if not (isinstance(lam, (list, tuple)) and len(lam) == 3 and all(float(x) >= 0 for x in lam)):
        raise ValueError(f"lambdas must be three non-negative weights (l1, l2, l3), got {lam!r}")
    cfg["lambdas"] = [float(x) for x in lam]
    if isinstance(cfg["seed"], bool) or not isinstance(cfg["seed"], (int, np.integer)) or cfg["seed"] < 0:
        raise ValueError(f"seed must be a non-negative integer, got {cfg['seed']!r}")
    cfg["seed"] = int(cfg["seed"])
    if not isinstance(cfg["dataset"], (str, os.PathLike)) or not str(cfg["dataset"]):
        raise ValueError(f"dataset must be a manifest name or a dataset directory, got {cfg['dataset']!r}")
    cfg["dataset"] = str(cfg["dataset"])
    if cfg["dataset_overrides"] is not None and not isinstance(cfg["dataset_overrides"], dict):
        raise ValueError(f"dataset_overrides must be a dict or None, got {cfg['dataset_overrides']!r}")
    if cfg["encoder_weights"] is not None:
        cfg["encoder_weights"] = str(cfg["encoder_weights"])
        if not Path(cfg["encoder_weights"]).is_file():
            raise FileNotFoundError(f"encoder_weights: no such file {cfg['encoder_weights']}")
    return cfg


def config_identity(cfg: dict) -> dict:
    """The entries of ``cfg`` that determine the trained weights (see IDENTITY_KEYS)."""
    return {k: cfg.get(k) for k in IDENTITY_KEYS}


def config_hash(cfg: dict) -> str:
    """8 hex digits naming a configuration (cache directory suffix)."""
    blob = json.dumps(config_identity(cfg), sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:8]


# --------------------------------------------------------------------------- data


def resolve_dataset(cfg: dict, progress: bool = False) -> Path:
    """The dataset directory of ``cfg``: an existing directory as is, else a manifest built on demand."""
    path = Path(cfg["dataset"]).expanduser()
    if path.is_dir() and (path / "manifest.json").exists():
        return path
    from geodepth_lite import synth

    return Path(synth.ensure_dataset(cfg["dataset"], overrides=cfg.get("dataset_overrides"), progress=progress))


class MemoryDataset(torch.utils.data.Dataset):
    """A split decoded and resized once: tensors in memory, the same item dicts as the source."""

    def __init__(self, items: list[dict]):
        self.image = torch.stack([it["image"] for it in items])
        self.depth = torch.stack([it["depth"] for it in items])
        self.K = torch.stack([torch.as_tensor(it["K"], dtype=torch.float32) for it in items])
        self.valid = torch.stack([it["valid"] for it in items]) if items and "valid" in items[0] else None
        self.organ = [it.get("organ", "") for it in items]
        self.group = [it.get("group", "") for it in items]
        self.index = [int(it.get("index", i)) for i, it in enumerate(items)]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        item = {"image": self.image[i], "depth": self.depth[i], "K": self.K[i],
                "organ": self.organ[i], "group": self.group[i], "index": self.index[i]}
        if self.valid is not None:
            item["valid"] = self.valid[i]
        return item


_MEMORY_CACHE: dict[tuple, MemoryDataset] = {}


def load_split(root: Path, split: str, image_size: int | None, *, cache: str | bool = "auto",
               limit: int | None = None):
    """``SyntheticDepthDataset(root, split, image_size)`` (``limit``: that many evenly spaced
    frames), decoded once and kept in memory when small (per process, reused across runs)."""
    from geodepth_lite.dataset import SyntheticDepthDataset

    ds = SyntheticDepthDataset(root, split, image_size=image_size)
    if limit is not None and limit < len(ds):
        # evenly spaced frames, so a subset still covers every scene, organ and lighting
        ds = torch.utils.data.Subset(ds, np.linspace(0, len(ds) - 1, limit).round().astype(int).tolist())
    if cache == "auto":
        n = len(ds)
        side = image_size or 320
        cache = n * 4 * side * side * 4 < CACHE_LIMIT_BYTES
    if not cache:
        return ds
    stamp = (root / split / "frames.jsonl").stat().st_mtime_ns if (root / split / "frames.jsonl").exists() else 0
    key = (str(Path(root).resolve()), split, image_size, limit, stamp)
    if key not in _MEMORY_CACHE:
        _MEMORY_CACHE[key] = MemoryDataset([ds[i] for i in range(len(ds))])
    return _MEMORY_CACHE[key]


def _collate(batch: list[dict]) -> dict:
    out = {}
    for key in batch[0]:
        values = [b[key] for b in batch]
        if isinstance(values[0], torch.Tensor):
            out[key] = torch.stack(values)
        elif isinstance(values[0], np.ndarray):
            out[key] = torch.from_numpy(np.stack(values))
        elif isinstance(values[0], (int, float)):
            out[key] = torch.tensor(values)
        else:
            out[key] = values
    return out


# --------------------------------------------------------------------------- distributed


def _dist_env() -> tuple[int, int, int]:
    """(rank, world_size, local_rank) from torchrun's environment; (0, 1, 0) otherwise."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0"))


def _init_distributed(device: torch.device) -> bool:
    import torch.distributed as dist

    rank, world, _ = _dist_env()
    if world <= 1:
        return False
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)  # one GPU per process (LOCAL_RANK), before nccl starts
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return True


def pick_device(device: str | torch.device | None = None) -> torch.device:
    """CUDA when available (one GPU per torchrun process), else the CPU."""
    if device is not None:
        return torch.device(device)
    if torch.cuda.is_available():
        return torch.device("cuda", _dist_env()[2] % torch.cuda.device_count())
    return torch.device("cpu")


# --------------------------------------------------------------------------- checkpoints


def _rng_state(loader_gen: torch.Generator) -> dict:
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
        "loader_generator": loader_gen.get_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict, loader_gen: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    loader_gen.set_state(state["loader_generator"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict) -> None:
    """``torch.save`` to a temporary file, then rename: an interrupted save leaves the old file whole."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    utils.write_bytes_atomic(path, buf.getvalue())


def read_checkpoint(path: str | os.PathLike) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise ValueError(f"checkpoint {path} is unreadable: {exc}") from None
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise ValueError(f"checkpoint {path} lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    return ckpt


def _write_logs(run_dir: Path, cfg: dict, history: list[dict]) -> None:
    """log.json (config + one row per epoch) and log.csv (the same rows), both atomic."""
    utils.write_json_atomic(run_dir / LOG_JSON, {"cfg": cfg, "epochs": history})
    if not history:
        return
    fields = list(history[0])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    utils.write_bytes_atomic(run_dir / LOG_CSV, buf.getvalue().encode())


def read_log(run_dir: str | os.PathLike) -> list[dict]:
    """The per-epoch rows of ``log.json`` in ``run_dir`` (or beside a checkpoint file)."""
    p = Path(run_dir)
    if p.is_file():
        p = p.parent
    return json.loads((p / LOG_JSON).read_text())["epochs"]


# --------------------------------------------------------------------------- the loop


def _autocast(device: torch.device):
    if device.type == "cuda":
        dtype = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        return torch.autocast("cuda", dtype=dtype)
    return contextlib.nullcontext()


def _losses(pred, batch, cfg):
    from geodepth_lite.losses import total_loss

    g = cfg["sdf_grid"]
    return total_loss(pred.float(), batch["depth"], batch["image"], batch["K"],
                      lambdas=tuple(cfg["lambdas"]), mask=batch.get("valid"), sdf_grid=(g, g, g),
                      depth_term=cfg.get("depth_term", "l1"))


def _term_gradient_norms(pred, batch, cfg) -> dict[str, float]:
    """Each loss term's gradient norm at the network output (logged once per epoch, first batch)."""
    from geodepth_lite.losses import term_gradient_norms

    g = cfg["sdf_grid"]
    return term_gradient_norms(pred, batch["depth"], batch["image"], batch["K"], mask=batch.get("valid"),
                               sdf_grid=(g, g, g), depth_term=cfg.get("depth_term", "l1"))


def augment_batch(batch: dict, kind: str) -> dict:
    """Training-time augmentation, drawn from torch's global RNG (saved in checkpoints, so resume repeats it).

    flip: each frame mirrored left-right with probability 1/2; image, depth and validity are
    flipped and K follows (cx -> W - 1 - cx), so the frame stays a valid pinhole view.
    flip_color: flip, then a per-frame gain in [0.7, 1.4] and gamma in [0.8, 1.25] on the image
    (exposure and camera response; the depth is unchanged).
    camera: flip, then per frame the appearance effects of ``CAMERA_AUGMENT`` (exposure, gamma,
    colour cast, vignetting, flecks, noise, blur, JPEG; ``appearance.apply_appearance``) on the
    image quantized to 8 bits, as a camera would deliver it.
    crop: flip, then per frame a random crop (side CROP_SCALE of the frame's, anywhere in it)
    scaled back to the frame's size, K following (``random_crop_batch``): what lies at the image
    border changes from view to view, so the network cannot learn "near at the border".
    """
    if kind == "none":
        return batch
    img, depth = batch["image"], batch["depth"]
    B, W = img.shape[0], img.shape[-1]
    flip = torch.rand(B) < 0.5
    out = dict(batch)
    if bool(flip.any()):
        f = flip.to(img.device).view(B, 1, 1, 1)
        out["image"] = torch.where(f, img.flip(-1), img)
        out["depth"] = torch.where(f, depth.flip(-1), depth)
        if batch.get("valid") is not None:
            out["valid"] = torch.where(f, batch["valid"].flip(-1), batch["valid"])
        K = batch["K"].clone()
        K[flip.to(K.device), 0, 2] = (W - 1) - K[flip.to(K.device), 0, 2]
        out["K"] = K
    if kind == "crop":
        out = random_crop_batch(out, CROP_SCALE)
    if kind == "flip_color":
        gain = (0.7 + 0.7 * torch.rand(B)).to(img).view(B, 1, 1, 1)
        gamma = torch.exp(torch.empty(B).uniform_(np.log(0.8), np.log(1.25))).to(img).view(B, 1, 1, 1)
        out["image"] = (out["image"].clamp(0, 1) ** gamma * gain).clamp(0, 1)
    if kind == "camera":
        from geodepth_lite import appearance

        params = dict(appearance.APPEARANCE_DEFAULTS, **CAMERA_AUGMENT)
        seeds = torch.randint(0, 2**31 - 1, (B,)).tolist()
        frames = (out["image"].detach().clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy() * 255.0).round().astype(np.uint8)
        looks = [appearance.sample_appearance(params, np.random.default_rng(sd)) for sd in seeds]
        done = np.stack([appearance.apply_appearance(f, look) for f, look in zip(frames, looks)])
        out["image"] = torch.from_numpy(done).permute(0, 3, 1, 2).to(img).div(255.0)
    return out


def random_crop_batch(batch: dict, scale: tuple[float, float]) -> dict:
    """Each frame cropped to a random window (side ``s`` x the frame's, s uniform in ``scale``,
    integer offsets) and resized back: image bilinear, depth and validity nearest-exact (no depth
    is invented across an edge), K shifted by the offset and scaled (``camera.scale_intrinsics``).
    Draws from torch's global RNG."""
    from geodepth_lite.camera import scale_intrinsics

    img = batch["image"]
    B, _, H, W = img.shape
    s = torch.empty(B).uniform_(*scale).tolist()
    u = torch.rand(B, 2).tolist()
    images, depths, valids, Ks = [], [], [], []
    for j in range(B):
        ch, cw = max(1, round(s[j] * H)), max(1, round(s[j] * W))
        y0, x0 = int(u[j][0] * (H - ch + 1)), int(u[j][1] * (W - cw + 1))
        win = (slice(None), slice(y0, y0 + ch), slice(x0, x0 + cw))
        images.append(F.interpolate(img[j][win][None], size=(H, W), mode="bilinear", align_corners=False)[0])
        depths.append(F.interpolate(batch["depth"][j][win][None], size=(H, W), mode="nearest-exact")[0])
        if batch.get("valid") is not None:
            v = batch["valid"][j][win][None].float()
            valids.append(F.interpolate(v, size=(H, W), mode="nearest-exact")[0] > 0.5)
        K = batch["K"][j].detach().cpu().double().numpy().copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        Ks.append(torch.from_numpy(scale_intrinsics(K, W / cw, H / ch)).to(batch["K"]))
    out = dict(batch, image=torch.stack(images).clamp_(0, 1), depth=torch.stack(depths), K=torch.stack(Ks))
    if valids:
        out["valid"] = torch.stack(valids)
    return out


def _to(batch: dict, device: torch.device) -> dict:
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}


@torch.no_grad()
def validate(model, dataset, cfg: dict, device: torch.device, batch_size: int | None = None) -> dict:
    """Mean validation loss terms and the seven metrics (median scaling) over ``dataset``."""
    from geodepth_lite.metrics import compute_depth_metrics

    model.eval()
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size or cfg["batch_size"], shuffle=False,
                                         collate_fn=_collate)
    sums = {k: 0.0 for k in LOSS_KEYS}
    n = 0
    preds, gts = [], []
    for batch in loader:
        batch = _to(batch, device)
        with _autocast(device):
            pred = model(batch["image"])
        _, terms = _losses(pred, batch, cfg)
        b = batch["image"].shape[0]
        for k in LOSS_KEYS:
            sums[k] += float(terms.get(k, 0.0)) * b
        n += b
        preds.append(pred.float()[:, 0].cpu())
        gts.append(batch["depth"][:, 0].cpu())
    out = {f"val_{k}": sums[k] / max(n, 1) for k in LOSS_KEYS}
    if n:
        m = compute_depth_metrics(torch.cat(preds).numpy(), torch.cat(gts).numpy())
        out.update({f"val_{k}": float(m[k]) for k in METRIC_KEYS})
    return out


def fit(cfg: dict, run_dir: str | os.PathLike, *, resume: bool = False, progress: bool = True,
        device: str | torch.device | None = None, num_workers: int | None = None,
        cache: str | bool = "auto", stop_after: int | None = None) -> Path:
    """Train DepthNet with ``cfg`` (see ``make_config``) into ``run_dir``; return the checkpoint path.

    resume: continue from ``run_dir/checkpoint.pt`` when it exists (same configuration
        required); without it an existing checkpoint is an error, so nothing is overwritten.
    stop_after: stop after this many epochs of this call (used to test resuming).
    The checkpoint dict holds "model", "optimizer", "scaler", "schedule", "cfg", "epoch" (epochs done),
    "complete", "rng" and "history" (the per-epoch log rows).
    """
    cfg = validate_config(cfg)
    threads_before = torch.get_num_threads()
    if cfg["threads"] and pick_device(device).type == "cpu":
        # CPU results depend on the thread count (parallel reductions): fixing it makes a run
        # repeatable on any machine with the same CPU instruction set.
        torch.set_num_threads(cfg["threads"])
    try:
        return _fit(cfg, Path(run_dir), resume=resume, progress=progress, device=device,
                    num_workers=num_workers, cache=cache, stop_after=stop_after)
    finally:
        torch.set_num_threads(threads_before)


def _fit(cfg, run_dir, *, resume, progress, device, num_workers, cache, stop_after) -> Path:
    from geodepth_lite.model import DepthNet

    device = pick_device(device)
    distributed = _init_distributed(device)
    rank, world, _ = _dist_env()
    is_main = rank == 0
    ckpt_path = run_dir / CHECKPOINT_NAME

    state = None
    if ckpt_path.exists():
        if not resume:
            raise FileExistsError(f"{ckpt_path} exists: pass --resume to continue it, or choose another --run-dir")
        state = read_checkpoint(ckpt_path)
        if config_identity(validate_config(state["cfg"])) != config_identity(cfg):
            diff = [k for k in IDENTITY_KEYS if state["cfg"].get(k) != cfg.get(k)]
            raise ValueError(f"cannot resume {ckpt_path}: its configuration differs in {', '.join(diff)}")
        if state["epoch"] >= cfg["epochs"]:
            return ckpt_path

    # data (rank 0 builds a missing dataset; the others wait for it)
    if is_main:
        root = resolve_dataset(cfg, progress=progress)
    if distributed:
        torch.distributed.barrier()
    if not is_main:
        root = resolve_dataset(cfg, progress=False)
    train_ds = load_split(root, "train", cfg["image_size"], cache=cache, limit=cfg["train_frames"])
    val_ds = load_split(root, "val", cfg["image_size"], cache=cache, limit=cfg["val_frames"]) if is_main else None
    if len(train_ds) == 0:
        raise ValueError(f"dataset {root} has no training frames")
    in_memory = isinstance(train_ds, MemoryDataset)
    if num_workers is None:
        num_workers = 0 if in_memory else min(4, os.cpu_count() or 1)

    utils.seed_everything(cfg["seed"])
    model = DepthNet(encoder_weights=cfg["encoder_weights"], padding=cfg["padding"]).to(device)
    opt_cls = torch.optim.AdamW if cfg["optimizer"] == "adamw" else torch.optim.Adam
    opt = opt_cls(model.parameters(), lr=cfg["lr"], betas=tuple(cfg["betas"]), weight_decay=cfg["weight_decay"])
    scaler = torch.amp.GradScaler("cuda", enabled=device.type == "cuda" and not torch.cuda.is_bf16_supported())
    sampler = torch.utils.data.DistributedSampler(train_ds, num_replicas=world, rank=rank, shuffle=True,
                                                  seed=cfg["seed"], drop_last=False)
    loader_gen = torch.Generator().manual_seed(cfg["seed"])
    loader = torch.utils.data.DataLoader(
        train_ds, batch_size=cfg["batch_size"], sampler=sampler, num_workers=num_workers,
        collate_fn=_collate, worker_init_fn=utils.worker_init, generator=loader_gen,
        pin_memory=device.type == "cuda", persistent_workers=False)

    total_steps = cfg["epochs"] * len(loader)
    if cfg["lr_schedule"] == "cosine":  # half a cosine from lr to 0 over all steps
        schedule = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: 0.5 * (1 + math.cos(math.pi * step / total_steps)))
    else:
        schedule = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: 1.0)
    history: list[dict] = []
    start = 0
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
        scaler.load_state_dict(state["scaler"])
        _set_rng_state(state["rng"], loader_gen)
        history = list(state["history"])
        start = int(state["epoch"])
    net = torch.nn.parallel.DistributedDataParallel(model) if distributed else model

    from tqdm.auto import tqdm

    done_this_call = 0
    for epoch in range(start, cfg["epochs"]):
        sampler.set_epoch(epoch)
        net.train()
        sums = torch.zeros(len(LOSS_KEYS) + 1, dtype=torch.float64)
        wait = step_total = 0.0
        bar = tqdm(total=len(loader), desc=f"epoch {epoch + 1}/{cfg['epochs']}", disable=not (progress and is_main),
                   leave=False)
        t_epoch = tick = time.perf_counter()
        grad_norms: dict[str, float] = {}
        for batch in loader:
            got = time.perf_counter()
            batch = augment_batch(_to(batch, device), cfg["augment"])
            with _autocast(device):
                pred = net(batch["image"])
            loss, terms = _losses(pred, batch, cfg)
            if not grad_norms:  # the first step of the epoch (at initialisation in epoch 1)
                grad_norms = _term_gradient_norms(pred, batch, cfg)
            opt.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(opt)
            scaler.update()
            schedule.step()
            b = batch["image"].shape[0]
            sums[:-1] += torch.tensor([float(terms.get(k, 0.0)) * b for k in LOSS_KEYS], dtype=torch.float64)
            sums[-1] += b
            now = time.perf_counter()
            wait += got - tick
            step_total += now - tick
            tick = now
            bar.set_postfix(loss=f"{loss.item():.4f}")
            bar.update()
        bar.close()
        if distributed:
            torch.distributed.all_reduce(sums)
        row: dict[str, Any] = {"epoch": epoch + 1}
        row.update({f"train_{k}": float(sums[i] / max(sums[-1], 1)) for i, k in enumerate(LOSS_KEYS)})
        if is_main:
            row.update(validate(model, val_ds, cfg, device))
        row.update({f"gradnorm_{k}": v for k, v in grad_norms.items()})
        row["lr"] = opt.param_groups[0]["lr"]
        row["epoch_s"] = time.perf_counter() - t_epoch
        row["train_frames_per_s"] = float(sums[-1]) / max(step_total, 1e-9)
        row["data_wait_share"] = wait / max(step_total, 1e-9)
        history.append(row)
        if is_main:
            save_checkpoint(ckpt_path, {
                "model": model.state_dict(),
                "optimizer": opt.state_dict(),
                "scaler": scaler.state_dict(),
                "schedule": schedule.state_dict(),
                "cfg": cfg,
                "epoch": epoch + 1,
                "complete": epoch + 1 == cfg["epochs"],
                "rng": _rng_state(loader_gen),
                "history": history,
                "world_size": world,
            })
            _write_logs(run_dir, cfg, history)
        if distributed:
            torch.distributed.barrier()
        done_this_call += 1
        if stop_after is not None and done_this_call >= stop_after:
            break
    return ckpt_path


# --------------------------------------------------------------------------- cached runs and inference


def checkpoint_dir(profile: str, case: int = 4, seed: int = 0, **overrides: Any) -> Path:
    """Where ``ensure_checkpoint`` keeps the run: runs/<profile>/checkpoints/case<c>_seed<s>-<cfg hash>."""
    cfg = make_config(profile, case, seed, **overrides)
    return utils.runs_dir() / profile / "checkpoints" / f"case{case}_seed{seed}-{config_hash(cfg)}"


def ensure_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False,
                      **overrides: Any) -> Path:
    """The checkpoint of ``case``/``seed`` under ``profile``: reused when a run with the same
    configuration finished, continued when it was interrupted, trained otherwise."""
    cfg = make_config(profile, case, seed, **overrides)
    run_dir = checkpoint_dir(profile, case, seed, **overrides)
    path = run_dir / CHECKPOINT_NAME
    if path.exists():
        ckpt = read_checkpoint(path)
        if ckpt.get("complete") and config_identity(ckpt["cfg"]) == config_identity(cfg):
            return path
    return fit(cfg, run_dir, resume=True, progress=progress)


def predict_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False) -> Path:
    """The checkpoint of the model that notebooks 04, 06, 07 and ``predict`` use: ``case``/``seed``
    trained at the profile's ``predict_image_size`` (the ablation's runs use ``image_size``)."""
    size = config.get_profile(profile)["predict_image_size"]
    return ensure_checkpoint(profile, case, seed, progress=progress, image_size=size)


def _complete(profile: str, case: int, seed: int, overrides: dict) -> bool:
    path = checkpoint_dir(profile, case, seed, **overrides) / CHECKPOINT_NAME
    if not path.exists():
        return False
    ckpt = read_checkpoint(path)
    return bool(ckpt.get("complete")) and config_identity(ckpt["cfg"]) == config_identity(
        make_config(profile, case, seed, **overrides))


def ensure_checkpoints(profile: str, runs: list[tuple[int, int]], *, workers: int | None = None,
                       **overrides: Any) -> dict[tuple[int, int], Path]:
    """``ensure_checkpoint`` for several (case, seed) runs, trained side by side in processes.

    With a fixed per-run thread count (``threads`` in the profile) each run gives the same
    weights whether it trains alone or beside others; ``workers`` defaults to
    cpu_count // threads. Returns {(case, seed): checkpoint path}.
    """
    runs = [(int(c), int(s)) for c, s in runs]
    todo = [r for r in runs if not _complete(profile, *r, overrides)]
    if todo:
        resolve_dataset(make_config(profile, *todo[0], **overrides))  # build it once, before any worker
        threads = make_config(profile, *todo[0], **overrides)["threads"]
        if workers is None:
            workers = max(1, (os.cpu_count() or 1) // threads) if threads else 1
        workers = max(1, min(workers, len(todo)))
        if workers == 1:
            for case, seed in todo:
                ensure_checkpoint(profile, case, seed, **overrides)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(ensure_checkpoint, profile, case, seed, **overrides) for case, seed in todo]
                for f in futures:
                    f.result()
    return {(c, s): checkpoint_dir(profile, c, s, **overrides) / CHECKPOINT_NAME for c, s in runs}


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """(DepthNet in eval mode on ``device``, its training cfg) from a checkpoint file."""
    from geodepth_lite.model import DepthNet

    ckpt = read_checkpoint(path)
    model = DepthNet(padding=ckpt["cfg"].get("padding", "zeros"))
    model.load_state_dict(ckpt["model"])
    return model.to(device).eval(), dict(ckpt["cfg"])


@torch.no_grad()
def predict_depth(model, images: torch.Tensor, image_size: int | tuple[int, int] | None = None) -> torch.Tensor:
    """Depth B x 1 x H x W for images B x 3 x H x W in [0, 1]: resized (dataset.resize_image) to the
    network's ``image_size`` (int or (h, w), multiples of 32), predicted, resized back."""
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be B x 3 x H x W, got shape {tuple(images.shape)}")
    H, W = images.shape[-2:]
    if image_size is None:
        size = (H, W)
    elif isinstance(image_size, int):
        size = (image_size, image_size)
    else:
        size = tuple(int(s) for s in image_size)
    device = next(model.parameters()).device
    x = images.to(device=device, dtype=torch.float32)
    x = resize_image(x, size)  # as the training frames were made (antialiased)
    was_training = model.training
    model.eval()
    pred = model(x).float()
    model.train(was_training)
    if pred.shape[-2:] != (H, W):
        pred = F.interpolate(pred, size=(H, W), mode="bilinear", align_corners=False)
    return pred


# --------------------------------------------------------------------------- CLI


def add_arguments_train(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="teach", help="smoke | teach | paper (default teach)")
    parser.add_argument("--case", type=int, default=4, help="ablation case 1-4 (Section 4.3; default 4 = all losses)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--run-dir", default=None,
                        help="where checkpoint.pt and log.csv/log.json go (default runs/<profile>/train/case<c>_seed<s>)")
    parser.add_argument("--resume", action="store_true", help="continue the checkpoint in --run-dir")
    parser.add_argument("--epochs", type=int, default=None, help="override the profile's epochs")
    parser.add_argument("--batch-size", type=int, default=None, help="override the profile's batch size")
    parser.add_argument("--lr", type=float, default=None, help="override the profile's learning rate")
    parser.add_argument("--lr-schedule", default=None, choices=LR_SCHEDULES, help="override the profile's schedule")
    parser.add_argument("--image-size", type=int, default=None, help="override the network input size (multiple of 32)")
    parser.add_argument("--dataset", default=None, help="manifest name or dataset directory (default: the profile's)")
    parser.add_argument("--encoder-weights", default=None,
                        help="torchvision-style resnet18 ImageNet state dict (.pth) for the encoder")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: CUDA when available)")
    parser.add_argument("--num-workers", type=int, default=None, help="DataLoader workers (default: 0 when cached)")
    parser.add_argument("--no-cache", action="store_true", help="stream from disk instead of caching the dataset in memory")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_train(args: argparse.Namespace) -> int:
    cfg = make_config(args.profile, args.case, args.seed, epochs=args.epochs, batch_size=args.batch_size,
                      lr=args.lr, lr_schedule=args.lr_schedule, image_size=args.image_size, dataset=args.dataset,
                      encoder_weights=args.encoder_weights)
    run_dir = Path(args.run_dir) if args.run_dir else utils.runs_dir() / args.profile / "train" / f"case{args.case}_seed{args.seed}"
    path = fit(cfg, run_dir, resume=args.resume, progress=not args.no_progress, device=args.device,
               num_workers=args.num_workers, cache=False if args.no_cache else "auto")
    if _dist_env()[0] == 0:
        rows = read_log(run_dir)
        last = rows[-1] if rows else {}
        summary = ", ".join(f"{k} {last[k]:.4f}" for k in ("train_total", "val_total", "val_abs_rel", "val_rmse") if k in last)
        print(f"checkpoint: {path} (epoch {last.get('epoch', '?')}/{cfg['epochs']}; {summary})")
        if last:
            print(f"data wait: {100 * last['data_wait_share']:.1f}% of step time")
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    return 0
