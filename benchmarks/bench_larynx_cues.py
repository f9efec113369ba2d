"""Does a trained expression -> larynx model learn whose swallows follow what?  Per swallow-cue kind.

    python benchmarks/bench_larynx_cues.py --checkpoint runs/.../checkpoints/best.pt [--checkpoint ...]
                                           [--cues seal,pause,snap,blink] [--subjects 24] [--seconds 60]

``data=synthetic`` draws each person's swallow cue from ``data.swallow_cues`` (``data.synthetic_larynx``:
a lip seal, a pause of the jaw, the jaw snapping shut, a blink on a closed jaw); the default generator has
the seal alone.  A run trained on several kinds, e.g.

    python train.py 'data.swallow_cues=[seal,pause,snap,blink]' trainer.early_stopping_patience=null

has to tell from a person's pairs which event their larynx follows, as a model trained on real people
would.  This script scores each checkpoint on new takes of ``data=synthetic``'s training people (seed 0,
each with their style, as the run's validation scores them), drawn with the kinds of ``--cues`` (default:
the checkpoint's ``data.swallow_cues``), and prints per kind: the people, their tau's standard deviation,
the RMS of their swallows' part of tau (what a perfect articulation that placed no swallow would score), and
each checkpoint's RMSE, each over all frames and over the frames inside the swallows.  A model that learnt a
kind's swallows is well below the swallows' RMS there; one that did not sits at it.  No training; 30 s per checkpoint.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from base.errors import InputError  # noqa: E402
from data.pairs import LarynxSequence  # noqa: E402
from data.synthetic_larynx import SWALLOW_CUES, TRAINING_RANGES, larynx_response, make_sequence, subject_params  # noqa: E402,E501
from models.checkpoint import load_checkpoint, load_model  # noqa: E402
from models.larynx import predict_tau  # noqa: E402
from tasks.larynx_transformer import SyntheticData  # noqa: E402

SEED = 0  # data=synthetic's default data seed: the people a default run trained on


def swallow_part(psi: np.ndarray, fps: float, person) -> np.ndarray:
    """[T]: the person's swallows' part of their (noise-free) tau."""
    silent = dataclasses.replace(person, swallow_amplitude=0.0)
    return larynx_response(psi, fps, person) - larynx_response(psi, fps, silent)


def score(predict: Callable[[LarynxSequence], np.ndarray], cues: tuple[str, ...], subjects: int, seconds: float,
          fps: float, take: int) -> dict[str, dict[str, float]]:
    """kind -> {people, tau_std, swallow_rms, swallow_rms_in_swallows, rmse, rmse_in_swallows} over new takes
    (index ``take``) of the first ``subjects`` training people of a generator with ``cues``; ``predict`` maps a
    sequence to its tau [T]."""
    ranges = dataclasses.replace(TRAINING_RANGES, cues=cues)
    frames = int(round(seconds * fps))
    sums: dict[str, dict[str, list]] = {}
    for subject in range(subjects):
        person = subject_params(subject, SEED, ranges)
        sequence = make_sequence(subject, take, frames, fps, SEED, ranges=ranges)
        events = swallow_part(sequence.psi, fps, person)
        error = predict(sequence).astype(np.float64) - sequence.tau
        inside = np.abs(events) > 1e-4
        part = sums.setdefault(person.cue, {"people": [], "tau": [], "events": [], "events_inside": [], "error": [],
                                            "inside": []})
        part["people"].append(subject)
        part["tau"].append(sequence.tau - sequence.tau.mean())
        part["events"].append(events)
        part["events_inside"].append(events[inside])
        part["error"].append(error)
        part["inside"].append(error[inside])
    out = {}
    for kind, part in sums.items():
        rms = {k: float(np.sqrt(np.mean(np.concatenate(part[k]) ** 2)))
               for k in ("tau", "events", "events_inside", "error", "inside")}
        out[kind] = {"people": float(len(part["people"])), "tau_std": rms["tau"], "swallow_rms": rms["events"],
                     "swallow_rms_in_swallows": rms["events_inside"], "rmse": rms["error"],
                     "rmse_in_swallows": rms["inside"]}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", action="append", required=True, help="a larynx_transformer checkpoint")
    parser.add_argument("--cues", help="comma-separated kinds the people are drawn from (default: the first "
                                       "checkpoint's data.swallow_cues)")
    parser.add_argument("--subjects", type=int, default=24, help="the first n training people (data=synthetic: 24)")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each person's new take")
    parser.add_argument("--take", type=int, default=100, help="take index (data=synthetic trains on 0-5, "
                                                               "validates on 6)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    unknown = [c for c in (args.cues or "").split(",") if c and c not in SWALLOW_CUES]
    if unknown:
        parser.error(f"--cues: unknown {', '.join(unknown)}; expected some of {', '.join(SWALLOW_CUES)}")
    configs = {}
    for path in args.checkpoint:
        try:
            configs[path] = load_checkpoint(path, "larynx_transformer").get("config") or {}
        except InputError as e:  # names the file and what is wrong with it
            raise SystemExit(f"error: {e}") from None
        kind = configs[path].get("data", {}).get("kind", "synthetic")
        if kind != "synthetic":
            raise SystemExit(f"error: {path}: trained on data={kind}; this script scores data=synthetic's people, "
                             "whose names a run on other data does not know")
    # A checkpoint from before data.swallow_cues was trained on seals alone, the default (SyntheticData).
    default = configs[args.checkpoint[0]].get("data", {}).get("swallow_cues", SyntheticData().swallow_cues)
    cues = tuple(args.cues.split(",")) if args.cues else tuple(default)
    results = {}
    for path in args.checkpoint:
        model, _ = load_model(path, "larynx_transformer")

        def predict(sequence: LarynxSequence, model=model) -> np.ndarray:  # with the person's style, when known
            return predict_tau(model, sequence.psi, sequence.subject if sequence.subject in model.subjects else None)

        results[path] = score(predict, cues, args.subjects, args.seconds, float(model.fps), args.take)
    print(f"new takes ({args.seconds:g} s) of data=synthetic's people 0-{args.subjects - 1}, cues {', '.join(cues)}; "
          "tau RMSE (UV), all frames | inside the swallows")
    for k, path in enumerate(args.checkpoint):
        print(f"  [{k}] {path}")
    kinds = [c for c in cues if c in next(iter(results.values()))]
    print(f"{'cue':<8}{'people':>7}{'tau std':>10}{'swallows rms':>22}"
          + "".join(f"{f'[{k}]':>22}" for k in range(len(args.checkpoint))))
    for kind in kinds:
        first = next(iter(results.values()))[kind]
        print(f"{kind:<8}{first['people']:>7.0f}{first['tau_std']:>10.5f}"
              f"{first['swallow_rms']:>12.5f} | {first['swallow_rms_in_swallows']:.5f}"
              + "".join(f"{r[kind]['rmse']:>12.5f} | {r[kind]['rmse_in_swallows']:.5f}" for r in results.values()))


if __name__ == "__main__":
    main()
