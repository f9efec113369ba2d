"""A folder of takes: each into its own subfolder (in worker processes with ``workers > 1``), going on past
a take that fails, and the summary table."""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import torch
from omegaconf import OmegaConf

from base.errors import InputError
from base.files import require_new_folder, write_csv
from base.progress import progress_bar
from motion.face.frames import VIDEO_SUFFIXES
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models, load_models
from motion.pipeline.take import run_take, take_audio
from motion.swallow import PlaybackConfig

CAPTURE_SUFFIXES = (".csv", ".npy")
TAKE_SUFFIXES = CAPTURE_SUFFIXES + VIDEO_SUFFIXES  # videos go through the face stage (motion.face)


def takes_in(folder: Path) -> list[Path]:
    """The takes of ``folder``: captures (.csv, .npy) and face videos, by name; a video with the stem of a
    capture is that capture's sound (``take_audio``), not a take of its own."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES]
    capture_stems = {p.stem for p in files if p.suffix.lower() in CAPTURE_SUFFIXES}
    takes = sorted(p for p in files if p.suffix.lower() in CAPTURE_SUFFIXES or p.stem not in capture_stems)
    if not takes:
        raise InputError(f"expressions={folder}: a folder without takes (.csv, .npy, or face videos "
                         f"{', '.join(VIDEO_SUFFIXES)})")
    return takes


_WORKER: dict = {}


def _init_worker(cfg_dict: dict) -> None:
    cfg = InferConfig(**{**cfg_dict, "swallow_playback": PlaybackConfig(**cfg_dict["swallow_playback"])})
    torch.set_num_threads(max(1, int(cfg.threads)))
    _WORKER["cfg"] = cfg
    _WORKER["models"] = load_models(cfg, announce=lambda message: None)


def _take_row(cfg: InferConfig, models: Models, take: Path, out_dir: Path, announce=print) -> dict:
    try:
        return run_take(cfg, models, str(take), out_dir, announce)
    except InputError as e:
        return {"take": str(take), "status": "failed", "reason": str(e), "out": ""}


def _worker_take(take: str, out_dir: str) -> dict:
    return _take_row(_WORKER["cfg"], _WORKER["models"], Path(take), Path(out_dir), announce=lambda message: None)


def run_folder(cfg: InferConfig, folder: Path, out_dir: Path) -> list[dict]:
    """Every take of ``folder`` into ``out_dir/<take>/``; failures reported, the others go on."""
    take_audio(cfg, None, in_folder=True)  # audio=<one file> is refused for a folder (each take's is beside it)
    takes = takes_in(folder)
    require_new_folder(out_dir)
    targets = [out_dir / take.stem for take in takes]
    if len({t.name for t in targets}) < len(targets):
        targets = [out_dir / f"{take.stem}{take.suffix.replace('.', '_')}" for take in takes]
    rows = []
    progress = progress_bar(total=len(takes), desc="takes", unit="take")
    if cfg.workers > 1 and len(takes) > 1:
        cfg_dict = OmegaConf.to_container(OmegaConf.structured(cfg))
        with ProcessPoolExecutor(min(cfg.workers, len(takes)), mp_context=get_context("spawn"),
                                 initializer=_init_worker, initargs=(cfg_dict,)) as pool:
            futures = [pool.submit(_worker_take, str(take), str(target)) for take, target in zip(takes, targets)]
            for future in futures:
                rows.append(future.result())
                progress.update(1)
    else:
        models = load_models(cfg)
        for take, target in zip(takes, targets):
            rows.append(_take_row(cfg, models, take, target))
            progress.update(1)
    progress.close()
    if any(row["status"] == "ok" for row in rows):
        out_dir.mkdir(parents=True, exist_ok=True)
        write_csv(out_dir / "summary.csv", {
            "take": [r["take"] for r in rows], "status": [r["status"] for r in rows],
            "frames": [r.get("frames", 0) for r in rows], "seconds": [r.get("seconds", 0.0) for r in rows],
            "out": [r["out"] for r in rows], "reason": [r["reason"] for r in rows]})
    return rows


def print_summary(rows: list[dict]) -> None:
    width = max(len(Path(r["take"]).name) for r in rows)
    print(f"\n{'take':<{width}}  status  frames  seconds  result")
    for r in rows:
        detail = r["out"] if r["status"] == "ok" else r["reason"]
        print(f"{Path(r['take']).name:<{width}}  {r['status']:<6}  {r.get('frames', 0):>6}  "
              f"{r.get('seconds', 0.0):>7.2f}  {detail}")
    failed = sum(r["status"] != "ok" for r in rows)
    print(f"{len(rows) - failed} of {len(rows)} takes done" + (f", {failed} failed" if failed else ""))
