"""Make the shipped swallow template (models/pretrained/swallow_template.csv) from synthetic swallows.

    python benchmarks/make_swallow_template.py [--out models/pretrained/swallow_template.csv] [--ship]

Eight time-warped, scaled and offset copies of one two-stage physiological swallow in quiet noisy tracks
(``data.synthetic_tau.physiological_swallow_clips``, seed 0, 30 fps) are written as tau CSVs and averaged
by ``python -m motion.swallow``; ``--ship`` enters the result in the manifest.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data.synthetic_tau import physiological_swallow_clips  # noqa: E402
from data.tau_track import TauTrack, write_tau_track  # noqa: E402
from models.pretrained import PRETRAINED  # noqa: E402
from motion.swallow import read_template  # noqa: E402
from tools.ship_model import ship_file  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(PRETRAINED / "swallow_template.csv"))
    parser.add_argument("--ship", action="store_true")
    args = parser.parse_args()
    clips = physiological_swallow_clips(seed=0, count=8, fps=30.0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, clip in enumerate(clips.clips):
            paths.append(Path(tmp) / f"clip{i}.csv")
            write_tau_track(paths[-1], TauTrack(clip.tau, clip.time, clip.fps))
        subprocess.run([sys.executable, "-m", "motion.swallow", f"inputs=[{','.join(map(str, paths))}]",
                        f"out={args.out}", "plot=null"], cwd=REPO, check=True)
    template = read_template(args.out)
    figures = {"clips": 8, "clips_used": 8, "peak_height_tau": round(template.peak_height, 5),
               "duration_s": round(template.duration, 3), "true_peak_height_tau": round(clips.swallow.amplitude, 5),
               "true_duration_s": round(clips.swallow.duration, 3)}
    print(figures)
    if args.ship:
        ship_file(args.out, "swallow_template", "swallow_template", "python benchmarks/make_swallow_template.py --ship",
                  figures)


if __name__ == "__main__":
    main()
