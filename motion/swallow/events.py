"""Swallow detection's vocabulary: its thresholds, one swallow's landmarks, one track's analysis.

Landmark names and how each is measured: :mod:`motion.swallow.landmarks`; how swallows are found:
:mod:`motion.swallow.detect`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Landmark names in time order (p: percent of the height; k: count from the peak outwards); a
# swallow has those it shows.
LANDMARK_NAMES: tuple[str, ...] = ("dip_start", "dip", "rise_start", "rise<p>", "rise_max<k>", "rise_min<k>", "peak",
                                   "fall_max<k>", "fall_min<k>", "fall<p>", "fall_end", "undershoot", "undershoot_end")


@dataclass
class DetectionConfig:
    """Thresholds of swallow detection (``configs/swallow.yaml: detection``).

    Seconds are track time, tau values in tau units (0.03 ~ 1 cm on HACK).  A human swallow
    raises the larynx by 1.5-2.5 cm (``data.synthetic_tau``), i.e. 0.045-0.075 tau, over 0.5-4 s
    from onset to return; speech wobble is 2-6 Hz, damped by ``detect_smooth_seconds``.
    """

    smooth_fraction: float = 0.04         # Gaussian sigma of the signal landmarks are read from, as a fraction
    #                                       of the swallow's width at half height (0.5 s wide: 0.02 s)
    detect_smooth_seconds: float = 0.08   # Gaussian sigma of the signal swallows are found in
    baseline_seconds: float = 10.0        # running window of the first baseline (> twice the longest swallow)
    rest_seconds: float = 2.0             # running median window over the rest samples (follows drift)
    min_prominence: float = 0.015         # tau units (~0.5 cm): scipy.signal.find_peaks prominence (after the
    #                                       detection smoothing, which takes ~20% off a 0.5 s swallow)
    min_height: float = 0.015             # tau units above the rest baseline
    min_width_seconds: float = 0.1        # main elevation's width at half prominence
    max_width_seconds: float = 3.0        # (a 4 s single-peak swallow is ~2 s wide at half height)
    split_fraction: float = 0.2           # two elevations are two swallows only if the signal between them
    #                                       falls below this fraction of the higher one
    rest_fraction: float = 0.05           # rest band = max(rest_fraction * height, noise_factor * spread at rest)
    noise_factor: float = 3.0             # (also: intermediate peaks/valleys stand out by noise_factor * noise)
    rest_point: str = "tangent"           # onset/return: tangent (tangent intercept) | band (band crossing)
    crossing_levels: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    max_crossing_spread_seconds: float = 0.04  # a level crossed at times further apart than this is ambiguous
    feature_prominence: float = 0.08      # intermediate peaks/valleys: prominence >= this fraction of the height

    def __post_init__(self) -> None:
        if self.rest_point not in ("tangent", "band"):
            raise ValueError(f"DetectionConfig.rest_point must be 'tangent' or 'band', got '{self.rest_point}'")
        for key in ("baseline_seconds", "rest_seconds", "min_width_seconds"):
            if not getattr(self, key) > 0:
                raise ValueError(f"DetectionConfig.{key} must be positive, got {getattr(self, key)}")
        if not self.max_width_seconds > self.min_width_seconds:
            raise ValueError(f"DetectionConfig.max_width_seconds ({self.max_width_seconds}) must exceed "
                             f"min_width_seconds ({self.min_width_seconds})")
        if not 0 < self.split_fraction < 0.5:
            raise ValueError(f"DetectionConfig.split_fraction must be in (0, 0.5), got {self.split_fraction}")
        bad = [f for f in self.crossing_levels if not 0 < f < 1]
        if bad:
            raise ValueError(f"DetectionConfig.crossing_levels must lie in (0, 1), got {list(self.crossing_levels)}")


@dataclass
class SwallowEvent:
    """One swallow in a track.

    landmarks: name -> time (s, track time) of each landmark found, in time order; levels: name ->
    tau above the rest baseline there; height: the peak's; prominence: scipy's on the detection
    signal; missing: landmark name -> why this swallow has none (only onset, return, dip, undershoot
    and the half-height crossings are reported).  Names: :mod:`motion.swallow.landmarks`.
    """

    landmarks: dict[str, float]
    levels: dict[str, float]
    height: float
    prominence: float
    missing: dict[str, str] = field(default_factory=dict)

    def has(self, name: str) -> bool:
        return name in self.landmarks

    def time(self, name: str) -> float:
        """The landmark's time (s), NaN if this swallow has none."""
        return float(self.landmarks.get(name, np.nan))

    @property
    def peak_time(self) -> float:
        return self.landmarks["peak"]

    @property
    def onset(self) -> float:
        """Where the swallow leaves rest (s): the start of its dip if it has one, else of its rise; NaN if neither."""
        return self.time("dip_start") if self.has("dip_start") else self.time("rise_start")

    @property
    def return_time(self) -> float:
        """Where the swallow is back at rest (s): the end of its undershoot if any, else of its descent; NaN
        if neither."""
        return self.time("undershoot_end") if self.has("undershoot_end") else self.time("fall_end")

    @property
    def duration(self) -> float:
        """Onset to return (s); NaN without either."""
        return self.return_time - self.onset

    @property
    def width(self) -> float:
        """Width of the main elevation at half height (s): ``fall50 - rise50``."""
        return self.time("fall50") - self.time("rise50")

    def notes(self) -> str:
        return "; ".join(f"{name}: {why}" for name, why in self.missing.items())


@dataclass
class TrackAnalysis:
    """Swallows of one uniformly sampled track and its rest baseline.

    events: swallows in time order; baseline [T] rest level (tau); noise: robust std of the white
    noise (tau); broken: why swallows were found but not measured; note: why no swallow was found.
    """

    events: list[SwallowEvent]
    baseline: np.ndarray
    noise: float
    broken: list[str] = field(default_factory=list)
    note: str = ""

