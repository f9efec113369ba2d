"""Swallow registration: align the swallows of several clips by their shared landmarks and average them.

The paper's swallowing control curve is the average of captured swallows aligned "via peaks and
valleys"; this is landmark registration (Ramsay & Silverman, Functional Data Analysis, 2nd ed.,
2005, ch. 7): each swallow gets an increasing piecewise-linear (or PCHIP) time warp through its
landmarks, mapping the mean landmark times onto its own, is resampled through it on a uniform grid
and the aligned swallows are averaged (mean and per-time standard deviation).

Which landmarks (``motion.swallow.detect``): every swallow has its peak and its half-height
crossings, nearly every one where its rise leaves rest and its descent reaches it; the other level
crossings, dip, undershoot and intermediate peaks and valleys are used where the swallows agree on
them (:func:`select_landmarks`):

- a landmark is used if at least ``landmark_majority`` of the swallows have it, and that many put it
  within +-``landmark_agreement`` half-height widths of each other once aligned on the common
  landmarks;
- a swallow whose landmark lies outside that window (a valley that is another feature, a crossing
  on a hold in this clip and on the rise in the others), or out of the common order, leaves it out
  of its warp; a swallow without a landmark is warped through its others (the warp interpolates).

No swallow is dropped for its landmarks.  Rejected are only swallows whose half-height width or
height is off the median by more than ``max_width_ratio`` / ``max_height_ratio`` (not the same kind
of event), each with the reason.

Levels are displacements from each track's rest baseline; the template is 0 at rest, time 0 at
its onset, with ``pad_seconds`` of rest before the onset and after the return.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

from base.errors import InputError
from data.tau_track import TauTrack
from motion.swallow.detect import analyse_track, uniform_track
from motion.swallow.events import DetectionConfig, SwallowEvent, TrackAnalysis

ALWAYS = ("rise50", "peak", "fall50")  # every swallow that is not broken has these


@dataclass
class RegistrationConfig:
    """How swallows are aligned and averaged (``configs/swallow.yaml: registration``)."""

    template_fps: float = 60.0
    warp: str = "linear"                  # linear | pchip
    pad_seconds: float = 0.3              # rest kept before the onset and after the return
    landmark_majority: float = 0.5        # a landmark is used if this share of the swallows has it
    landmark_agreement: float = 0.3       # half-height widths within which the swallows must agree on a landmark
    max_width_ratio: float = 3.0          # swallows wider/narrower than this factor of the median are rejected
    max_height_ratio: float = 4.0         # same for peak heights
    min_swallows: int = 1

    def __post_init__(self) -> None:
        if self.warp not in ("linear", "pchip"):
            raise ValueError(f"RegistrationConfig.warp must be 'linear' or 'pchip', got '{self.warp}'")
        for key in ("template_fps", "landmark_agreement"):
            if not getattr(self, key) > 0:
                raise ValueError(f"RegistrationConfig.{key} must be positive, got {getattr(self, key)}")
        for key in ("max_width_ratio", "max_height_ratio"):
            if not getattr(self, key) > 1:
                raise ValueError(f"RegistrationConfig.{key} must exceed 1, got {getattr(self, key)}")
        if not 0 < self.landmark_majority <= 1:
            raise ValueError(f"RegistrationConfig.landmark_majority must be in (0, 1], got {self.landmark_majority}")


def landmark_warps(grid: np.ndarray, target: np.ndarray, landmarks: np.ndarray, kind: str = "linear") -> np.ndarray:
    """Increasing time warps through landmarks.

    Args:
        grid: [S] template times (s).
        target: [K] increasing template times of the landmarks.
        landmarks: [M,K] each curve's landmark times, increasing along K where finite; NaN where a
            curve has no such landmark (its warp goes through the others).  At least two finite per row.
        kind: ``linear`` (piecewise linear between the landmarks) or ``pchip`` (monotone cubic).

    Returns:
        [M,S]: each curve's time for each template time; beyond its first and last landmark the warp
        continues with the curve's mean slope between them.
    """
    grid = np.asarray(grid, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    landmarks = np.atleast_2d(np.asarray(landmarks, dtype=np.float64))
    out = np.empty((len(landmarks), len(grid)))
    for m, marks in enumerate(landmarks):
        have = np.isfinite(marks)
        x, y = target[have], marks[have]
        if len(x) < 2:
            raise ValueError(f"landmark_warps: curve {m} has {len(x)} landmark(s), need 2")
        if (np.diff(x) <= 0).any() or (np.diff(y) <= 0).any():
            raise ValueError(f"landmark_warps: curve {m}: landmarks must increase with the target")
        slope = (y[-1] - y[0]) / (x[-1] - x[0])
        if kind == "pchip" and len(x) > 2:
            inside = PchipInterpolator(x, y)(np.clip(grid, x[0], x[-1]))
        else:
            inside = np.interp(grid, x, y)
        out[m] = np.where(grid < x[0], y[0] + slope * (grid - x[0]),
                          np.where(grid > x[-1], y[-1] + slope * (grid - x[-1]), inside))
    return out


def register_curves(times: Sequence[np.ndarray], values: Sequence[np.ndarray], landmarks: np.ndarray,
                    target: np.ndarray, grid: np.ndarray, kind: str = "linear") -> np.ndarray:
    """Resample M curves through their landmark warps onto a template grid.

    Args:
        times, values: M curves, ``times[m]`` [T_m] increasing (any sampling), ``values[m]`` [T_m].
        landmarks: [M,K] curve times of the landmarks (NaN where missing, see :func:`landmark_warps`).
        target: [K] template times of the landmarks.
        grid: [S] template times.
        kind: ``linear`` or ``pchip`` warps.

    Returns:
        [M,S]: curve m at warp_m(grid); NaN where the warp leaves the curve's time span.
    """
    warps = landmark_warps(grid, target, landmarks, kind)
    return np.stack([np.interp(w, t, v, left=np.nan, right=np.nan) for w, t, v in zip(warps, times, values)])


def nan_mean_std(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, sample std (0 where one value) and count over axis 0 of [M,S], ignoring NaN."""
    count = np.isfinite(curves).sum(axis=0)
    filled = np.where(np.isfinite(curves), curves, 0.0)
    safe = np.maximum(count, 1)
    mean = filled.sum(axis=0) / safe
    square = (np.where(np.isfinite(curves), curves - mean, 0.0) ** 2).sum(axis=0)
    std = np.sqrt(square / np.maximum(count - 1, 1))
    return np.where(count > 0, mean, np.nan), np.where(count > 1, std, 0.0), count


@dataclass
class SwallowTemplate:
    """The swallow control curve.

    time [S] seconds (0 = onset, uniform at ``fps``), tau [S] displacement from rest (tau units),
    std [S] per-time standard deviation of the aligned swallows; landmarks [K] template times (s)
    of ``landmark_names`` (``motion.swallow.detect``; a template read from a file knows its onset only).
    """

    time: np.ndarray
    tau: np.ndarray
    std: np.ndarray
    fps: float
    landmarks: np.ndarray | None = None
    landmark_names: tuple[str, ...] = ()

    @property
    def peak_height(self) -> float:
        return float(np.max(self.tau))

    @property
    def duration(self) -> float:
        """Onset to return (s): from the first to the last of its rest landmarks (dip_start or rise_start,
        fall_end or undershoot_end); without them, the span where |tau| exceeds 4% of the peak."""
        names = list(self.landmark_names)
        starts = [n for n in ("dip_start", "rise_start") if n in names]
        ends = [n for n in ("undershoot_end", "fall_end") if n in names]
        if self.landmarks is not None and starts and ends:
            return float(self.landmarks[names.index(ends[0])] - self.landmarks[names.index(starts[0])])
        active = np.flatnonzero(np.abs(self.tau) > 0.04 * self.peak_height)
        return float(self.time[active[-1]] - self.time[active[0]]) if len(active) else 0.0

    def __call__(self, time: np.ndarray) -> np.ndarray:
        """Template displacement at template times [...] (PCHIP between samples, 0 outside its span)."""
        time = np.asarray(time, dtype=np.float64)
        inside = (time >= self.time[0]) & (time <= self.time[-1])
        values = PchipInterpolator(self.time, self.tau)(np.clip(time, self.time[0], self.time[-1]))
        return np.where(inside, values, 0.0)


@dataclass
class ClipReport:
    """What happened to one input: swallows found, used, why others (or the clip) were not used (reasons),
    and which landmarks its swallows left out of their warps (notes)."""

    source: str
    found: int = 0
    used: int = 0
    reasons: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def is_used(self) -> bool:
        return self.used > 0


@dataclass
class TemplateBuild:
    """Result of :func:`build_template`.

    template; aligned [M,S] the used swallows on the template grid (NaN outside their data);
    naive_time [S'] / naive_tau [S'] the unaligned mean of the used clips (baseline removed, time
    since each clip's start); clips: one report per input; events [(clip index, SwallowEvent)] for
    the M used swallows; landmarks [M,K] their landmark times (s, track time; NaN: not used for that
    swallow) of ``template.landmark_names``.
    """

    template: SwallowTemplate
    aligned: np.ndarray
    naive_time: np.ndarray
    naive_tau: np.ndarray
    clips: list[ClipReport]
    events: list[tuple[int, SwallowEvent]]
    landmarks: np.ndarray

    def report(self) -> str:
        lines = []
        for c in self.clips:
            if c.is_used:
                lines.append(f"  used     {c.source}: {c.used} of {c.found} swallow(s)")
                lines.extend(f"           - {r}" for r in c.reasons + c.notes)
            else:
                lines.append(f"  rejected {c.source}: {'; '.join(c.reasons)}")
        t = self.template
        used = sum(c.is_used for c in self.clips)
        marks = ", ".join(f"{n} {v:.3f}" for n, v in zip(t.landmark_names, t.landmarks))
        lines.append(f"template: {len(self.events)} swallow(s) from {used} of {len(self.clips)} clip(s); "
                     f"peak height {t.peak_height:.4f} tau (~{t.peak_height / 0.03:.2f} cm), "
                     f"duration {t.duration:.3f} s (onset to return), {len(t.time)} samples at {t.fps:g} fps")
        lines.append(f"landmarks (s from onset): {marks}")
        return "\n".join(lines)


def _inner_neighbours(times: np.ndarray, centre: int) -> np.ndarray:
    """[M,K] index of each landmark's nearest finite neighbour towards landmark ``centre`` in the same
    swallow (-1: none, or the centre itself)."""
    out = np.full(times.shape, -1)
    for m, row in enumerate(times):
        for k in range(len(row)):
            if k == centre or not np.isfinite(row[k]):
                continue
            step = 1 if k < centre else -1
            j = k + step
            while not np.isfinite(row[j]):
                j += step
            out[m, k] = j
    return out


def chained_target(times: np.ndarray, centre: int) -> np.ndarray:
    """Template times [K] of landmarks from their times [M,K] in M swallows (NaN: missing), ``centre`` at 0.

    Outwards from the centre, landmark k sits at the mean over the swallows that have it of its gap to
    the swallow's inner neighbour plus that neighbour's template time: the mean landmark times (relative
    to the centre) when every swallow has every landmark, unbiased by which swallows miss one.
    """
    target = np.full(times.shape[1], np.nan)
    target[centre] = 0.0
    inner = _inner_neighbours(times, centre)
    for k in sorted(range(times.shape[1]), key=lambda j: abs(j - centre)):
        have = np.flatnonzero(inner[:, k] >= 0)
        if k != centre and len(have):
            target[k] = np.mean(times[have, k] - times[have, inner[have, k]] + target[inner[have, k]])
    return target


def _densest_window(values: np.ndarray, half_width: float) -> np.ndarray:
    """Boolean mask [N] of the finite ``values`` inside the window of +-``half_width`` holding the most."""
    finite = np.flatnonzero(np.isfinite(values))
    best = np.zeros(len(values), dtype=bool)
    for i in finite:
        inside = np.isfinite(values) & (np.abs(values - values[i]) <= half_width)
        centre = np.median(values[inside])
        inside = np.isfinite(values) & (np.abs(values - centre) <= half_width)
        if inside.sum() > best.sum():
            best = inside
    return best


def select_landmarks(events: Sequence[SwallowEvent], config: RegistrationConfig | None = None
                     ) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, list[list[str]]]:
    """The landmarks the swallows share, and which of them each swallow's warp goes through.

    First the swallows are aligned on the landmarks every swallow has (``rise_start``, ``rise50``,
    ``peak``, ``fall50``, ``fall_end``, where measured).  Every other landmark is mapped through that
    preliminary warp into template time; it is used if at least ``landmark_majority`` of the swallows
    put it within +-``landmark_agreement`` half-height widths of each other (the densest such window),
    and a swallow whose landmark falls outside that window (a crossing on a hold in this clip and on
    the rise in the others, a valley that is another feature) leaves it out of its warp.  A swallow
    whose landmarks are out of the common order leaves out the one further from the others.

    Args:
        events: M swallows (each with ``rise50``, ``peak``, ``fall50``).
        config: ``landmark_majority``, ``landmark_agreement``.

    Returns:
        (names [K] in time order, times [M,K] (s, track time; NaN where a swallow's landmark is missing
        or left out), target [K] template times relative to the peak (:func:`chained_target`), notes [M]
        why landmarks were left out).
    """
    cfg = config or RegistrationConfig()
    m_count = len(events)
    counts: dict[str, int] = {}
    for e in events:
        for name in e.landmarks:
            counts[name] = counts.get(name, 0) + 1
    notes: list[list[str]] = [[] for _ in events]

    # Preliminary alignment on the landmarks all (most) swallows have.
    base = [n for n in ("rise_start", "rise50", "peak", "fall50", "fall_end")
            if n in ALWAYS or counts.get(n, 0) >= cfg.landmark_majority * m_count]
    base_times = np.array([[e.time(n) for n in base] for e in events])       # [M,B]
    for m in range(m_count):  # onset/return must lie outside the half-height crossings
        if not (np.diff(base_times[m][np.isfinite(base_times[m])]) > 0).all():
            for k, n in enumerate(base):
                if n in ("rise_start", "fall_end"):
                    base_times[m, k] = np.nan
            notes[m].append("rise_start/fall_end left out (inside the half-height crossings)")
    base_target = chained_target(base_times, base.index("peak"))
    width = base_target[base.index("fall50")] - base_target[base.index("rise50")]

    def to_template(m: int, t: float) -> float:
        have = np.isfinite(base_times[m])
        x, y = base_times[m, have], base_target[have]
        slope = (y[-1] - y[0]) / (x[-1] - x[0])
        if t < x[0]:
            return float(y[0] + slope * (t - x[0]))
        if t > x[-1]:
            return float(y[-1] + slope * (t - x[-1]))
        return float(np.interp(t, x, y))

    names = [n for n in counts if counts[n] >= cfg.landmark_majority * m_count or n in ALWAYS]
    times = np.array([[e.time(n) for n in names] for e in events])           # [M,K]
    for k, name in enumerate(names):
        if name in base:
            times[:, k] = base_times[:, base.index(name)]
    mapped = np.array([[to_template(m, t) if np.isfinite(t) else np.nan for t in row]
                       for m, row in enumerate(times)])                       # [M,K] template time
    used = np.ones(len(names), dtype=bool)
    for k, name in enumerate(names):
        if name in base:
            continue
        agree = _densest_window(mapped[:, k], cfg.landmark_agreement * width)
        if agree.sum() < cfg.landmark_majority * m_count:
            used[k] = False  # the swallows disagree on where it is
            continue
        middle = float(np.median(mapped[agree, k]))
        for m in np.flatnonzero(np.isfinite(mapped[:, k]) & ~agree):
            notes[m].append(f"{name} left out ({(mapped[m, k] - middle) / width:+.2f} half-height widths from "
                            f"where the other swallows have it)")
            times[m, k] = mapped[m, k] = np.nan
    names = [n for n, u in zip(names, used) if u]
    times, mapped = times[:, used], mapped[:, used]
    order = np.argsort(np.nanmedian(mapped, axis=0), kind="stable")
    names = [names[k] for k in order]
    times, mapped = times[:, order], mapped[:, order]
    middle = np.nanmedian(mapped, axis=0)
    # Out of the common order (a swallow's landmark crossing its neighbour's): leave out the one further off.
    for m in range(m_count):
        while True:
            have = np.flatnonzero(np.isfinite(times[m]))
            steps = np.diff(times[m, have])
            if (steps > 0).all():
                break
            i = int(np.argmax(steps <= 0))
            pair = [k for k in have[i:i + 2] if names[k] not in ALWAYS]
            if not pair:
                raise ValueError(f"select_landmarks: swallow {m}: rise50, peak, fall50 out of order")
            k = max(pair, key=lambda j: abs(mapped[m, j] - middle[j]))
            notes[m].append(f"{names[k]} left out (out of order)")
            times[m, k] = mapped[m, k] = np.nan
    target = chained_target(times, names.index("peak"))
    keep = np.isfinite(target)
    keep[1:] &= np.diff(target) > 1e-3  # landmarks closer than a millisecond in the mean (rare ties)
    names = [n for n, u in zip(names, keep) if u]
    return tuple(names), times[:, keep], target[keep], [list(dict.fromkeys(n)) for n in notes]


def build_template(tracks: Sequence[TauTrack], detection: DetectionConfig | None = None,
                   registration: RegistrationConfig | None = None) -> TemplateBuild:
    """Detect the swallows in ``tracks``, register them by their shared landmarks and average them.

    Args:
        tracks: tau tracks (any length and frame rate; non-uniform ones are resampled at their fps);
            each may hold any number of swallows.
        detection: :class:`DetectionConfig` (defaults if None).
        registration: :class:`RegistrationConfig` (defaults if None).

    Returns:
        :class:`TemplateBuild`: the template (time [S] s from onset at ``template_fps``, tau [S],
        std [S]), the aligned swallows [M,S], the naive unaligned mean, one report per track.

    Raises:
        InputError: fewer than ``min_swallows`` usable swallows (the message lists each track's reason).
    """
    reg = registration or RegistrationConfig()
    reports = [ClipReport(track.source or f"clip {i}") for i, track in enumerate(tracks)]
    uniform = [uniform_track(t) for t in tracks]
    analyses: list[TrackAnalysis | None] = []
    candidates: list[tuple[int, SwallowEvent]] = []
    for i, track in enumerate(uniform):
        if len(track) < 5:
            reports[i].reasons.append(f"only {len(track)} samples")
            analyses.append(None)
            continue
        analysis = analyse_track(track.tau, track.fps, detection, start_time=float(track.time[0]))
        analyses.append(analysis)
        reports[i].found = len(analysis.events) + len(analysis.broken)
        reports[i].reasons.extend(analysis.broken)
        if not analysis.events and not analysis.broken:
            reports[i].reasons.append(analysis.note)
        candidates.extend((i, e) for e in analysis.events)

    kept = candidates
    if kept:
        med_width = np.median([e.width for _, e in kept])
        med_height = np.median([e.height for _, e in kept])
        selected = []
        for i, e in kept:
            w, h = e.width / med_width, e.height / med_height
            if not 1 / reg.max_width_ratio <= w <= reg.max_width_ratio:
                reports[i].reasons.append(f"swallow at {e.peak_time:.2f} s is {e.width:.2f} s wide at half height, "
                                          f"{w:.2f}x the median {med_width:.2f} s (max_width_ratio "
                                          f"{reg.max_width_ratio:g})")
            elif not 1 / reg.max_height_ratio <= h <= reg.max_height_ratio:
                reports[i].reasons.append(f"swallow at {e.peak_time:.2f} s rises {e.height:.4f}, {h:.2f}x "
                                          f"the median {med_height:.4f} (max_height_ratio {reg.max_height_ratio:g})")
            else:
                selected.append((i, e))
        kept = selected
    if len(kept) < max(1, reg.min_swallows):
        detail = "\n".join(f"  {r.source}: {'; '.join(r.reasons) or 'ok'}" for r in reports)
        raise InputError(f"{len(kept)} usable swallow(s), need at least {max(1, reg.min_swallows)}:\n{detail}")
    for i, _ in kept:
        reports[i].used += 1

    events = [e for _, e in kept]
    names, marks, target, notes = select_landmarks(events, reg)
    for (i, e), note in zip(kept, notes):
        if note:
            reports[i].notes.append(f"swallow at {e.peak_time:.2f} s: {'; '.join(note)}")

    step = 1.0 / reg.template_fps
    first, last = target[0] - reg.pad_seconds, target[-1] + reg.pad_seconds
    values = [uniform[i].tau - analyses[i].baseline for i, _ in kept]
    times = [uniform[i].time for i, _ in kept]
    # The template's time origin: its onset (the mean onset relative to the peak), else its first landmark.
    origin = next((target[names.index(n)] for n in ("dip_start", "rise_start") if n in names), target[0])
    grid = origin + np.arange(int(np.floor((first - origin) / step)), int(np.ceil((last - origin) / step)) + 1) * step
    aligned = register_curves(times, values, marks, target, grid, reg.warp)
    mean, std, count = nan_mean_std(aligned)
    keep = count > 0
    template = SwallowTemplate(grid[keep] - origin, mean[keep], std[keep], reg.template_fps, target - origin, names)

    clip_ids = sorted({i for i, _ in kept})
    span = min(uniform[i].time[-1] - uniform[i].time[0] for i in clip_ids)
    naive_time = np.arange(int(np.floor(span * reg.template_fps)) + 1) * step
    naive = np.stack([np.interp(naive_time, uniform[i].time - uniform[i].time[0],
                                uniform[i].tau - analyses[i].baseline) for i in clip_ids])
    return TemplateBuild(template, aligned[:, keep], naive_time, naive.mean(axis=0), reports, kept, marks)


def template_error(time: np.ndarray, tau: np.ndarray, true_time: np.ndarray, true_tau: np.ndarray,
                   max_shift: float = 1.0, scale_range: tuple[float, float] = (0.8, 1.25),
                   rate: float = 250.0) -> tuple[float, float, float]:
    """Error of a template against a known swallow, as issue 13 defines it.

    The RMS of ``template((t - shift) / scale) - truth(t)`` over the truth's span, minimised over
    shifts within ``max_shift`` seconds and time scales in ``scale_range`` (coarse grid, then a finer
    one around the best), divided by the truth's peak height.

    Args:
        time, tau: [S] the template (0 outside its span).
        true_time, true_tau: [R] the true swallow over its duration (onset to return).
        max_shift: seconds; scale_range: (lowest, highest) time scale; ``(1, 1)`` for shifts only.
        rate: samples per second of the comparison.

    Returns:
        (error as a fraction of the true peak height, best shift (s), best scale).
    """
    time, tau = np.asarray(time, np.float64), np.asarray(tau, np.float64)
    grid = np.arange(true_time[0], true_time[-1] + 0.5 / rate, 1.0 / rate)
    truth = np.interp(grid, true_time, true_tau)

    def rms(shifts: np.ndarray, scales: np.ndarray) -> np.ndarray:
        out = np.empty((len(scales), len(shifts)))
        for j, scale in enumerate(scales):
            at = (grid[None, :] - shifts[:, None]) / scale
            diff = np.interp(at.ravel(), time, tau, left=0.0, right=0.0).reshape(at.shape) - truth
            out[j] = np.sqrt(np.mean(diff ** 2, axis=1))
        return out

    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    scales = np.exp(np.linspace(lo, hi, max(1, int(round((hi - lo) / 0.01)) + 1)))
    shifts = np.arange(-max_shift, max_shift + 1e-9, 0.01)
    errors = rms(shifts, scales)
    j, i = np.unravel_index(np.argmin(errors), errors.shape)
    fine_scales = np.exp(np.clip(np.log(scales[j]) + np.linspace(-0.01, 0.01, 11), lo, hi))
    fine_shifts = np.clip(shifts[i] + np.arange(-0.01, 0.0105, 0.001), -max_shift, max_shift)
    errors = rms(fine_shifts, fine_scales)
    j, i = np.unravel_index(np.argmin(errors), errors.shape)
    return float(errors[j, i] / np.max(true_tau)), float(fine_shifts[i]), float(fine_scales[j])
