"""Synthetic larynx motion: the swallow profile and random tau trajectories.

tau is in UV units of the larynx map, positive = up the neck (``models.rig``);
on HACK's template one UV unit is about 33 cm along the front of the neck, so
tau = 0.03 is about 1 cm.

Swallow kinematics: in the pharyngeal phase the hyolaryngeal complex rises by
about 1.5-2.5 cm and returns within roughly a second (videofluoroscopy:
Logemann, "Evaluation and Treatment of Swallowing Disorders", 2nd ed., 1998;
Kim & McCullough, Dysphagia 23:274-279, 2008, mean hyoid elevation ~1.5 cm
and laryngeal elevation ~2 cm).  The default profile has five landmarks: onset,
a small preparatory dip (valley), the peak, an undershoot below rest (valley)
and the return to rest.

Recorded swallows differ (issue 13, from a recording on a real subject): the larynx rises in two
stages (a first rise to about a third of the peak, a short hold or slight dip, the main elevation),
stays up briefly and descends; onset to return takes 1.5-3 s; there need not be a dip before or an
undershoot after.  Two generators cover such shapes:

- :data:`SWALLOW_SHAPES`: a family of PCHIP knot shapes (single peak, two-stage rise with a hold,
  each with and without dip and undershoot) for :func:`warped_swallow_clips`; the swallow tests
  and the detector's defaults are developed on these.
- :func:`physiological_swallow_clips`: a held-out stand-in for recorded swallows built on another
  code path (a sum of minimum-jerk transitions between levels, smooth sine-series time warps,
  uncentred scales, quiet tracks with band-limited motion); nothing is tuned on it.
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

    @property
    def peak_phase(self) -> float:
        """Phase of the highest knot (PCHIP keeps the maximum there)."""
        return float(self.phases[int(np.argmax(self.levels))])

    def __call__(self, phase: np.ndarray) -> np.ndarray:
        """Profile at ``phase`` (0 = onset, 1 = return); 0 outside [0, 1]; smooth (C1) landmarks."""
        phase = np.asarray(phase, dtype=np.float64)
        # Extra knots with zero level outside [0, 1] give zero slope at onset and return.
        knots = np.concatenate([[-0.2], self.phases, [1.2]])
        values = np.concatenate([[0.0], self.levels, [0.0]])
        # Smooth the landmarks into a C1 bump: PCHIP keeps extrema at the landmarks.
        out = PchipInterpolator(knots, values)(np.clip(phase, -0.2, 1.2))
        return np.where((phase >= 0) & (phase <= 1), out, 0.0)


# The shape family of the swallow tests (issue 13): knots (phase, level); PCHIP puts extrema at knots
# where the slope changes sign and is monotone in between.  "two_stage": a first rise to ~1/3 of
# the peak, a hold (monotone, nearly flat), the main elevation, a brief plateau, the descent.
SWALLOW_SHAPES: dict[str, SwallowShape] = {
    "classic": SwallowShape(),
    "single": SwallowShape([0.0, 0.45, 1.0], [0.0, 1.0, 0.0]),
    "two_stage": SwallowShape([0.0, 0.2, 0.34, 0.52, 0.62, 1.0], [0.0, 0.34, 0.37, 1.0, 0.96, 0.0]),
    "two_stage_dip": SwallowShape([0.0, 0.07, 0.22, 0.34, 0.52, 0.62, 0.84, 1.0],
                                  [0.0, -0.1, 0.35, 0.31, 1.0, 0.96, -0.16, 0.0]),
}


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


@dataclass
class SwallowTruth:
    """One generated swallow: ``onset`` and ``peak_time`` (s), ``duration`` (s, onset to return),
    ``amplitude`` (tau)."""

    onset: float
    duration: float
    amplitude: float
    peak_time: float


def tau_trajectory_with_truth(num_frames: int, fps: float, seed: int, swallows_per_minute: float = 4.0,
                              speech: float = 0.008, drift: float = 0.002) -> tuple[np.ndarray, list[SwallowTruth]]:
    """A plausible larynx track and the swallows in it: rest, random swallows, speech-like wobble and slow drift.

    Returns (tau [T], swallows in time order).  ``speech`` is the standard deviation (tau units) of
    the band-limited 2-6 Hz speech motion, ``drift`` the amplitude of a sub-0.2 Hz posture drift.
    Each swallow is ``swallow_profile`` with duration SWALLOW_DURATION x U(0.8, 1.25) and amplitude
    SWALLOW_AMPLITUDE x U(0.75, 1.2); its peak (of the swallow alone) is 0.4 of the duration after the onset.
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
    truth = []
    peak_phase = SwallowShape().peak_phase
    for t in kept:
        duration = SWALLOW_DURATION * rng.uniform(0.8, 1.25)
        amplitude = SWALLOW_AMPLITUDE * rng.uniform(0.75, 1.2)
        tau += swallow_profile(time, t, duration, amplitude)
        truth.append(SwallowTruth(t, float(duration), float(amplitude), t + peak_phase * float(duration)))
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
    return tau, truth


def random_tau_trajectory(num_frames: int, fps: float, seed: int, swallows_per_minute: float = 4.0,
                          speech: float = 0.008, drift: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tau_trajectory_with_truth` returning (tau [T], swallow_onsets [S] in seconds)."""
    tau, truth = tau_trajectory_with_truth(num_frames, fps, seed, swallows_per_minute, speech, drift)
    return tau, np.array([s.onset for s in truth])


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
    ``onset`` seconds, lasts ``duration`` seconds (onset to return), peaks
    ``amplitude`` tau units above the rest level ``offset`` at ``peak_time``
    seconds; ``landmark_times`` [K] are the true times (s) of the shape's knots
    in this clip (for the default shape: onset, dip, peak, undershoot, return).
    """

    time: np.ndarray
    tau: np.ndarray
    fps: float
    onset: float
    duration: float
    amplitude: float
    offset: float
    landmark_times: np.ndarray
    peak_time: float


def band_limited_motion(num_frames: int, fps: float, std: float, low_hz: float, high_hz: float,
                        rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise [T] band-limited to [low_hz, high_hz] (FFT mask), scaled to standard deviation ``std``."""
    if std <= 0 or num_frames < 2:
        return np.zeros(num_frames)
    spectrum = np.fft.rfft(rng.standard_normal(num_frames))
    freqs = np.fft.rfftfreq(num_frames, 1.0 / fps)
    spectrum[(freqs < low_hz) | (freqs > high_hz)] = 0.0
    motion = np.fft.irfft(spectrum, n=num_frames)
    return std * motion / motion.std() if motion.std() > 0 else motion


def warped_swallow_clips(count: int, seed: int, fps_choices: tuple[float, ...] = (25.0, 30.0, 50.0, 60.0),
                         duration_range: tuple[float, float] = (0.85, 1.2),
                         amplitude_range: tuple[float, float] = (0.8, 1.2), warp_strength: float = 0.25,
                         noise: float = 0.0015, offset: float = 0.01, lead: tuple[float, float] = (0.3, 1.0),
                         tail: tuple[float, float] = (0.4, 1.2), drift: float = 0.0,
                         shape: SwallowShape | None = None, duration: float = SWALLOW_DURATION,
                         wander: float = 0.0) -> list[SyntheticSwallowClip]:
    """Clips of one known swallow: random monotone time warps, durations, amplitudes, noise and offsets.

    Clip i shows ``amplitude_i * SWALLOW_AMPLITUDE * shape(w_i(phase))`` where
    ``w_i`` is the inverse of a centred random warp (:func:`random_monotone_warps`)
    and phase runs over ``duration_i * duration`` seconds; plus a rest level
    uniform in ``[-offset, offset]``, white noise of std ``noise`` (tau units),
    an optional linear drift of up to ``drift`` tau units over the clip, optional
    quiet motion (0.1-1.5 Hz, std ``wander`` tau units), ``lead`` / ``tail``
    seconds of rest before and after, sampled at a rate drawn from
    ``fps_choices``.  ``duration_range`` / ``amplitude_range`` are factors of
    ``duration`` (s, default SWALLOW_DURATION) / SWALLOW_AMPLITUDE.  The
    structural mean of the clips is, up to the sampling of durations and warps,
    ``swallow_profile(t, 0, mean duration, mean amplitude, shape)``.
    """
    shape = SwallowShape() if shape is None else shape
    rng = np.random.default_rng(seed)
    phase, warps = random_monotone_warps(count, seed=int(rng.integers(2**31)), strength=warp_strength)
    peak_knot = int(np.argmax(shape.levels))
    clips = []
    for i in range(count):
        fps = float(rng.choice(fps_choices))
        clip_duration = duration * rng.uniform(*duration_range)
        amplitude = SWALLOW_AMPLITUDE * rng.uniform(*amplitude_range)
        onset = rng.uniform(*lead)
        length = onset + clip_duration + rng.uniform(*tail)
        time = np.arange(int(np.floor(length * fps)) + 1) / fps
        clip_phase = (time - onset) / clip_duration
        template_phase = np.interp(clip_phase, warps[i], phase)  # identity outside [0, 1]
        template_phase = np.where((clip_phase < 0) | (clip_phase > 1), clip_phase, template_phase)
        rest = rng.uniform(-offset, offset)
        tau = amplitude * shape(template_phase) + rest + noise * rng.standard_normal(len(time))
        if drift:
            tau += rng.uniform(-drift, drift) * time / time[-1]
        if wander:
            tau += band_limited_motion(len(time), fps, wander, 0.1, 1.5, rng)
        landmarks = onset + clip_duration * np.interp(shape.phases, phase, warps[i])
        clips.append(SyntheticSwallowClip(time, tau, fps, onset, clip_duration, amplitude, rest, landmarks,
                                          float(landmarks[peak_knot])))
    return clips


# --------------------------------------------------------------------------- held-out stand-in


def _minimum_jerk(u: np.ndarray) -> np.ndarray:
    """The minimum-jerk transition 10u^3 - 15u^4 + 6u^5 from 0 (u <= 0) to 1 (u >= 1) (Flash & Hogan 1985)."""
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u)


@dataclass
class PhysiologicalSwallow:
    """A two-stage swallow as a sum of minimum-jerk transitions (the stand-in's truth).

    Over ``duration`` seconds: a first rise to ``first_level`` of the peak over ``first_rise``
    (fractions of the duration), a hold of ``hold`` with a dip of ``hold_dip``, the main elevation
    over ``main_rise`` to 1, a plateau of ``plateau`` sagging by ``sag``, then the descent to rest;
    scaled by ``amplitude`` (tau units).
    """

    duration: float
    amplitude: float
    first_level: float
    first_rise: float
    hold: float
    hold_dip: float
    main_rise: float
    plateau: float
    sag: float

    @property
    def peak_time(self) -> float:
        """Seconds from the onset to the end of the main elevation (the maximum, before the plateau sags)."""
        return self.duration * (self.first_rise + self.hold + self.main_rise)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """tau above rest at ``t`` [...] seconds from the onset (0 outside [0, duration])."""
        d = self.duration
        t = np.asarray(t, dtype=np.float64)
        t1 = d * self.first_rise
        t2 = t1 + d * self.hold
        t3 = t2 + d * self.main_rise
        t4 = t3 + d * self.plateau
        level = self.first_level * _minimum_jerk(t / t1)
        level = level - self.hold_dip * np.sin(np.pi * np.clip((t - t1) / (t2 - t1), 0.0, 1.0)) ** 2
        level = level + (1.0 - self.first_level) * _minimum_jerk((t - t2) / (t3 - t2))
        level = level - self.sag * np.sin(0.5 * np.pi * np.clip((t - t3) / (t4 - t3), 0.0, 1.0)) ** 2
        level = level - (1.0 - self.sag) * _minimum_jerk((t - t4) / (d - t4))
        return np.where((t >= 0) & (t <= d), self.amplitude * level, 0.0)


def random_physiological_swallow(rng: np.random.Generator, duration_range: tuple[float, float] = (1.5, 3.0)
                                 ) -> PhysiologicalSwallow:
    """A random :class:`PhysiologicalSwallow`: 1.5-3 s, 1.4-2.4 cm (tau 0.042-0.072), first stage 0.28-0.40."""
    first_rise, hold, main_rise, plateau = rng.uniform(0.12, 0.2), rng.uniform(0.08, 0.18), \
        rng.uniform(0.14, 0.22), rng.uniform(0.05, 0.12)
    return PhysiologicalSwallow(duration=float(rng.uniform(*duration_range)),
                                amplitude=float(rng.uniform(0.042, 0.072)),
                                first_level=float(rng.uniform(0.28, 0.40)), first_rise=first_rise, hold=hold,
                                hold_dip=float(rng.uniform(0.0, 0.05)), main_rise=main_rise, plateau=plateau,
                                sag=float(rng.uniform(0.0, 0.06)))


@dataclass
class PhysiologicalClips:
    """The stand-in for recorded swallows: copies of one swallow in quiet tracks, and the truth.

    clips: the tracks (``SyntheticSwallowClip``; ``landmark_times`` holds the copy's onset, peak and
    return); swallow: the true swallow; truth_time [R] (s from its onset, over its duration) and
    truth_tau [R] (tau above rest): the curve a template is scored against.
    """

    clips: list[SyntheticSwallowClip]
    swallow: PhysiologicalSwallow
    truth_time: np.ndarray
    truth_tau: np.ndarray


def physiological_swallow_clips(seed: int, count: int = 8, fps: float = 30.0, noise: float = 0.0008,
                                motion: float = 0.0012, warp: float = 0.12,
                                time_scale: tuple[float, float] = (0.85, 1.18),
                                amplitude_scale: tuple[float, float] = (0.85, 1.15), offset: float = 0.02,
                                drift: float = 0.003, lead: tuple[float, float] = (0.5, 1.5),
                                tail: tuple[float, float] = (0.5, 1.5)) -> PhysiologicalClips:
    """``count`` time-warped, scaled and offset copies of one random two-stage swallow in quiet noisy tracks.

    Copy i is ``g_i * swallow(s_i * w_i(u))`` over ``s_i * duration`` seconds with u its phase: w_i a
    smooth increasing warp of [0, 1], ``u + sum_k c_k sin(pi k u) / (pi k)`` (k = 1..3, c_k normal with
    std ``warp``, scaled down so that the slope stays above 0.4); s_i uniform in ``time_scale``,
    g_i in ``amplitude_scale`` (neither centred on 1: the truth is the swallow itself, scale 1).
    Each track: a rest level uniform in [-offset, offset], a linear drift up to ``drift``, quiet motion
    (0.2-1.5 Hz, std ``motion``) and white noise (std ``noise``), ``lead`` / ``tail`` seconds around the
    swallow, at ``fps``.  This generator shares no code with :func:`warped_swallow_clips` or
    :data:`SWALLOW_SHAPES` (the held-out check of ``motion.swallow``).
    """
    rng = np.random.default_rng(seed)
    swallow = random_physiological_swallow(rng)
    k = np.arange(1, 4)
    clips = []
    for _ in range(count):
        c = rng.normal(0.0, warp, size=3)
        worst = np.abs(c).sum()
        if worst > 0.6:
            c *= 0.6 / worst  # w'(u) = 1 + sum c_k cos(pi k u) >= 0.4
        stretch = float(rng.uniform(*time_scale))
        gain = float(rng.uniform(*amplitude_scale))
        onset = float(rng.uniform(*lead))
        span = stretch * swallow.duration
        length = onset + span + float(rng.uniform(*tail))
        time = np.arange(int(np.floor(length * fps)) + 1) / fps
        u = np.clip((time - onset) / span, 0.0, 1.0)
        warped = u + (c[None, :] * np.sin(np.pi * k[None, :] * u[:, None]) / (np.pi * k[None, :])).sum(axis=1)
        inside = (time >= onset) & (time <= onset + span)
        tau = np.where(inside, gain * swallow(warped * swallow.duration), 0.0)
        rest = float(rng.uniform(-offset, offset))
        tau = tau + rest + rng.uniform(-drift, drift) * time / time[-1]
        tau = tau + band_limited_motion(len(time), fps, motion, 0.2, 1.5, rng) + noise * rng.standard_normal(len(time))
        # Where the copy peaks: invert the warp at the swallow's peak phase on a fine grid.
        fine = np.linspace(0.0, 1.0, 4001)
        fine_warp = fine + (c[None, :] * np.sin(np.pi * k[None, :] * fine[:, None]) / (np.pi * k[None, :])).sum(axis=1)
        peak_u = float(np.interp(swallow.peak_time / swallow.duration, fine_warp, fine))
        marks = np.array([onset, onset + span * peak_u, onset + span])
        clips.append(SyntheticSwallowClip(time, tau, fps, onset, span, gain * swallow.amplitude, rest, marks,
                                          float(marks[1])))
    truth_time = np.linspace(0.0, swallow.duration, int(np.ceil(swallow.duration * 500)) + 1)
    return PhysiologicalClips(clips, swallow, truth_time, swallow(truth_time))
