"""An ensemble's spread over training seeds, from the members of runs already made (no training).

    python benchmarks/score_members.py OUT [OUT ...] [--family damped] [--seed 0]

``OUT``: work folders of ``bench_larynx_real.py --training-seeds ...``; each run of a family, benchmark seed
``s`` and training seed ``t`` left ``OUT/<family>/seed<s>/train<t>/members_heldout.npz`` (the held-out ``tau``
[sequences, frames], every member's prediction ``member`` and, where the members refit, ``fold_member`` before
the refits: [members, sequences, frames]) and its ridge RMSE in ``OUT/results.json``.

Four training seeds give four ensembles, and a standard deviation from four values is uncertain by a factor of
two either way (a 90% interval of 0.62-2.92 times the estimate, chi-square with 3 degrees of freedom).  The
members give more: member k of every run validates on the same fold k of the takes (``data.split_seed`` fixes
the folds, the training seed only the member's seed), so an ensemble whose member k comes from any of the n
runs is as good a draw of "an ensemble trained from other seeds" as the runs' own.  The n^K recombined
ensembles give the ensemble's mean and spread over member seeds.  One network (member 0 before any refit: the
network ``task.members=1`` trains, which validates on fold 0) has only its n runs; the members before their
refits that validated on the other folds show what one network scores with another validation split.  Prints
per family the runs' RMSE / ridge, and per combination (``refit``: the members as the ensemble holds them;
``fold``: before their refits) the recombined mean and standard deviation and its ratio to one network's.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from base.errors import InputError  # noqa: E402
from models.larynx import trimmed_mean  # noqa: E402

COMBINATIONS = {"refit": "member", "fold": "fold_member"}  # printed name -> the npz array


def read_run(path: Path) -> dict[str, np.ndarray]:
    """The arrays of one ``members_heldout.npz``; InputError naming the file and what it lacks."""
    try:
        with np.load(path) as npz:
            arrays = {k: npz[k].astype(np.float64) for k in npz.files}
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read ({e}); expected bench_larynx_real's members_heldout.npz") from None
    missing = [k for k in ("tau", "member") if k not in arrays]
    if missing:
        raise InputError(f"{path}: no {', '.join(missing)}; expected tau [sequences, frames] and member "
                         "[members, sequences, frames]")
    return arrays


def rmse(prediction: np.ndarray, tau: np.ndarray) -> float:
    """Root mean square of ``prediction - tau`` over every frame of every sequence, in float64."""
    return float(np.sqrt(np.mean((np.asarray(prediction, np.float64) - tau) ** 2)))


def ensemble_rmse(members: np.ndarray, tau: np.ndarray) -> float:
    """RMSE of the trimmed mean (the ensemble's combination) of ``members`` [K, sequences, frames] against tau."""
    return rmse(trimmed_mean(torch.as_tensor(members, dtype=torch.float64)).numpy(), tau)


def recombined_rmse(runs: list[dict[str, np.ndarray]], key: str) -> np.ndarray:
    """[n^K]: the RMSE of every ensemble whose member k is member k of any of the n ``runs`` (``runs[i][key]``
    [K, sequences, frames]); the runs must share the held-out tau and the member count."""
    tau = runs[0]["tau"]
    if any(r["tau"].shape != tau.shape or not np.array_equal(r["tau"], tau) for r in runs):
        raise InputError("the runs hold different held-out tau: recombine runs of one family and benchmark seed")
    count = runs[0][key].shape[0]
    if any(r[key].shape[0] != count for r in runs):
        raise InputError(f"the runs' {key} hold {[r[key].shape[0] for r in runs]} members; expected the same count")
    return np.array([ensemble_rmse(np.stack([runs[i][key][k] for k, i in enumerate(choice)]), tau)
                     for choice in itertools.product(range(len(runs)), repeat=count)])


def find_runs(outs: list[Path], family: str | None, seed: int) -> dict[str, dict[int, tuple[Path, float]]]:
    """family -> training seed -> (its members_heldout.npz, the run's ridge RMSE) for benchmark seed ``seed``."""
    found: dict[str, dict[int, tuple[Path, float]]] = {}
    for out in outs:
        results_file = out / "results.json"
        if not results_file.is_file():
            raise InputError(f"{results_file}: not found; expected a bench_larynx_real.py work folder")
        try:
            results = json.loads(results_file.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"{results_file}: not JSON ({e}); expected bench_larynx_real.py's results") from None
        for path in sorted(out.glob(f"*/seed{seed}/train*/members_heldout.npz")):
            name, training_seed = path.parts[-4], int(path.parts[-2].removeprefix("train"))
            if family not in (None, name):
                continue
            ridge = {run["ridge"] for run in results.get(name, [])}
            if len(ridge) != 1:  # the ridge depends on the benchmark seed only: one value per family here
                raise InputError(f"{results_file}: {len(ridge)} ridge RMSEs for {name}; expected the runs of "
                                 "one benchmark seed")
            found.setdefault(name, {})[training_seed] = (path, ridge.pop())
    if not found:
        raise InputError(f"no <family>/seed{seed}/train<t>/members_heldout.npz in {', '.join(map(str, outs))}"
                         + (f" for {family}" if family else "") + "; expected runs of --training-seeds")
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("outs", nargs="+", type=Path, help="bench_larynx_real.py work folders")
    parser.add_argument("--family", default=None, help="only this family")
    parser.add_argument("--seed", type=int, default=0, help="the benchmark seed of the runs")
    args = parser.parse_args()
    try:
        found = find_runs(args.outs, args.family, args.seed)
        for family, by_seed in sorted(found.items()):
            seeds = sorted(by_seed)
            runs = [read_run(by_seed[t][0]) for t in seeds]
            ridge = by_seed[seeds[0]][1]
            print(f"{family}, benchmark seed {args.seed}, training seeds {seeds} (RMSE / ridge):")
            one = np.array([rmse(r.get("fold_member", r["member"])[0], r["tau"]) / ridge for r in runs])
            print(f"  one network   {' '.join(f'{v:.3f}' for v in one)} = {one.mean():.3f} +- {one.std():.3f}")
            if all("fold_member" in r for r in runs):  # a single network validated on fold k, for every k
                folds = np.array([[rmse(f, r["tau"]) / ridge for f in r["fold_member"]] for r in runs])
                print(f"  one network on each fold {' '.join(f'{v:.3f}' for v in folds.mean(0))}: "
                      f"{folds.mean():.3f} +- {folds.std():.3f} over the runs and folds")
            for name, key in COMBINATIONS.items():
                if not all(key in r for r in runs):
                    continue
                own = np.array([ensemble_rmse(r[key], r["tau"]) for r in runs]) / ridge
                mixed = recombined_rmse(runs, key) / ridge
                ratio = f"{mixed.std() / one.std():.2f}" if one.std() > 0 else "-"
                print(f"  {name:<13} {' '.join(f'{v:.3f}' for v in own)} = {own.mean():.3f} +- {own.std():.3f}; "
                      f"{len(mixed)} recombined {mixed.mean():.3f} +- {mixed.std():.4f}, spread / one network's "
                      f"{ratio}")
    except InputError as e:
        raise SystemExit(f"error: {e}") from None


if __name__ == "__main__":
    main()
