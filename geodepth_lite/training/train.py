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

The loop reads top to bottom as ``fit`` -> ``run_epoch`` -> ``process_batch`` ->
``compute_losses``. Around it: ``config.make_config`` (the settings), ``checkpoint``
(saving, resuming, cached runs), ``inference`` (device, batching, ``predict_depth``),
``augment`` (training-time augmentation) and ``losses.LOSS_TERMS`` (the terms).
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.core import losses
from geodepth_lite.core.errors import UserError
from geodepth_lite.core.metrics import METRIC_NAMES, frame_metrics_torch
from geodepth_lite.core.model import DepthNet
from geodepth_lite.data import integrity
from geodepth_lite.data.augment import augment_batch
from geodepth_lite.data.datasets import (
    DeviceBatches,
    DeviceSplit,
    MemoryDataset,
    load_split,
    read_frames,
    resolve_dataset,
)
from geodepth_lite.training import checkpoint as ckpt_io
from geodepth_lite.training import config, distributed, inference, provenance


def log_keys() -> tuple[str, ...]:
    """The loss columns of the training log: every term of ``losses.LOSS_TERMS``, then the weighted total."""
    return (*losses.term_names(), "total")


def get_lr_factor(step: int, total_steps: int, schedule: str) -> float:
    """The learning rate at optimizer ``step`` as a share of ``cfg["lr"]``.

    constant (the paper): 1 throughout. cosine: half a cosine from 1 to 0 over all steps.
    """
    if schedule == "cosine":
        return 0.5 * (1 + math.cos(math.pi * step / total_steps))
    return 1.0


def in_depth_unit(pred: torch.Tensor, depth: torch.Tensor, cfg: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """(prediction, ground truth) as the losses see them: divided by ``cfg["depth_unit"]`` (untouched at 1)."""
    unit = cfg.get("depth_unit", 1.0)
    return (pred, depth) if unit == 1.0 else (pred / unit, depth / unit)


def compute_losses(pred: torch.Tensor, batch: dict, cfg: dict, frame_ids=None):
    """(weighted total, {term: value}) of ``losses.total_loss`` for a batch, in float32, in the
    configuration's depth unit (``in_depth_unit``), with its loss settings (``config.loss_spec``).
    ``frame_ids``: see :func:`batch_frame_ids`."""
    pred, depth = in_depth_unit(pred.float(), batch["depth"], cfg)
    return losses.total_loss(pred, depth, batch["image"], batch["K"], config.loss_spec(cfg),
                             mask=batch.get("valid"), frame_ids=frame_ids)


def frame_space(root, split: str, image_size) -> tuple:
    """What names a split's frames apart from their index: the dataset folder, the split, the size they are
    resized to, and when the split's frame list was written (a dataset written anew gets new ids)."""
    root = Path(root).resolve()
    listing = root / split / "frames.jsonl"
    return (str(root), split, image_size, listing.stat().st_mtime_ns if listing.exists() else 0)


def batch_frame_ids(batch: dict, space: tuple | None) -> list | None:
    """One id per frame of a batch as the loader gives it (before augmentation, its "index" on the host),
    keying the cached ground-truth SDF fields (``losses.sdf_loss``) by the frame's identity: no copy of the
    frames to the host and no hash. None (key by content) without ``space`` or an "index"."""
    index = batch.get("index")
    if space is None or index is None:
        return None
    return [(*space, int(i)) for i in (index.tolist() if isinstance(index, torch.Tensor) else index)]


def term_gradient_norms(pred: torch.Tensor, batch: dict, cfg: dict, frame_ids=None) -> dict[str, float]:
    """The gradient norm at the network output of each weighted loss term (logged once per epoch, on
    the first batch); a term whose weight is zero is not evaluated, and its ``gradnorm_`` column is
    absent from the log. The loss settings are the configuration's (``config.loss_spec``)."""
    pred, depth = in_depth_unit(pred, batch["depth"], cfg)
    return losses.term_gradient_norms(pred, depth, batch["image"], batch["K"], config.loss_spec(cfg),
                                      mask=batch.get("valid"), frame_ids=frame_ids)


@torch.no_grad()
def validate(model, dataset, cfg: dict, device: torch.device, batch_size: int | None = None,
             space: tuple | None = None) -> dict:
    """Mean validation loss terms and the seven metrics (median scaling) over ``dataset``.

    The metrics are computed per frame on ``device`` (``metrics.frame_metrics_torch``, the numbers of
    ``metrics.compute_depth_metrics``) and read to the host once, at the end. The SDF term is evaluated
    only where ``cfg["val_sdf"]`` (the teach and smoke profiles, whose notebooks plot it; the paper
    profile leaves it out, and its ``val_sdf`` and ``val_total`` read NaN). ``space``: names the split's
    frames (:func:`frame_space`), so cached ground-truth fields are keyed by frame id. Nothing here
    draws a random number or changes the model's weights."""
    model.eval()
    bs = batch_size or cfg["batch_size"]
    if isinstance(dataset, DeviceSplit):
        torch.empty((), dtype=torch.int64).random_()  # the draw a DataLoader makes (its base seed): the same run
        loader = dataset.batches(bs)
    else:
        loader = torch.utils.data.DataLoader(dataset, batch_size=bs, shuffle=False, collate_fn=inference.collate)
    keys = log_keys()
    skip_sdf = not cfg.get("val_sdf", True) and losses.group_weights(cfg["lambdas"])["lambda3"] > 0
    vcfg = cfg if not skip_sdf else {**cfg, "lambdas": [*cfg["lambdas"][:2], 0.0]}
    sums = {k: 0.0 for k in keys}
    n = 0
    per_frame: list[dict] = []
    for batch in loader:
        ids = batch_frame_ids(batch, space)
        batch = inference.to_device(batch, device)
        with inference.autocast(device):
            pred = model(batch["image"])  # (B, 1, H, W)
        _, terms = compute_losses(pred, batch, vcfg, ids)
        b = batch["image"].shape[0]
        for k in keys:
            sums[k] += float(terms.get(k, 0.0)) * b
        n += b
        per_frame.append(frame_metrics_torch(pred.float(), batch["depth"]))
    out = {f"val_{k}": sums[k] / max(n, 1) for k in keys}
    if skip_sdf:
        out["val_sdf"] = out["val_total"] = float("nan")  # not evaluated: the weighted total lacks a term
    if n:
        out.update(_metric_means(per_frame))
    return out


def _metric_means(per_frame: list[dict]) -> dict:
    """The seven metrics' means over the frames with a valid pixel, from per-batch
    ``metrics.frame_metrics_torch`` results (one read to the host); the numpy protocol's errors."""
    cat = {k: torch.cat([f[k] for f in per_frame]) for k in (*METRIC_NAMES, "used", "bad")}
    used, bad = cat["used"], cat["bad"]
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise UserError(f"pred frame {i} cannot be scored: a non-finite or non-positive depth on valid pixels")
    if not bool(used.any()):
        raise UserError("no valid ground-truth pixel in any frame")
    means = torch.stack([cat[k][used].mean() for k in METRIC_NAMES]).tolist()
    return {f"val_{k}": v for k, v in zip(METRIC_NAMES, means)}


def build_network(cfg: dict, network=None) -> torch.nn.Module:
    """The network ``fit`` trains: ``DepthNet`` when ``network`` is None; else ``network``, either a
    class taking DepthNet's keyword arguments (``encoder_weights``, ``padding``, ``input_pad``), such
    as a DepthNet subclass, or a callable ``(cfg) -> nn.Module``. Its initial weights are drawn from
    the random generators as they stand (``fit`` seeds them first)."""
    network = DepthNet if network is None else network
    if not isinstance(network, type):
        return network(cfg)
    extra = {} if cfg.get("head_range") is None else {"depth_range": tuple(cfg["head_range"])}
    return network(encoder_weights=cfg["encoder_weights"], padding=cfg["padding"], input_pad=cfg["input_pad"],
                   **extra)


def fit(cfg: dict, run_dir: str | os.PathLike, *, resume: bool = False, progress: bool = True,
        device: str | torch.device | None = None, num_workers: int | None = None,
        cache: str | bool = "auto", stop_after: int | None = None, network=None, device_data: bool | None = None,
        keep_best: bool = False, channels_last: bool = False) -> Path:
    """Train DepthNet with ``cfg`` (see ``config.make_config``) into ``run_dir``; return the checkpoint path.

    resume: continue from ``run_dir/checkpoint.pt`` when it exists (same configuration
        required); without it an existing checkpoint is an error, so nothing is overwritten.
    stop_after: stop after this many epochs of this call (used to test resuming).
    network: train this network instead of DepthNet (see ``build_network``); None (the default)
        trains DepthNet, with the same weights as ever. The configuration does not record it: a run
        folder holds one network, and its checkpoint loads into that network (``checkpoint.load_weights``).
    device_data: keep both splits decoded on the training device (``datasets.DeviceSplit``) and gather each
        batch there; None (the default): on CUDA where they take at most a quarter of its free memory. The
        batches, their order and every random draw are the loader's: the same run either way.
    keep_best: also keep ``best.pt``, a copy of the checkpoint of the epoch with the least validation Abs Rel
        so far (a model chosen on the validation split; ``checkpoint.pt`` stays the last epoch's).
    channels_last: the network and its input in ``torch.channels_last`` memory format (on CUDA, tensor-core
        convolutions without layout changes); the same network and the same numbers up to rounding.
    The run's provenance records ``device_data`` and ``channels_last`` as used.
    """
    if network is not None and not callable(network):
        raise TypeError(f"network must be a class or a callable (cfg) -> nn.Module, got {network!r}")
    cfg = config.validate_config(cfg)
    threads_before = torch.get_num_threads()
    if cfg["threads"] and inference.pick_device(device).type == "cpu":
        # CPU results depend on the thread count (parallel reductions): fixing it makes a run
        # repeatable on any machine with the same CPU instruction set.
        torch.set_num_threads(cfg["threads"])
    try:
        options = {"device_data": device_data, "keep_best": bool(keep_best), "channels_last": bool(channels_last)}
        return Trainer(cfg, Path(run_dir), device=device, progress=progress, network=network, options=options).train(
            resume=resume, num_workers=num_workers, cache=cache, stop_after=stop_after)
    finally:
        torch.set_num_threads(threads_before)


def worker_batches(loader):
    """The batches of ``loader``; when the loop stops early (an error), its worker processes are shut
    down at once, so that they exit cleanly instead of being killed at interpreter exit. A worker
    too slow to stop is still killed; its temporary files go with the run's folder for them
    (``utils.worker_temp_dir``)."""
    batches = iter(loader)
    try:
        yield from batches
    finally:
        shutdown = getattr(batches, "_shutdown_workers", None)  # multi-process loaders only
        if shutdown is not None:
            shutdown()


BEST_NAME = "best.pt"  # keep_best: the checkpoint of the epoch with the least validation Abs Rel


class TrainingDiverged(UserError):
    """A non-finite loss or weight: training stops at once, naming the epoch, step, term and lr."""


class Trainer:
    """One training run: ``train`` -> ``run_epoch`` -> ``process_batch`` -> ``compute_losses``."""

    def __init__(self, cfg: dict, run_dir: Path, *, device=None, progress: bool = True, network=None,
                 options: dict | None = None):
        self.cfg, self.run_dir, self.network = cfg, run_dir, network
        self.device = inference.pick_device(device)
        self.distributed = distributed.init_distributed(self.device)
        self.rank, self.world, _ = distributed.dist_env()
        self.is_main = self.rank == 0
        self.progress = progress and self.is_main
        self.ckpt_path = run_dir / ckpt_io.CHECKPOINT_NAME
        # fit's run options: data on the device (None: where it fits), best.pt, channels_last
        self.options = {"device_data": None, "keep_best": False, "channels_last": False, **(options or {})}
        if self.device.type == "cuda":  # fixed image sizes: cuDNN picks each convolution's fastest algorithm once
            torch.backends.cudnn.benchmark = True

    def train(self, *, resume: bool, num_workers: int | None, cache, stop_after: int | None) -> Path:
        """Rank 0 holds the run folder's lock for the whole run (``checkpoint.run_folder``); the data
        loader's workers keep their temporary files in a folder removed when the run ends, however it
        ends (``utils.worker_temp_dir``, entered on ``self.stack`` by ``make_loader``)."""
        with contextlib.ExitStack() as self.stack:
            if self.is_main:
                self.stack.enter_context(ckpt_io.run_folder(self.run_dir))
            return self._train(resume=resume, num_workers=num_workers, cache=cache, stop_after=stop_after)

    def _train(self, *, resume: bool, num_workers: int | None, cache, stop_after: int | None) -> Path:
        cfg = self.cfg
        if self.is_main:  # half-written checkpoint/log files of a run killed while saving (under the lock only)
            stale = utils.remove_stale_temps(self.run_dir, locked=True)
            if stale:
                print(f"removed {stale} half-written temporary file(s) of an interrupted save in {self.run_dir}")
        # 1. an existing checkpoint: continue it (same configuration) or refuse to overwrite it
        state = None
        if self.ckpt_path.exists():
            if not resume:
                raise FileExistsError(f"{self.ckpt_path} exists: pass --resume to continue it, "
                                      "or choose another --run-dir")
            state = ckpt_io.read_checkpoint(self.ckpt_path, for_resume=True,
                                            limits=None if self.network is None else ckpt_io.ANY_NETWORK)
            self.check_state(state)  # before its epoch is compared, and again with the model's parameters
            saved = config.validate_config(state["cfg"])  # keys added since it was saved: at their defaults
            if config.config_identity(saved) != config.config_identity(cfg):
                diff = [k for k in config.IDENTITY_KEYS if saved.get(k) != cfg.get(k)]
                raise UserError(f"cannot resume {self.ckpt_path}: its configuration differs in {', '.join(diff)}")
            if state["epoch"] >= cfg["epochs"]:
                return self.ckpt_path
        # 2. data (rank 0 builds a missing dataset; the others wait for it)
        self.load_data(cache, num_workers)
        # 3. model, optimizer, learning-rate schedule, in the order that fixes the random draws
        utils.seed_everything(cfg["seed"])
        self.model = self.make_model(fresh=state is None)
        opt_cls = torch.optim.AdamW if cfg["optimizer"] == "adamw" else torch.optim.Adam
        self.opt = opt_cls(self.model.parameters(), lr=cfg["lr"], betas=tuple(cfg["betas"]),
                           weight_decay=cfg["weight_decay"])
        self.scaler = torch.amp.GradScaler(
            "cuda", enabled=self.device.type == "cuda" and not torch.cuda.is_bf16_supported())
        if self.is_main:  # room for the first checkpoint, before the first epoch
            utils.check_output_dir(self.run_dir, need_bytes=ckpt_io.checkpoint_bytes(self.model))
        self.make_loader()
        total_steps = cfg["epochs"] * len(self.loader)
        self.schedule = torch.optim.lr_scheduler.LambdaLR(
            self.opt, lambda step: get_lr_factor(step, total_steps, cfg["lr_schedule"]))
        # 4. resume: every state as it was after the last finished epoch
        self.history: list[dict] = []
        start = 0 if state is None else self.restore(state)
        # this session's provenance after the earlier sessions' (a resumed run keeps theirs)
        earlier = provenance.earlier_sessions(ckpt_io.read_log_file(self.run_dir)) if state is not None else []
        self.sessions = [*earlier, {**provenance.session(cfg, self.device, start),
                                    "device_data": self.device_data, "load_data_s": round(self.load_s, 2),
                                    "channels_last": self.options["channels_last"],
                                    **({"init_from_sha256": self.init_sha256} if self.init_sha256 else {})}]
        self.net = torch.nn.parallel.DistributedDataParallel(self.model) if self.distributed else self.model
        # 5. the epochs, a checkpoint after each
        for done, epoch in enumerate(range(start, cfg["epochs"]), start=1):
            self.history.append(self.run_epoch(epoch))
            if self.is_main:
                self.save(epoch)
                if self.options["keep_best"]:
                    self.keep_best()
            if self.distributed:
                torch.distributed.barrier()
            if stop_after is not None and done >= stop_after:
                break
        return self.ckpt_path

    def make_model(self, fresh: bool) -> torch.nn.Module:
        """The network on the device (in its memory format); a fresh run with ``init_from`` starts
        from that run's weights (``start_from``; its checkpoint's SHA-256 kept in ``init_sha256``)."""
        self.model = build_network(self.cfg, self.network).to(self.device)
        self.init_sha256 = self.start_from(self.cfg["init_from"]) if fresh and self.cfg["init_from"] else None
        if self.options["channels_last"]:
            self.model = self.model.to(memory_format=torch.channels_last)
        return self.model

    def start_from(self, name: str) -> str:
        """Fine-tuning: load the weights of the finished run folder ``name`` beside this run's (the
        configuration's ``init_from``); returns that checkpoint's SHA-256 for the provenance."""
        source = self.run_dir.parent / name / ckpt_io.CHECKPOINT_NAME
        if not source.is_file():
            raise UserError(f"init_from: no run {name} beside {self.run_dir}: train the run to fine-tune first")
        ckpt = ckpt_io.read_checkpoint(source, limits=None if self.network is None else ckpt_io.ANY_NETWORK)
        if not ckpt.get("complete"):
            raise UserError(f"init_from: {source} is not finished (epoch {ckpt.get('epoch')}): finish it first")
        if config.config_hash(config.validate_config(ckpt["cfg"])) != name.rsplit("-", 1)[1]:
            raise UserError(f"init_from: {source} holds a configuration other than the one its folder is named for")
        ckpt_io.load_weights(self.model, ckpt["model"], source)
        return integrity.file_sha256(source)

    def check_state(self, state: dict, params: list | None = None) -> None:
        """One line naming the checkpoint when its training state cannot be resumed
        (``checkpoint.training_state_problem``)."""
        problem = ckpt_io.training_state_problem(state, params)
        if problem:
            raise UserError(f"cannot resume {self.ckpt_path}: {problem} (written by something other than train, "
                             "or changed since)")

    def restore(self, state: dict) -> int:
        """Every state as it was after the checkpoint's last epoch; returns that epoch."""
        ckpt_io.load_weights(self.model, state["model"], self.ckpt_path)
        self.check_state(state, list(self.model.parameters()))
        try:
            self.opt.load_state_dict(state["optimizer"])
            self.schedule.load_state_dict(state["schedule"])
            self.scaler.load_state_dict(state["scaler"])
            ckpt_io.set_rng_state(state["rng"], self.loader_gen)
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise UserError(f"cannot resume {self.ckpt_path}: its optimizer, schedule or random state "
                             f"does not fit this run ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
        self.history = list(state["history"])
        if self.is_main:
            print(f"resuming {self.ckpt_path} after epoch {int(state['epoch'])}/{self.cfg['epochs']}")
        return int(state["epoch"])

    def load_data(self, cache, num_workers: int | None) -> None:
        cfg = self.cfg
        if self.is_main:
            root = resolve_dataset(cfg, progress=self.progress)
        if self.distributed:
            torch.distributed.barrier()
        if not self.is_main:
            root = resolve_dataset(cfg, progress=False)
        t0 = time.perf_counter()
        self.device_data = self.use_device_data(root)
        if self.device_data:
            self.train_ds = DeviceSplit(load_split(root, "train", cfg["image_size"], cache=False,
                                                   limit=cfg["train_frames"]), self.device)
            self.val_ds = (DeviceSplit(load_split(root, "val", cfg["image_size"], cache=False,
                                                  limit=cfg["val_frames"]), self.device) if self.is_main else None)
            if self.is_main and self.progress:
                print(f"decoded {len(self.train_ds)} + {len(self.val_ds)} frames onto {self.device} in "
                      f"{time.perf_counter() - t0:.1f} s")
        else:
            self.train_ds = load_split(root, "train", cfg["image_size"], cache=cache, limit=cfg["train_frames"])
            self.val_ds = (load_split(root, "val", cfg["image_size"], cache=cache, limit=cfg["val_frames"])
                           if self.is_main else None)
        self.load_s = time.perf_counter() - t0
        # frame ids key the cached ground-truth SDF fields where no augmentation changes a frame's ground truth
        self.spaces = {split: frame_space(root, split, cfg["image_size"]) for split in ("train", "val")}
        if len(self.train_ds) == 0:
            raise UserError(f"dataset {root} has no training frames")
        in_memory = isinstance(self.train_ds, (MemoryDataset, DeviceSplit))
        self.num_workers = utils.workers_fit_temp_dir(
            (0 if in_memory else min(4, os.cpu_count() or 1)) if num_workers is None else num_workers)

    def use_device_data(self, root) -> bool:
        """Whether both splits go onto the device (``fit``'s ``device_data``; None: CUDA, and they take at
        most a quarter of its free memory)."""
        asked = self.options["device_data"]
        if asked is not None:
            return bool(asked)
        if self.device.type != "cuda":
            return False
        cfg = self.cfg
        n = sum(min(len(read_frames(root, split)), cfg[f"{split}_frames"] or 1 << 62) for split in ("train", "val"))
        free, _ = torch.cuda.mem_get_info(self.device)
        return DeviceSplit.nbytes(n, cfg["image_size"]) <= free // 4

    def make_loader(self) -> None:
        cfg = self.cfg
        self.sampler = torch.utils.data.DistributedSampler(self.train_ds, num_replicas=self.world, rank=self.rank,
                                                           shuffle=True, seed=cfg["seed"], drop_last=False)
        self.loader_gen = torch.Generator().manual_seed(cfg["seed"])
        if self.device_data:
            self.loader = DeviceBatches(self.train_ds, self.sampler, cfg["batch_size"], self.loader_gen)
            return
        temp_dir = self.stack.enter_context(utils.worker_temp_dir(self.num_workers))
        self.loader = torch.utils.data.DataLoader(
            self.train_ds, batch_size=cfg["batch_size"], sampler=self.sampler, num_workers=self.num_workers,
            collate_fn=inference.collate, worker_init_fn=functools.partial(utils.worker_init, temp_dir=temp_dir),
            generator=self.loader_gen,
            pin_memory=self.device.type == "cuda", persistent_workers=False)

    def run_epoch(self, epoch: int) -> dict[str, Any]:
        """One pass over the training split, then validation; returns the epoch's log row."""
        cfg, keys = self.cfg, log_keys()
        self.sampler.set_epoch(epoch)
        self.net.train()
        sums = torch.zeros(len(keys) + 1, dtype=torch.float64)  # each term x frames, then frames
        wait = step_total = 0.0
        bar = tqdm(total=len(self.loader), desc=f"epoch {epoch + 1}/{cfg['epochs']}", disable=not self.progress,
                   leave=False)
        t_epoch = tick = time.perf_counter()
        grad_norms: dict[str, float] = {}
        for step, batch in enumerate(worker_batches(self.loader), start=1):
            got = time.perf_counter()
            loss, terms, pred, batch = self.process_batch(batch)
            if not bool(torch.isfinite(loss)):
                raise TrainingDiverged(self.divergence_message(epoch, step, terms))
            if not grad_norms:  # the first step of the epoch (at initialisation in epoch 1)
                grad_norms = term_gradient_norms(pred, batch, cfg, self.frame_ids(batch, "train"))
            self.step(loss)
            b = batch["image"].shape[0]
            sums[:-1] += torch.tensor([float(terms.get(k, 0.0)) * b for k in keys], dtype=torch.float64)
            sums[-1] += b
            now = time.perf_counter()
            wait += got - tick
            step_total += now - tick
            tick = now
            bar.set_postfix(loss=f"{loss.item():.4f}")
            bar.update()
        bar.close()
        bad = next((n for n, p in self.model.named_parameters() if not bool(torch.isfinite(p).all())), None)
        if bad is not None:  # the last step's update broke the weights: stop before validation fails on it
            raise TrainingDiverged(self.divergence_message(epoch, len(self.loader), {}, weight=bad))
        if self.distributed:
            torch.distributed.all_reduce(sums)
        row: dict[str, Any] = {"epoch": epoch + 1}
        row.update({f"train_{k}": float(sums[i] / max(sums[-1], 1)) for i, k in enumerate(keys)})
        if self.is_main:
            row.update(validate(self.model, self.val_ds, cfg, self.device, space=self.spaces["val"]))
        row.update({f"gradnorm_{k}": v for k, v in grad_norms.items()})
        row["lr"] = self.opt.param_groups[0]["lr"]
        row["epoch_s"] = time.perf_counter() - t_epoch
        row["train_frames_per_s"] = float(sums[-1]) / max(step_total, 1e-9)
        row["data_wait_share"] = wait / max(step_total, 1e-9)
        return row

    def divergence_message(self, epoch: int, step: int, terms: dict, weight: str | None = None) -> str:
        """One line: where training diverged, which loss term, the learning rate, what was kept."""
        if weight is not None:
            what = f"the weights became non-finite (first {weight})"
        else:
            bad = [k for k, v in terms.items() if k != "total" and not math.isfinite(float(v))]
            what = ("the loss term" + ("s " if len(bad) > 1 else " ") + ", ".join(bad) + " became non-finite"
                    if bad else f"the weighted loss is {float(terms.get('total', float('nan')))}")
        kept = (f"{self.ckpt_path} (epoch {epoch}) is kept" if epoch and self.ckpt_path.exists()
                else "no checkpoint was written")
        return (f"training diverged in {self.run_dir}: epoch {epoch + 1}, step {step} of {len(self.loader)}: "
                f"{what} at learning rate {self.opt.param_groups[0]['lr']:g}; {kept}. Lower --lr, or check "
                "the dataset")

    def frame_ids(self, batch: dict, split: str) -> list | None:
        """The frames' ids (:func:`batch_frame_ids`) where augmentation leaves their ground truth as it is
        (``augment="none"``), else None (cached ground-truth fields keyed by content)."""
        if split == "train" and self.cfg["augment"] != "none":
            return None
        return batch_frame_ids(batch, getattr(self, "spaces", {}).get(split))

    def process_batch(self, batch: dict):
        """Augment, forward, losses: (loss, {term: value}, prediction (B, 1, H, W), the batch as seen)."""
        ids = self.frame_ids(batch, "train")  # read from the loader's batch, on the host
        batch = augment_batch(inference.to_device(batch, self.device), self.cfg["augment"])
        image = batch["image"]
        if self.options["channels_last"]:
            image = image.contiguous(memory_format=torch.channels_last)
        with inference.autocast(self.device):
            pred = self.net(image)  # (B, 1, H, W)
        loss, terms = compute_losses(pred, batch, self.cfg, ids)
        return loss, terms, pred, batch

    def step(self, loss: torch.Tensor) -> None:
        """Backward, optimizer step (through the grad scaler on CUDA float16), schedule step."""
        self.opt.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        self.scaler.step(self.opt)
        self.scaler.update()
        self.schedule.step()

    def keep_best(self) -> None:
        """``best.pt``: a copy of the checkpoint just written when its epoch has the least validation Abs Rel
        of the run so far (ties: the earlier epoch stays)."""
        scores = [float(r.get("val_abs_rel", math.nan)) for r in self.history]
        last = scores[-1]
        if math.isfinite(last) and all(not (s <= last) for s in scores[:-1]):
            utils.write_bytes_atomic(self.run_dir / BEST_NAME, self.ckpt_path.read_bytes())

    def save(self, epoch: int) -> None:
        ckpt_io.save_checkpoint(self.ckpt_path, {
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "scaler": self.scaler.state_dict(),
            "schedule": self.schedule.state_dict(),
            "cfg": self.cfg,
            "epoch": epoch + 1,
            "complete": epoch + 1 == self.cfg["epochs"],
            "rng": ckpt_io.rng_state(self.loader_gen),
            "history": self.history,
            "world_size": self.world,
        })
        self.sessions[-1].update(end_utc=provenance.utc_now(), epochs_done=epoch + 1 - self.sessions[-1]["first_epoch"])
        ckpt_io.write_logs(self.run_dir, self.cfg, self.history, self.sessions)
