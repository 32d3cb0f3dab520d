"""The three papermill/CLI profiles: smoke (seconds, tests), teach (laptop CPU, minutes), paper (GPU).

Every notebook and ``train``/``reproduce`` read their defaults from here, so one
table says what each profile means. The paper's settings (Section 4.1): Adam,
betas 0.9/0.999, weight decay 0.01, lr 1e-4, batch 20, 18 epochs, 320x320,
3600/900/300 frames.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from geodepth_lite.core.errors import UserError
from geodepth_lite.core.losses import DEPTH_TERMS, LossSpec, group_weights
from geodepth_lite.core.model import PADDINGS, check_depth_range
from geodepth_lite.core.sdf import SDF_SAMPLINGS, SDFOptions
from geodepth_lite.data.augment import AUGMENTS

PROFILES: dict[str, dict] = {
    "smoke": {
        "dataset": "scenario_smoke",   # manifest in data_manifests/
        "image_size": 64,              # network input (multiple of 32)
        "predict_image_size": 64,      # input of the model notebooks 04, 06, 07 and `predict` use
        "predict_overrides": {},       # that model's training settings beyond the ablation's (make_config keys)
        "predict_flips": "hv",         # test-time flips of that model's predictions (inference.FLIPS)
        "real_overrides": {"augment": "crop"},  # the model for real frames: the predict model's settings and these
        "epochs": 1,                   # passes over the training split
        "batch_size": 4,               # frames per step
        "lr": 1e-4,                    # Adam learning rate
        "lr_schedule": "constant",     # constant | cosine (per-step decay to 0)
        "weight_decay": 0.01,          # Adam weight decay (paper)
        "optimizer": "adam",           # adam (L2 coupled into the gradient, the paper) | adamw (decoupled)
        "depth_term": "l1",            # l1 (the paper's Eq. 1) | log_l1 | silog (scale-invariant log)
        "augment": "none",             # none | flip | flip_color | camera (augment.augment_batch)
        "padding": "zeros",            # the network's convolution padding: zeros (the paper's ResNet) | replicate
        "border_weight": 0.0,          # beta: depth-term weight 1 + beta at the image edge (losses.border_weight_map)
        "geo_weights": None,           # (lambda2, lambda3) of the geometric terms; None = 1, 1
        "sdf_grid": 8,                 # SDF samples per axis
        "seeds": [0],                  # ablation seeds
        "train_frames": None,          # N evenly spaced training frames (None = the whole split)
        "val_frames": None,            # N evenly spaced validation frames (None = the whole split)
        "threads": 1,                  # CPU threads per run (None = torch's default); results depend on it
        "heldout_overrides": {"camera": {"width": 64, "height": 64}, "splits": {"test": 6}},  # held-out groups
        "closeup_overrides": {"camera": {"width": 64, "height": 64}, "splits": {"test": 6}},  # heldout_closeup
    },
    "teach": {
        # Departs from the paper where a CPU budget and the validation split said so
        # (docs/teach_recipe.md, notebook 04): scale-invariant depth term, no weight decay,
        # larger lr with cosine decay, geometric weights from the loss-weight search (same page).
        "dataset": "scenario_teach",
        "image_size": 64,              # the 128x128 frames, downsampled for a CPU (the ablation's runs)
        # the model notebooks 04, 06 and 07 show and `predict` uses: 96 px scores the held-out close-ups
        # 30% below the shading prior where 64 px gets 16% (docs/teach_recipe.md), at 1.9x the training time
        "predict_image_size": 96,
        # ... run on the image mirrored by 16 px on every side, so that no real pixel sits at the edge of
        # what the network sees, with the border weighed 1 + 2 in the depth term (docs/teach_recipe.md)
        "predict_overrides": {"input_pad": 16, "border_weight": 2.0},
        # ... and predicts each frame as the mean over its four mirrorings (inference.FLIPS): on the
        # validation split 5% lower Abs Rel at no training cost (docs/teach_recipe.md)
        "predict_flips": "hv",
        # the model for real frames (notebook 07's gallery, `predict` on your frames) is that model trained
        # on random crops: it drops the far blob that real close-ups otherwise get, at +10% validation
        # Abs Rel on the synthetic frames (docs/teach_recipe.md), so notebooks 04 and 06 keep the other
        "real_overrides": {"augment": "crop"},
        "epochs": 8,
        "batch_size": 20,
        "lr": 1e-3,                    # larger than the paper's: few steps on a CPU
        "lr_schedule": "cosine",       # decays to 0, so the last epoch's weights are settled (paper: constant)
        "weight_decay": 0.0,           # the paper's coupled L2 of 0.01 cost accuracy at this budget
        "optimizer": "adam",
        "depth_term": "silog",         # relative depth; the absolute L1 is dominated by far lumen pixels
        "augment": "none",
        "padding": "zeros",
        "border_weight": 0.0,          # every pixel alike; 2 evens out the border error (docs/teach_recipe.md)
        "geo_weights": (0.003, 0.01),  # (lambda2, lambda3), chosen on the validation split (docs/teach_recipe.md)
        "sdf_grid": 8,                 # 8^3 samples for 64x64 depth maps (the paper gives no grid size)
        "seeds": [0, 1],               # paired seeds of the ablation (notebook 05 retrains these)
        "train_frames": None,          # all 600 training frames
        "val_frames": 40,              # evenly spaced validation frames scored after each epoch
        "threads": 1,                  # one thread per run, two runs side by side on two cores
        # held-out texture x lighting groups rendered smaller and shorter than ColonDepth's 364 at 256x256
        "heldout_overrides": {"camera": {"width": 128, "height": 128}, "splits": {"test": 60}},
        "closeup_overrides": {"camera": {"width": 128, "height": 128}},  # all 300 close-ups, at 128x128
    },
    "paper": {
        "dataset": "scenario_paper",
        "image_size": 320,
        "predict_image_size": 320,
        "predict_overrides": {},       # the paper's recipe
        "predict_flips": "none",       # one forward pass per frame, as the paper
        "real_overrides": {},          # the paper applies its one model to clinical frames
        "epochs": 18,
        "batch_size": 20,
        "lr": 1e-4,
        "lr_schedule": "constant",     # the paper: 1e-4 for epochs 1-18
        "weight_decay": 0.01,
        "optimizer": "adam",           # torch.optim.Adam: weight decay as L2 in the gradient
        "depth_term": "l1",
        "augment": "none",
        "padding": "zeros",
        "border_weight": 0.0,          # the paper weighs every pixel alike
        "geo_weights": None,           # the paper does not state its lambdas; 1, 1
        "sdf_grid": 32,                # the paper gives no grid size: the workbook's choice at 320 px
        "seeds": [0, 1, 2],
        "train_frames": None,
        "val_frames": None,
        "threads": None,
        "heldout_overrides": None,     # the manifests as shipped: 364 frames at 256x256 per group
        "closeup_overrides": None,     # 300 close-ups at 256x256
        "val_sdf": False,              # validation scores the metrics, not the SDF term (no notebook plots it)
        # the head's depth range set from the scenario data (training depths 0.11-33.5, median 1.96 scene
        # units), not 0.01-100: with the L1 term the head must start at the data's scale, and its floor
        # sit at the data's, or near pixels sink to the floor (docs/paper_recipe.md)
        "head_range": (0.1, 40.0),
    },
}

# The four ablation cases of Section 4.2.1 as loss weights (lambda1, lambda2, lambda3).
ABLATION_CASES: dict[int, tuple[float, float, float]] = {
    1: (1.0, 0.0, 0.0),  # depth + smoothness
    2: (1.0, 1.0, 0.0),  # + gradient + normal
    3: (1.0, 0.0, 1.0),  # + SDF
    4: (1.0, 1.0, 1.0),  # all
}


def case_lambdas(case: int, geo_weights=None) -> list[float]:
    """(lambda1, lambda2, lambda3) of ablation ``case``: the case's terms switched on, weighted by the
    profile's ``geo_weights`` = (lambda2, lambda3) (None: the paper's unstated weights taken as 1)."""
    if case not in ABLATION_CASES:
        raise UserError(f"case must be one of {sorted(ABLATION_CASES)}, got {case!r}")
    l2, l3 = (1.0, 1.0) if geo_weights is None else (float(geo_weights[0]), float(geo_weights[1]))
    on = ABLATION_CASES[case]
    return [on[0], on[1] * l2, on[2] * l3]


def get_profile(name: str) -> dict:
    """The settings of profile ``name``; a clear error for an unknown one."""
    if name not in PROFILES:
        raise UserError(f"unknown profile {name!r}: choose one of {', '.join(PROFILES)}")
    return dict(PROFILES[name])


# --------------------------------------------------------------------------- training configurations
# Settings that change the trained weights: a checkpoint is reused or resumed only
# when all of these match. Runtime-only options (progress bar, workers, device) do not.
IDENTITY_KEYS = (
    "dataset", "dataset_overrides", "image_size", "epochs", "batch_size", "lr",
    "weight_decay", "betas", "sdf_grid", "lambdas", "seed", "train_frames", "val_frames", "encoder_weights",
    "threads", "lr_schedule", "optimizer", "depth_term", "augment", "padding", "border_weight",
    "input_pad", "sdf_sampling", "sdf_sign", "head_range", "depth_unit", "init_from",
)
# Keys added after checkpoints existed: part of a configuration's identity only when they differ from
# this default, so checkpoints trained before the key was added keep their names and stay valid.
LATER_KEY_DEFAULTS = {"border_weight": 0.0, "input_pad": 0, "sdf_sampling": "bbox", "sdf_sign": "view",
                      "head_range": None, "depth_unit": 1.0, "init_from": None}
# init_from: the run folder, beside this run's, whose finished weights a fine-tuning run starts from
INIT_FROM = re.compile(r"case[1-4]_seed\d{1,6}-[0-9a-f]{8}")
SDF_SIGNS = ("view", "masked")  # sign rules of a training run (sdf.SIGN_RULES; "nearest" is for comparison only)
LR_SCHEDULES = ("constant", "cosine")
OPTIMIZERS = ("adam", "adamw")  # adam: L2 coupled into the gradient (the paper, torch.optim.Adam); adamw: decoupled


def make_config(profile: str = "teach", case: int = 4, seed: int = 0, **overrides: Any) -> dict:
    """The training configuration of ablation ``case`` (1-4, Section 4.2.1) under ``profile``.

    ``overrides`` replace single entries (``epochs=2``, ``lr=3e-4``,
    ``dataset="scenario_smoke"``, ``dataset_overrides={...}``, ``train_frames=40``...).
    """
    p = get_profile(profile)
    if case not in ABLATION_CASES:
        raise UserError(f"case must be one of {sorted(ABLATION_CASES)}, got {case!r}")
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
        "lambdas": case_lambdas(case, p.get("geo_weights")),
        "optimizer": p.get("optimizer", "adam"),
        "depth_term": p.get("depth_term", "l1"),
        "augment": p.get("augment", "none"),
        "padding": p.get("padding", "zeros"),   # the network's convolution padding (model.PADDINGS)
        "border_weight": p.get("border_weight", 0.0),  # beta of the depth term's border weight (losses)
        "input_pad": p.get("input_pad", 0),     # mirrored pixels around the network's input (model.DepthNet)
        "sdf_sampling": p.get("sdf_sampling", "bbox"),  # SDF samples: bbox (the paper's Eq. 9) | frustum
        "sdf_sign": p.get("sdf_sign", "view"),  # SDF sign: view (the paper's) | masked (out-of-view points left out)
        "head_range": p.get("head_range"),      # (smallest, largest) depth of the head; None = model.MIN/MAX_DEPTH
        "depth_unit": p.get("depth_unit", 1.0),  # the losses see depth / depth_unit (1 = scene units)
        "init_from": None,                      # a finished run beside this one to fine-tune (its folder name)
        "seed": int(seed),
        "train_frames": p.get("train_frames"),  # N evenly spaced training frames (None = all)
        "val_frames": p.get("val_frames"),      # N evenly spaced validation frames (None = all)
        "encoder_weights": None,
        "threads": p.get("threads"),            # CPU threads (fixed: results depend on it); None = torch's
        "val_sdf": p.get("val_sdf", True),      # validation evaluates the SDF term (not an identity key)
    }
    for key, value in overrides.items():
        if key not in cfg:
            raise UserError(f"unknown training setting {key!r}: choose from {', '.join(cfg)}")
        if (value is not None or key in ("dataset_overrides", "train_frames", "val_frames", "encoder_weights",
                                         "threads", "head_range")):
            cfg[key] = value
    return validate_config(cfg)


CONFIG_DEFAULTS = {"dataset_overrides": None, "train_frames": None, "val_frames": None, "encoder_weights": None,
                   "threads": None, "betas": [0.9, 0.999], "lr_schedule": "constant", "optimizer": "adam",
                   "depth_term": "l1", "augment": "none", "padding": "zeros", "border_weight": 0.0, "input_pad": 0,
                   "sdf_sampling": "bbox", "sdf_sign": "view", "val_sdf": True, "head_range": None,
                   "depth_unit": 1.0, "init_from": None}


def validate_config(cfg: dict) -> dict:
    """Check a training configuration; a clear error naming the field. Returns a normalised copy."""
    cfg = {**{k: (list(v) if isinstance(v, list) else v) for k, v in CONFIG_DEFAULTS.items()}, **cfg}
    for key, allowed in (("optimizer", OPTIMIZERS), ("depth_term", tuple(DEPTH_TERMS)), ("augment", AUGMENTS),
                         ("padding", PADDINGS), ("lr_schedule", LR_SCHEDULES),
                         ("sdf_sampling", tuple(SDF_SAMPLINGS)), ("sdf_sign", SDF_SIGNS)):
        if cfg[key] not in allowed:
            raise UserError(f"{key} must be one of {', '.join(allowed)}, got {cfg[key]!r}")
    if not isinstance(cfg["val_sdf"], bool):
        raise UserError(f"val_sdf must be True or False, got {cfg['val_sdf']!r}")
    missing = [k for k in IDENTITY_KEYS if k not in cfg]
    if missing:
        raise UserError(f"training config is missing {', '.join(missing)}")
    _check_sizes(cfg)
    _check_optimizer(cfg)
    _check_data(cfg)
    return cfg


def _positive_int(cfg: dict, key: str) -> None:
    v = cfg[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
        raise UserError(f"{key} must be a positive integer, got {v!r}")
    cfg[key] = int(v)


def _check_sizes(cfg: dict) -> None:
    """Epochs, batch, SDF grid, input size and padding, frame limits, threads, border weight (in place)."""
    for key in ("epochs", "batch_size", "sdf_grid", "image_size"):
        _positive_int(cfg, key)
    if cfg["image_size"] % 32:
        raise UserError("image_size must be a multiple of 32 (the encoder downsamples 5 times), "
                         f"got {cfg['image_size']}")
    for key in ("train_frames", "val_frames", "threads"):
        if cfg.get(key) is not None:
            _positive_int(cfg, key)
    bw = cfg["border_weight"]
    if isinstance(bw, bool) or not isinstance(bw, (int, float, np.floating, np.integer)) or not 0 <= bw < float("inf"):
        raise UserError(f"border_weight must be a non-negative number, got {bw!r}")
    cfg["border_weight"] = float(bw)
    pad = cfg["input_pad"]
    if isinstance(pad, bool) or not isinstance(pad, (int, np.integer)) or pad < 0 or pad % 16:
        raise UserError(f"input_pad must be a non-negative multiple of 16 (pixels), got {pad!r}")
    cfg["input_pad"] = int(pad)
    _check_depth_scale(cfg)


def _check_depth_scale(cfg: dict) -> None:
    """The head's range (None or two depths 0 < lo < hi) and the losses' depth unit (> 0), in place."""
    if cfg["head_range"] is not None:
        cfg["head_range"] = list(check_depth_range(cfg["head_range"]))
    unit = cfg["depth_unit"]
    if isinstance(unit, bool) or not isinstance(unit, (int, float, np.floating, np.integer)) or not (
            0 < unit < float("inf")):
        raise UserError(f"depth_unit must be a positive number, got {unit!r}")
    cfg["depth_unit"] = float(unit)


def _check_optimizer(cfg: dict) -> None:
    """Learning rate, weight decay, betas and loss weights: finite numbers in range (in place)."""
    for key in ("lr", "weight_decay"):
        v = cfg[key]
        if (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0
                or (key == "lr" and v == 0)):
            raise UserError(f"{key} must be a {'positive' if key == 'lr' else 'non-negative'} number, got {v!r}")
        cfg[key] = float(v)
    betas = cfg["betas"]
    if not (isinstance(betas, (list, tuple)) and len(betas) == 2 and all(0 <= float(b) < 1 for b in betas)):
        raise UserError(f"betas must be two numbers in [0, 1), got {betas!r}")
    cfg["betas"] = [float(b) for b in betas]
    lam = cfg["lambdas"]
    if not isinstance(lam, (list, tuple, dict)):
        raise UserError(f"lambdas must be the loss weights by group name or in group order, got {lam!r}")
    cfg["lambdas"] = list(group_weights(lam).values())  # in group order: [lambda1, lambda2, lambda3]
    if not all(math.isfinite(float(w)) and float(w) >= 0 for w in cfg["lambdas"]):
        raise UserError(f"lambdas must be finite non-negative numbers, got {lam!r}")


def _check_data(cfg: dict) -> None:
    """Seed, dataset, its overrides, the encoder's weights file and the run to fine-tune (in place)."""
    if cfg["init_from"] is not None and not (isinstance(cfg["init_from"], str)
                                             and INIT_FROM.fullmatch(cfg["init_from"])):
        raise UserError(f"init_from must name a run folder such as case4_seed0-1a2b3c4d, got {cfg['init_from']!r}")
    if isinstance(cfg["seed"], bool) or not isinstance(cfg["seed"], (int, np.integer)) or cfg["seed"] < 0:
        raise UserError(f"seed must be a non-negative integer, got {cfg['seed']!r}")
    cfg["seed"] = int(cfg["seed"])
    if not isinstance(cfg["dataset"], (str, os.PathLike)) or not str(cfg["dataset"]):
        raise UserError(f"dataset must be a manifest name or a dataset directory, got {cfg['dataset']!r}")
    cfg["dataset"] = str(cfg["dataset"])
    if cfg["dataset_overrides"] is not None and not isinstance(cfg["dataset_overrides"], dict):
        raise UserError(f"dataset_overrides must be a dict or None, got {cfg['dataset_overrides']!r}")
    if cfg["encoder_weights"] is not None:
        cfg["encoder_weights"] = str(cfg["encoder_weights"])
        if not Path(cfg["encoder_weights"]).is_file():
            raise FileNotFoundError(f"encoder_weights: no such file {cfg['encoder_weights']}")


def loss_spec(cfg: dict) -> LossSpec:
    """The loss settings of a training configuration (``make_config``): its weights, depth term, border
    weight, and the SDF term's grid (``sdf_grid`` samples per axis), sampling and sign rule; the search and
    the cache of ground-truth fields are :class:`SDFOptions`' defaults. The one place a configuration
    becomes :class:`LossSpec`."""
    g = cfg["sdf_grid"]
    return LossSpec(lambdas=cfg["lambdas"], depth_term=cfg["depth_term"], border_weight=cfg["border_weight"],
                    sdf=SDFOptions(grid=(g, g, g), sampling=cfg["sdf_sampling"], sign_rule=cfg["sdf_sign"]))


def config_identity(cfg: dict) -> dict:
    """The entries of ``cfg`` that determine the trained weights (see IDENTITY_KEYS); a key of
    LATER_KEY_DEFAULTS is left out while it holds its default."""
    return {k: cfg.get(k) for k in IDENTITY_KEYS
            if not (k in LATER_KEY_DEFAULTS and cfg.get(k, LATER_KEY_DEFAULTS[k]) == LATER_KEY_DEFAULTS[k])}


def config_hash(cfg: dict) -> str:
    """8 hex digits naming a configuration (cache directory suffix)."""
    blob = json.dumps(config_identity(cfg), sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:8]


# --------------------------------------------------------------------------- made once, at the edge
def _frozen(value: Any) -> Any:
    """A read-only copy of a settings value: mappings as read-only mappings, lists as tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: _frozen(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(v) for v in value)
    return value


def _thawed(value: Any) -> Any:
    """A plain, writable copy of a value ``_frozen`` made: dicts and lists again (JSON- and fit-ready)."""
    if isinstance(value, Mapping):
        return {k: _thawed(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [_thawed(v) for v in value]
    return value


@dataclass(frozen=True, eq=False)
class RunConfig:
    """One training run's settings, checked and frozen: made once where a command, ``reproduce`` or a
    notebook starts (``Profile.run``), then passed down as this object. It carries its identity (the
    settings that change the weights) and its hash, which names its run folder exactly as before
    (``case<c>_seed<s>-<hash>``). Read a setting as ``run["image_size"]``; ``run.as_dict()`` is a
    plain copy for ``train.fit``."""

    profile: str
    case: int
    seed: int
    overrides: Mapping[str, Any]
    settings: Mapping[str, Any] = field(repr=False)

    def __getitem__(self, key: str) -> Any:
        return _thawed(self.settings[key])

    def get(self, key: str, default: Any = None) -> Any:
        return _thawed(self.settings.get(key, default))

    def as_dict(self) -> dict:
        """The settings as a plain dict (lists, not tuples): what ``make_config`` returned."""
        return _thawed(self.settings)

    @property
    def identity(self) -> dict:
        return config_identity(self.as_dict())

    @property
    def hash(self) -> str:
        return config_hash(self.as_dict())

    @property
    def folder_name(self) -> str:
        """The run folder's name: ``case<c>_seed<s>-<config hash>``."""
        return f"case{self.case}_seed{self.seed}-{self.hash}"

    def __reduce__(self):  # for the worker processes: the read-only mappings themselves do not pickle
        return (_rebuilt, (RunConfig, self.profile, self.case, self.seed, _thawed(self.overrides), self.as_dict()))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RunConfig) and (self.profile, self.folder_name) == (other.profile, other.folder_name)

    def __hash__(self) -> int:
        return hash((self.profile, self.folder_name))


@dataclass(frozen=True, eq=False)
class Profile:
    """A profile's settings (``PROFILES``), checked and frozen: made once at the edge (``profile(name)``)
    and passed down, so no module below the edge reads the profile table again. It makes the run
    configurations of its runs: ``run(case, seed, **overrides)``, and the two models the notebooks
    load beside the ablation's, ``predict_run()`` and ``real_run()``."""

    name: str
    settings: Mapping[str, Any] = field(repr=False)

    def __getitem__(self, key: str) -> Any:
        return _thawed(self.settings[key])

    def get(self, key: str, default: Any = None) -> Any:
        return _thawed(self.settings.get(key, default))

    def __reduce__(self):
        return (_rebuilt, (Profile, self.name, _thawed(self.settings)))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Profile) and self.name == other.name

    def __hash__(self) -> int:
        return hash(self.name)

    def run(self, case: int = 4, seed: int = 0, **overrides: Any) -> RunConfig:
        """The configuration of ablation ``case``, ``seed`` with ``overrides`` (``make_config``), checked now."""
        cfg = make_config(self.name, case, seed, **overrides)
        return RunConfig(self.name, int(case), int(seed), _frozen(dict(overrides)), _frozen(cfg))

    def predict_settings(self) -> dict:
        """The settings that turn an ablation run into the profile's ``predict`` model (notebooks 04, 06, 07
        and ``predict``): its ``predict_image_size`` and ``predict_overrides``."""
        return {**self.get("predict_overrides", {}), "image_size": self["predict_image_size"]}

    def real_settings(self) -> dict:
        """The settings of the model for real endoscope frames: ``predict_settings`` and ``real_overrides``."""
        return {**self.predict_settings(), **self.get("real_overrides", {})}

    def predict_run(self, case: int = 4, seed: int = 0) -> RunConfig:
        return self.run(case, seed, **self.predict_settings())

    def real_run(self, case: int = 4, seed: int = 0) -> RunConfig:
        return self.run(case, seed, **self.real_settings())


def _rebuilt(kind: type, *parts: Any) -> RunConfig | Profile:
    """A ``RunConfig`` or ``Profile`` from the plain parts its ``__reduce__`` gave (checked when first made)."""
    if kind is RunConfig:
        name, case, seed, overrides, settings = parts
        return RunConfig(name, case, seed, _frozen(overrides), _frozen(settings))
    name, settings = parts
    return Profile(name, _frozen(settings))


def profile(name: str) -> Profile:
    """Profile ``name``, checked and frozen (a ``UserError`` names the choices for an unknown one)."""
    return Profile(name, _frozen(get_profile(name)))
