"""The three papermill/CLI profiles: smoke (seconds, tests), teach (laptop CPU, minutes), paper (GPU).

Every notebook and ``train``/``reproduce`` read their defaults from here, so one
table says what each profile means. The paper's settings (Section 4.1): Adam,
betas 0.9/0.999, weight decay 0.01, lr 1e-4, batch 20, 18 epochs, 320x320,
3600/900/300 frames.
"""

from __future__ import annotations

PROFILES: dict[str, dict] = {
    "smoke": {
        "dataset": "scenario_smoke",   # manifest in data_manifests/
        "image_size": 64,              # network input (multiple of 32)
        "epochs": 1,                   # passes over the training split
        "batch_size": 4,               # frames per step
        "lr": 1e-4,                    # Adam learning rate
        "weight_decay": 0.01,          # Adam weight decay (paper)
        "sdf_grid": 8,                 # SDF samples per axis
        "seeds": [0],                  # ablation seeds
    },
    "teach": {
        "dataset": "scenario_teach",
        "image_size": 64,
        "epochs": 6,
        "batch_size": 20,
        "lr": 1e-3,                    # larger than the paper's: few steps on a CPU
        "weight_decay": 0.01,
        "sdf_grid": 16,
        "seeds": [0, 1],
    },
    "paper": {
        "dataset": "scenario_paper",
        "image_size": 320,
        "epochs": 18,
        "batch_size": 20,
        "lr": 1e-4,
        "weight_decay": 0.01,
        "sdf_grid": 32,
        "seeds": [0, 1, 2],
    },
}

# The four ablation cases of Section 4.3 as loss weights (lambda1, lambda2, lambda3).
ABLATION_CASES: dict[int, tuple[float, float, float]] = {
    1: (1.0, 0.0, 0.0),  # depth + smoothness
    2: (1.0, 1.0, 0.0),  # + gradient + normal
    3: (1.0, 0.0, 1.0),  # + SDF
    4: (1.0, 1.0, 1.0),  # all
}


def get_profile(name: str) -> dict:
    """The settings of profile ``name``; a clear error for an unknown one."""
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}: choose one of {', '.join(PROFILES)}")
    return dict(PROFILES[name])
