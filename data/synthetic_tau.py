"""Synthetic larynx motion: the swallow profile and random tau trajectories.

tau is in UV units of the larynx map, positive = up the neck (``models.rig``);
on HACK's template one UV unit is about 33 cm along the front of the neck, so
tau = 0.03 is about 1 cm.

Swallow kinematics: in the pharyngeal phase the hyolaryngeal complex rises by
about 1.5-2.5 cm and returns within roughly a second (videofluoroscopy:
Logemann, "Evaluation and Treatment of Swallowing Disorders", 2nd ed., 1998;
Kim & McCullough, Dysphagia 23:274-279, 2008, mean hyoid elevation ~1.5 cm
and laryngeal elevation ~2 cm).  Our profile has five landmarks: onset, a
small preparatory dip (valley), the peak, an undershoot below rest (valley)
and the return to rest; the alignment in ``motion.swallow`` uses them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

# Landmark times as fractions of the swallow's duration and their tau values
# as fractions of its amplitude: onset, dip, peak, undershoot, return.
SWALLOW_LANDMARK_PHASES = np.array([0.0, 0.12, 0.40, 0.68, 1.0])
SWALLOW_LANDMARK_LEVELS = np.array([0.0, -0.12, 1.0, -0.22, 0.0])
SWALLOW_AMPLITUDE = 0.055  # tau units, ~1.8 cm
SWALLOW_DURATION = 1.1     # seconds


@dataclass
class SwallowShape:
    """A swallow's shape: landmark phases in [0, 1] and levels (fractions of the amplitude)."""

    phases: np.ndarray = None
    levels: np.ndarray = None

    def __post_init__(self) -> None:
        self.phases = SWALLOW_LANDMARK_PHASES.copy() if self.phases is None else np.asarray(self.phases, float)
        self.levels = SWALLOW_LANDMARK_LEVELS.copy() if self.levels is None else np.asarray(self.levels, float)

    def __call__(self, phase: np.ndarray) -> np.ndarray:
        """Profile at ``phase`` (0 = onset, 1 = return); 0 outside [0, 1]; smooth (C1) landmarks."""
        phase = np.asarray(phase, dtype=np.float64)
        # Extra knots with zero level outside [0, 1] give zero slope at onset and return.
        knots = np.concatenate([[-0.2], self.phases, [1.2]])
        values = np.concatenate([[0.0], self.levels, [0.0]])
        # Smooth the landmarks into a C1 bump: PCHIP keeps extrema at the landmarks.
        out = PchipInterpolator(knots, values)(np.clip(phase, -0.2, 1.2))
        return np.where((phase >= 0) & (phase <= 1), out, 0.0)


def swallow_profile(time: np.ndarray, onset: float = 0.0, duration: float = SWALLOW_DURATION,
                    amplitude: float = SWALLOW_AMPLITUDE, shape: SwallowShape | None = None) -> np.ndarray:
    """tau displacement of one swallow starting at ``onset`` seconds, sampled at ``time`` [T] seconds."""
    shape = SwallowShape() if shape is None else shape
    return amplitude * shape((np.asarray(time, dtype=np.float64) - onset) / duration)


def swallow_landmark_times(onset: float = 0.0, duration: float = SWALLOW_DURATION,
                           shape: SwallowShape | None = None) -> np.ndarray:
    """Times (s) of onset, dip, peak, undershoot and return of a swallow."""
    shape = SwallowShape() if shape is None else shape
    return onset + duration * shape.phases


def random_tau_trajectory(num_frames: int, fps: float, seed: int, swallows_per_minute: float = 4.0,
                          speech: float = 0.008, drift: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """A plausible larynx track: rest, random swallows, speech-like wobble and slow drift.

    Returns (tau [T], swallow_onsets [S] in seconds).  ``speech`` is the
    standard deviation (tau units) of the band-limited 2-6 Hz speech motion,
    ``drift`` the amplitude of a sub-0.2 Hz posture drift.
    """
    rng = np.random.default_rng(seed)
    time = np.arange(num_frames) / fps
    length = num_frames / fps
    tau = np.zeros(num_frames)
    count = rng.poisson(swallows_per_minute * length / 60.0)
    onsets = np.sort(rng.uniform(0.0, max(length - SWALLOW_DURATION * 1.5, 0.0), size=count))
    # Keep swallows apart: at least one swallow duration between onsets.
    kept: list[float] = []
    for t in onsets:
        if not kept or t - kept[-1] > 1.6 * SWALLOW_DURATION:
            kept.append(float(t))
    for t in kept:
        tau += swallow_profile(time, t, SWALLOW_DURATION * rng.uniform(0.8, 1.25),
                               SWALLOW_AMPLITUDE * rng.uniform(0.75, 1.2))
    if speech > 0:
        spectrum = np.fft.rfft(rng.standard_normal(num_frames))
        freqs = np.fft.rfftfreq(num_frames, 1.0 / fps)
        spectrum[(freqs < 2.0) | (freqs > 6.0)] = 0.0
        wobble = np.fft.irfft(spectrum, n=num_frames)
        if wobble.std() > 0:
            # Speech comes in phrases: an envelope switching on and off every few seconds.
            envelope = (np.sin(2 * np.pi * time / rng.uniform(4.0, 8.0) + rng.uniform(0, 2 * np.pi)) > -0.2)
            envelope = np.convolve(envelope.astype(float), np.ones(int(fps * 0.2) or 1) / (int(fps * 0.2) or 1), "same")
            tau += speech * envelope * wobble / wobble.std()
    if drift > 0:
        phase = rng.uniform(0, 2 * np.pi)
        tau += drift * np.sin(2 * np.pi * time * rng.uniform(0.03, 0.15) + phase)
    return tau, np.array(kept)


def random_monotone_warps(count: int, seed: int, strength: float = 0.25, num_segments: int = 6,
                          resolution: int = 257, centered: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Random increasing maps of [0, 1] onto itself (time warps), piecewise linear.

    Each warp ``g`` maps a template phase to a clip phase; its ``num_segments``
    equal pieces of the template get slopes ``exp(strength * z)`` (z standard
    normal), rescaled so that ``g(0) = 0`` and ``g(1) = 1``.  With
    ``centered`` the warps are composed with the inverse of their mean, so their
    pointwise mean is exactly the identity: the template is then the
    structural mean of the warped clips (the usual identifiability convention of
    registration; Ramsay & Silverman, Functional Data Analysis, 2nd ed., ch. 7).

    Returns (phase [G], clip_phase [count, G]) with G = ``resolution``: warp i
    maps ``phase`` to ``clip_phase[i]``; ``np.interp(u, clip_phase[i], phase)``
    is its inverse (clip phase to template phase).
    """
    rng = np.random.default_rng(seed)
    phase = np.linspace(0.0, 1.0, resolution)
    knots = np.linspace(0.0, 1.0, num_segments + 1)
    slopes = np.exp(strength * rng.standard_normal((count, num_segments)))
    values = np.concatenate([np.zeros((count, 1)), np.cumsum(slopes, axis=1)], axis=1)
    values /= values[:, -1:]
    warps = np.stack([np.interp(phase, knots, v) for v in values])
    if centered and count > 1:
        mean = warps.mean(axis=0)                       # increasing, 0 -> 0, 1 -> 1
        inverse_of_mean = np.interp(phase, mean, phase)  # mean^-1 on the grid
        warps = np.stack([np.interp(inverse_of_mean, phase, w) for w in warps])
    return phase, warps


@dataclass
class SyntheticSwallowClip:
    """One synthetic swallow clip and the truth it was made from.

    tau [T] at time [T] seconds (uniform at ``fps``); the swallow starts at
    ``onset`` seconds, lasts ``duration`` seconds, peaks ``amplitude`` tau units
    above the rest level ``offset``; ``landmark_times`` [5] are the true times
    (s) of onset, dip, peak, undershoot and return in this clip.
    """

    time: np.ndarray
    tau: np.ndarray
    fps: float
    onset: float
    duration: float
    amplitude: float
    offset: float
    landmark_times: np.ndarray


def warped_swallow_clips(count: int, seed: int, fps_choices: tuple[float, ...] = (25.0, 30.0, 50.0, 60.0),
                         duration_range: tuple[float, float] = (0.85, 1.2),
                         amplitude_range: tuple[float, float] = (0.8, 1.2), warp_strength: float = 0.25,
                         noise: float = 0.0015, offset: float = 0.01, lead: tuple[float, float] = (0.3, 1.0),
                         tail: tuple[float, float] = (0.4, 1.2), drift: float = 0.0,
                         shape: SwallowShape | None = None) -> list[SyntheticSwallowClip]:
    """Clips of one known swallow: random monotone time warps, durations, amplitudes, noise and offsets.

    Clip i shows ``amplitude_i * SWALLOW_AMPLITUDE * shape(w_i(phase))`` where
    ``w_i`` is the inverse of a centred random warp (:func:`random_monotone_warps`)
    and phase runs over ``duration_i * SWALLOW_DURATION`` seconds; plus a rest
    level uniform in ``[-offset, offset]``, white noise of std ``noise`` (tau
    units), an optional linear drift of up to ``drift`` tau units over the clip,
    ``lead`` / ``tail`` seconds of rest before and after, sampled at a rate drawn
    from ``fps_choices``.  ``duration_range`` / ``amplitude_range`` are factors
    of SWALLOW_DURATION / SWALLOW_AMPLITUDE.  The structural mean of the clips
    is, up to the sampling of durations and warps,
    ``swallow_profile(t, 0, mean duration, mean amplitude, shape)``.
    """
    shape = SwallowShape() if shape is None else shape
    rng = np.random.default_rng(seed)
    phase, warps = random_monotone_warps(count, seed=int(rng.integers(2**31)), strength=warp_strength)
    clips = []
    for i in range(count):
        fps = float(rng.choice(fps_choices))
        duration = SWALLOW_DURATION * rng.uniform(*duration_range)
        amplitude = SWALLOW_AMPLITUDE * rng.uniform(*amplitude_range)
        onset = rng.uniform(*lead)
        length = onset + duration + rng.uniform(*tail)
        time = np.arange(int(np.floor(length * fps)) + 1) / fps
        clip_phase = (time - onset) / duration
        template_phase = np.interp(clip_phase, warps[i], phase)  # identity outside [0, 1]
        template_phase = np.where((clip_phase < 0) | (clip_phase > 1), clip_phase, template_phase)
        rest = rng.uniform(-offset, offset)
        tau = amplitude * shape(template_phase) + rest + noise * rng.standard_normal(len(time))
        if drift:
            tau += rng.uniform(-drift, drift) * time / time[-1]
        landmarks = onset + duration * np.interp(shape.phases, phase, warps[i])
        clips.append(SyntheticSwallowClip(time, tau, fps, onset, duration, amplitude, rest, landmarks))
    return clips
