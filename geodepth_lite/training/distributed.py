"""Multi-process training with ``torchrun`` (DistributedDataParallel): rank, world size, set-up.

``torchrun --nproc_per_node N -m geodepth_lite train ...`` sets RANK, WORLD_SIZE and
LOCAL_RANK; without it every function here describes a single process.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist


def dist_env() -> tuple[int, int, int]:
    """(rank, world_size, local_rank) from torchrun's environment; (0, 1, 0) otherwise."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0"))


def is_main_process() -> bool:
    """Rank 0 (the only process without torchrun): the one that writes checkpoints and logs."""
    return dist_env()[0] == 0


def init_distributed(device: torch.device) -> bool:
    """Start the process group (nccl on CUDA, gloo on the CPU) under torchrun; False when single-process."""
    _, world, _ = dist_env()
    if world <= 1:
        return False
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)  # one GPU per process (LOCAL_RANK), before nccl starts
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return True


def shutdown() -> None:
    """Close the process group if one is open."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
