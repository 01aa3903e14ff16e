"""Distributed training under ``torchrun``: the process group, ranks and broadcasts."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

import torch
import torch.distributed as dist

from scanguard.errors import ConfigError

log = logging.getLogger(__name__)


def dist_rank_world() -> tuple[int, int]:
    """This process's rank and the world size (``(0, 1)`` outside a process group)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_distributed() -> tuple[int, int]:
    """Join the process group that ``torchrun`` describes (``WORLD_SIZE`` > 1), once.

    The backend is ``nccl`` when CUDA is present, ``gloo`` otherwise. Outside ``torchrun``
    (no ``WORLD_SIZE``, or 1) nothing happens.

    Returns:
        This process's rank and the world size.

    Raises:
        ConfigError: torch was built without distributed support, or the group cannot be
            joined.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1 or (dist.is_available() and dist.is_initialized()):
        return dist_rank_world()
    if not dist.is_available():
        raise ConfigError("WORLD_SIZE > 1 but this torch has no torch.distributed")
    backend = "nccl" if torch.cuda.is_available() else "gloo"
    try:
        dist.init_process_group(backend=backend)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"cannot join the {backend} process group: {exc}") from None
    log.info("rank %d of %d (%s)", dist.get_rank(), dist.get_world_size(), backend)
    return dist_rank_world()


def local_world() -> int:
    """Number of processes on this machine (``LOCAL_WORLD_SIZE``, at least 1)."""
    return max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))


def broadcast_floats(values: Sequence[float]) -> list[float]:
    """Rank 0's ``values`` on every rank (as they are outside a process group)."""
    if dist_rank_world()[1] == 1:
        return list(values)
    t = torch.tensor(list(values), dtype=torch.float64)
    torch.distributed.broadcast(t, src=0)
    return [float(v) for v in t.tolist()]
