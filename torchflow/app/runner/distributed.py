"""One experiment over ``torchrun`` processes (README, "Scaling out"): every rank simulates the same
data, runs chunks ``rank, rank + world, ...`` of each filter and sends its per-trial results to rank 0.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any, List, Optional

import torch
import torch.distributed as dist

from torchflow.core.errors import ArgumentError


@dataclass
class Shard:
    """This process's ``rank`` (0 .. ``world`` - 1) of ``world``; ``local_rank`` on its node (its GPU)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    def __post_init__(self):
        for name in ("rank", "world", "local_rank"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (1 if name == "world" else 0):
                raise ArgumentError(f"{name}: expected an int >= {1 if name == 'world' else 0}, got {v!r}")
        if self.rank >= self.world:
            raise ArgumentError(f"rank: expected < world = {self.world}, got {self.rank}")

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def mine(self, chunks: List) -> List:
        """This rank's chunks of ``chunks`` (round-robin)."""
        return chunks[self.rank :: self.world]

    def gather(self, obj: Any) -> Optional[List[Any]]:
        """Every rank's ``obj`` in rank order on rank 0 (``None`` elsewhere); ``[obj]`` when
        the run is not distributed. Objects are pickled; keep tensors on the CPU."""
        if self.world == 1:
            return [obj]
        out = [None] * self.world if self.is_main else None
        dist.gather_object(obj, out, dst=0)
        return out

    def broadcast(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every rank (``obj`` itself when not distributed)."""
        if self.world == 1:
            return obj
        box = [obj if self.is_main else None]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    @staticmethod
    def from_env(device: str = "cpu", timeout_minutes: float = 720.0) -> "Shard":
        """The shard ``torchrun`` describes, its process group initialised (``Shard()`` outside
        ``torchrun``; ``device`` ``cuda``: NCCL and this rank's GPU); ``timeout_minutes``: how long a
        rank waits for the slowest at a gather (torch's 10-30 min defaults would end long runs)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return Shard()
        rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
        cuda = str(device).startswith("cuda")
        if not dist.is_initialized():
            if cuda:
                torch.cuda.set_device(local)
            dist.init_process_group(
                backend="nccl" if cuda else "gloo", timeout=datetime.timedelta(minutes=float(timeout_minutes))
            )
        return Shard(rank=rank, world=world, local_rank=local)

    def device(self, device: str) -> str:
        """The device this rank runs on: ``cuda`` becomes ``cuda:<local_rank>`` in a distributed
        run; an explicit ``cuda:<i>`` there is refused (every rank would share GPU i)."""
        if self.world > 1 and str(device).startswith("cuda"):
            if str(device) != "cuda":
                raise ArgumentError(
                    f"device: expected 'cuda' under torchrun (rank r uses cuda:LOCAL_RANK), got {device!r}"
                )
            return f"cuda:{self.local_rank}"
        return str(device)

    def close(self) -> None:
        if self.world > 1 and dist.is_initialized():
            dist.destroy_process_group()
