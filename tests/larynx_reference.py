"""References for the larynx transformer's streaming decoder (``models.larynx``), for its tests and
``benchmarks/bench_larynx_streaming.py``: FaceFormer's decoding, which the cache must match (and whose cost it
is measured against), and the bytes a stream carries from frame to frame (bounded memory)."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from models.larynx import LarynxStream


@torch.no_grad()
def generate_uncached(model: nn.Module, psi: Tensor, subject: Tensor | None = None) -> Tensor:
    """Decoding as FaceFormer does it: rerun ``model.forward`` on the whole prefix at every frame (O(T^2)).

    tau [B,T] (UV units) from psi [B,T,55] and style indices subject [B] (None: the unknown subject's)."""
    return torch.stack([model(psi[:, : t + 1], subject)[:, -1] for t in range(psi.shape[1])], dim=1)


def tensor_bytes(root, exclude: tuple = ()) -> int:
    """Bytes of the storage of every tensor reachable from ``root`` through attributes, lists, tuples, dicts
    and dataclasses, each storage counted once (views share it); objects in ``exclude`` (e.g. the model,
    whose weights do not belong to a stream) are not entered."""
    seen_storages, seen_objects, total = set(), set(), 0
    skip = {id(x) for x in exclude}
    pending = [root]
    while pending:
        obj = pending.pop()
        if id(obj) in seen_objects or id(obj) in skip:
            continue
        seen_objects.add(id(obj))
        if isinstance(obj, Tensor):
            storage = obj.untyped_storage()
            if storage.data_ptr() not in seen_storages:
                seen_storages.add(storage.data_ptr())
                total += storage.nbytes()
        elif isinstance(obj, dict):
            pending.extend(obj.values())
        elif isinstance(obj, (list, tuple, set)):
            pending.extend(obj)
        elif hasattr(obj, "__dict__") and not isinstance(obj, type):
            pending.extend(vars(obj).values())
    return total


def state_bytes(stream: LarynxStream) -> int:
    """Bytes of the tensors ``stream`` carries from frame to frame: all it holds but its models and its
    snapshot of the weights (both fixed for the stream's life)."""
    return tensor_bytes(stream, exclude=(stream.members, stream.weights))
