"""Training on several processes (``torchrun``): which rank this is, its device, its slice of the batch,
and the collective steps the loop takes (``tasks.loop``).

The same loop runs on every rank under DistributedDataParallel (NCCL on CUDA, gloo on the CPU).  Every
rank draws the step's global batch from the same seeded generator and trains on its ``1/N`` slice
(:func:`split_batch`; N must divide the batch), DDP averages the gradients, so the update is the
one-process update of the same global batch (to float rounding; the tasks' losses are means over the
batch).  The logged train metrics are the ranks' means (:func:`mean_over_ranks`); decisions that every
rank must share (the run folder, early stopping) are rank 0's (:func:`from_rank0`).
"""
from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from base.errors import InputError


@dataclass(frozen=True)
class Ranks:
    """This process among the training processes (one process: rank 0 of 1).  ``local_rank`` is its
    number on its machine (torchrun's ``LOCAL_RANK``), the GPU it uses."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def launched_ranks() -> Ranks:
    """The ranks of an initialised process group, else of torchrun's ``RANK``, ``WORLD_SIZE``,
    ``LOCAL_RANK`` environment (absent: one process)."""
    env = os.environ
    if dist.is_available() and dist.is_initialized():
        rank = dist.get_rank()
        return Ranks(rank, dist.get_world_size(), int(env.get("LOCAL_RANK", rank)))
    if "WORLD_SIZE" not in env and int(env.get("SLURM_STEP_NUM_TASKS", 1)) > 1:
        raise InputError(f"{env['SLURM_STEP_NUM_TASKS']} SLURM tasks run train.py without torchrun's environment "
                         f"(RANK, WORLD_SIZE): each would train alone into the run directory; run one task per job "
                         f"(hydra.launcher.tasks_per_node=1) or start the processes with torchrun")
    return Ranks(int(env.get("RANK", 0)), int(env.get("WORLD_SIZE", 1)), int(env.get("LOCAL_RANK", 0)))


def resolve_device(name: str, local_rank: int = 0, task_moves: bool = True) -> torch.device:
    """``trainer.device`` (auto | cpu | cuda) as the device of the process of ``local_rank``.

    ``auto`` is CUDA when a GPU is present and the task can move there (``task_moves``: its ``Task``
    has ``to(device)``), else the CPU.  InputError for ``cuda`` without a GPU, for a task that cannot
    move, or for more processes on a machine than it has GPUs.
    """
    if name == "cpu" or (name == "auto" and not (torch.cuda.is_available() and task_moves)):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise InputError("trainer.device=cuda: no CUDA device is available here (torch.cuda.is_available() is "
                         "False); use trainer.device=auto or trainer.device=cpu")
    if not task_moves:
        raise InputError("trainer.device=cuda: this task cannot run on CUDA (its Task has no to(device), "
                         "tasks/__init__.py); use trainer.device=cpu")
    count = torch.cuda.device_count()
    if local_rank >= count:
        raise InputError(f"trainer.device={name}: the process of local rank {local_rank} has no GPU ({count} on "
                         f"this machine); start at most {count} processes per machine (torchrun --nproc_per_node)")
    return torch.device("cuda", local_rank)


def split_batch(batch, rank: int, world: int):
    """Rank ``rank``'s slice of the global ``batch`` among ``world`` ranks: rows
    ``[rank * B/world, (rank + 1) * B/world)`` on dim 0 of every tensor of at least one dimension (in a
    tensor, or tuples, lists and dicts of them, rebuilt in kind); other values are passed unchanged.

    Raises InputError when ``world`` does not divide the batch size ``B`` (equal slices make the
    ranks' mean gradients average to the global batch's), TypeError when the tensors do not share
    their dim-0 size (then the task must define ``split_batch``).
    """
    sizes: set[int] = set()

    def visit(value) -> None:
        if isinstance(value, torch.Tensor):
            if value.dim() > 0:
                sizes.add(value.shape[0])
        elif isinstance(value, dict):
            for item in value.values():
                visit(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item)

    visit(batch)
    if len(sizes) != 1:
        raise TypeError(f"cannot split the batch over {world} ranks on dim 0: its tensors have "
                        f"{sorted(sizes) or 'no'} dim-0 sizes, expected one batch size; give the task a "
                        f"split_batch(batch, rank, world) (tasks/__init__.py)")
    size = sizes.pop()
    if size % world:
        raise InputError(f"the global batch of {size} samples does not split evenly over {world} processes: "
                         f"choose a batch size (task.batch_size) that is a multiple of {world}")
    first, last = rank * size // world, (rank + 1) * size // world

    def cut(value):
        if isinstance(value, torch.Tensor):
            return value[first:last] if value.dim() > 0 else value
        if isinstance(value, dict):
            return type(value)((key, cut(item)) for key, item in value.items())
        if isinstance(value, tuple) and hasattr(value, "_fields"):  # a named tuple
            return type(value)(*(cut(item) for item in value))
        if isinstance(value, (list, tuple)):
            return type(value)(cut(item) for item in value)
        return value

    return cut(batch)


def to_device(batch, device: torch.device):
    """``batch`` (a tensor, or tuples, lists and dicts of them) with every tensor on ``device``."""
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return type(batch)((key, to_device(item, device)) for key, item in batch.items())
    if isinstance(batch, tuple) and hasattr(batch, "_fields"):
        return type(batch)(*(to_device(item, device) for item in batch))
    if isinstance(batch, (list, tuple)):
        return type(batch)(to_device(item, device) for item in batch)
    return batch


class TaskParallel(DistributedDataParallel):
    """DistributedDataParallel that forwards the attributes it does not have to the wrapped module, so a
    task's ``loss`` may use ``self.model.<attribute>`` (e.g. ``shift``, ``tau_scale``) while
    ``self.model(...)`` runs through DDP's gradient synchronisation."""

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            if name == "module":
                raise
            return getattr(self.module, name)


def mean_over_ranks(values: dict[str, float], ranks: Ranks, device: torch.device) -> dict[str, float]:
    """The mean of each value over the ranks (every rank passes the same keys in the same order)."""
    if ranks.world == 1 or not values:
        return values
    total = torch.tensor(list(values.values()), dtype=torch.float64, device=device)
    dist.all_reduce(total)
    return dict(zip(values, (total / ranks.world).tolist()))


def from_rank0(value, ranks: Ranks):
    """Rank 0's ``value`` on every rank (a picklable object)."""
    if ranks.world == 1:
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


@contextlib.contextmanager
def process_group(ranks: Ranks, device: torch.device) -> Iterator[None]:
    """Join the ranks' process group (NCCL on CUDA, gloo on the CPU) for the block, unless there is one
    process or a group is already running; leave it once every rank has finished the block."""
    started = False
    if ranks.world > 1 and not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        started = True
    try:
        yield
        if started:  # a rank that tore gloo down while rank 0 still wrote its checkpoint aborted at exit
            dist.barrier()
    finally:
        if started:  # the DDP wrapper holds the group in its reducer, in reference cycles: free it first
            gc.collect()
            dist.destroy_process_group()
