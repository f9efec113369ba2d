"""Swallow templates: our detection + landmark registration against simple baselines, on known swallows.

    python benchmarks/bench_swallow_registration.py [--seeds 3] [--standin-seeds 20] [--no-skfda]

Template error as issue 13 defines it: the RMS difference between a template and the true swallow
over the true swallow's duration, after the best time shift (within 1 s) and time scale (0.8-1.25)
of the template, / the true peak height (``motion.swallow.template_error``).

Data (``data.synthetic_tau``):

- the shape family ``SWALLOW_SHAPES`` (single peak; two-stage rise with a hold; each with and without
  dip and undershoot), base durations 0.8 / 1.6 / 3.0 s, 30 and 60 fps, 8 copies per set
  (``warped_swallow_clips``: centred random monotone warps, durations x0.85-1.2, amplitudes x0.8-1.2,
  offsets, white noise 0.0015, quiet motion 0.0008, drift 0.004 tau; 0.4-1.2 s of rest around);
  truth: the structural mean.  "harder": warp strength 0.35 (not 0.25), motion 0.0015, drift 0.006.
  The detector's defaults were developed on this family.
- the held-out stand-in for the recorded check (``physiological_swallow_clips``, another code path:
  minimum-jerk two-stage swallows of 1.5-3 s, smooth sine-series warps, uncentred time and amplitude
  scales, 30 fps, quiet noisy tracks); truth: the swallow itself.  Nothing was tuned on it.

Methods, each on the same clips:

- ours: ``motion.swallow.build_template`` (detection, landmark selection, registration, mean);
- five-landmark: ``benchmarks/swallow_baseline.py``, a simple registration: rest from the first and last
  0.3 s (linear), 10% and 50% crossings either side of the maximum and the maximum, piecewise-linear
  warps to the mean landmarks, mean (the baseline issue 13 quotes for the recorded check);
- naive: the clips averaged on time since their start (rest removed with the true offset);
- skfda landmark elastic (optional, ``pip install ".[bench]"``): scikit-fda's
  ``landmark_elastic_registration`` on the five landmarks above, on a common 60 fps grid.

Also printed for the stand-in: the amplitude floor, the error of the truth scaled by the copies'
mean amplitude factor (the part no average of the copies can remove).
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, for `python benchmarks/...`

from swallow_baseline import five_landmark_mean, five_landmarks  # noqa: E402  (beside this script)

from data.synthetic_tau import SWALLOW_SHAPES, physiological_swallow_clips, swallow_profile, warped_swallow_clips  # noqa: E402
from data.tau_track import TauTrack  # noqa: E402
from motion.swallow import build_template, template_error  # noqa: E402

SCENARIOS = {
    "family": dict(noise=0.0015, drift=0.004, wander=0.0008, warp_strength=0.25),
    "family, harder": dict(noise=0.0015, drift=0.006, wander=0.0015, warp_strength=0.35),
}


def naive(clips):
    span = min(c.time[-1] for c in clips)
    grid = np.arange(0.0, span, 1 / 60)
    return grid, np.mean([np.interp(grid, c.time, c.tau - c.offset) for c in clips], axis=0)


def skfda_landmark(clips):
    import skfda
    from skfda.preprocessing.registration import landmark_elastic_registration

    curves, marks = five_landmarks(clips)
    length = max(c.time[-1] for c in clips)
    grid = np.arange(int(np.floor(length * 60)) + 1) / 60
    data = np.stack([np.interp(grid, c.time, x, right=0.0) for c, x in zip(clips, curves)])
    registered = landmark_elastic_registration(skfda.FDataGrid(data, grid), marks)
    return grid, registered.data_matrix[..., 0].mean(axis=0)


def ours(clips):
    build = build_template([TauTrack(c.tau, c.time, c.fps, f"clip{i}") for i, c in enumerate(clips)])
    used = sum(r.used for r in build.clips)
    return build.template.time, build.template.tau, used


def score(methods, clips, truth_time, truth):
    row = {}
    for name, method in methods.items():
        started = time.perf_counter()
        out = method(clips)
        elapsed = time.perf_counter() - started
        shift = 3.0 if name == "naive" else 1.0
        row[name] = (template_error(out[0], out[1], truth_time, truth, max_shift=shift)[0], elapsed,
                     out[2] if len(out) > 2 else len(clips))
    return row


def table(title, rows):
    names = list(rows[0])
    print(f"\n{title}: {len(rows)} template(s) of 8 clips")
    print(f"{'method':28s} {'error % mean':>13s} {'max':>7s} {'clips used':>11s} {'ms':>7s}")
    for name in names:
        err = 100 * np.array([r[name][0] for r in rows])
        ms = 1000 * np.median([r[name][1] for r in rows])
        used = min(r[name][2] for r in rows)
        print(f"{name:28s} {err.mean():13.2f} {err.max():7.2f} {f'>= {used} of 8':>11s} {ms:7.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="sets per (shape, duration, fps) of the family")
    parser.add_argument("--standin-seeds", type=int, default=20)
    parser.add_argument("--no-skfda", action="store_true")
    args = parser.parse_args()
    warnings.filterwarnings("ignore")
    methods = {"ours": ours, "five-landmark": five_landmark_mean, "naive": naive}
    if not args.no_skfda:
        try:
            import skfda  # noqa: F401

            methods["skfda landmark elastic (5)"] = skfda_landmark
        except ImportError:
            print("scikit-fda not installed (pip install \".[bench]\"): its row is skipped")

    for scenario, options in SCENARIOS.items():
        rows, per_shape = [], {}
        for shape_name, shape in SWALLOW_SHAPES.items():
            for duration in (0.8, 1.6, 3.0):
                for fps in (30.0, 60.0):
                    for seed in range(args.seeds):
                        clips = warped_swallow_clips(8, seed=seed, fps_choices=(fps,), shape=shape, duration=duration,
                                                     lead=(0.4, 1.2), tail=(0.4, 1.2), **options)
                        amplitude = np.mean([c.amplitude for c in clips])
                        mean_duration = np.mean([c.duration for c in clips])
                        truth_time = np.linspace(0.0, mean_duration, 1001)
                        truth = swallow_profile(truth_time, 0.0, mean_duration, amplitude, shape)
                        row = score(methods, clips, truth_time, truth)
                        rows.append(row)
                        per_shape.setdefault(shape_name, []).append(row)
        table(f"scenario '{scenario}' {options}, all shapes x 0.8/1.6/3.0 s x 30/60 fps x {args.seeds} seeds", rows)
        print(f"{'per shape (mean / max %)':28s} " + "  ".join(f"{m}" for m in methods))
        for shape_name, shape_rows in per_shape.items():
            cells = []
            for m in methods:
                err = 100 * np.array([r[m][0] for r in shape_rows])
                cells.append(f"{err.mean():5.2f} / {err.max():5.2f}")
            print(f"  {shape_name:26s} " + "   ".join(cells))

    rows, floors = [], []
    for seed in range(args.standin_seeds):
        standin = physiological_swallow_clips(seed=10_000 + seed)
        rows.append(score(methods, standin.clips, standin.truth_time, standin.truth_tau))
        gain = np.mean([c.amplitude for c in standin.clips]) / standin.swallow.amplitude
        floors.append(template_error(standin.truth_time, gain * standin.truth_tau, standin.truth_time,
                                     standin.truth_tau)[0])
    table(f"held-out stand-in for the recorded check (physiological_swallow_clips, seeds 10000-"
          f"{10_000 + args.standin_seeds - 1})", rows)
    floor = 100 * np.array(floors)
    print(f"{'amplitude floor (mean gain)':28s} {floor.mean():13.2f} {floor.max():7.2f}")


if __name__ == "__main__":
    main()
