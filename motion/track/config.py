"""The tracker's settings (``TrackerConfig``): pixels and frames, given for the default neck view.

The defaults suit ``scene.render.DEFAULT_CM_PER_PX`` = 0.08 cm/px (a larynx ~55 px wide and ~90 px
tall); :meth:`TrackerConfig.at_scale` gives the same physical sizes at another pixel scale (the CLI
applies it for ``cm_per_px=``).  The sections and what each setting does:

- ``bandpass``: the filter that frames and kernel go through (``motion.track.kernel.bandpass``).
- ``window``: the Gaussian weight of each kernel pixel in the match (``motion.track.kernel.match_window``);
  its vertical offset and sigma may be left to the rig's calibration (``calibrate_window``).
- ``search``: where the match is looked for and when it is accepted (``motion.track.match``).
- ``neck``: the patches of larynx-free skin whose motion the band follows and the compensation
  removes (``motion.track.neck``).

Measurements behind the defaults: ``benchmarks/README.md`` (section "Tracker and renderer").
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from scene.render import DEFAULT_CM_PER_PX


def _odd(width: int, factor: float) -> int:
    """A running-mean width scaled by ``factor``, kept odd (so it stays centred); 0 stays 0 (off)."""
    return 0 if width <= 1 else max(3, int(round(width * factor)) // 2 * 2 + 1)


@dataclass
class BandpassConfig:
    """Frames and kernel alike: a Gaussian low-pass, minus running means along rows and along columns."""

    lowpass_sigma_px: float = 4.0   # Gaussian low-pass sigma (0 = off): mesh facets, pixel noise
    row_highpass_px: int = 21       # width of the running mean removed along each row (0 = off): jaw line, shading
    column_highpass_px: int = 101   # height of the running mean removed along each column (0 = off): neck sides

    def __post_init__(self) -> None:
        if self.lowpass_sigma_px < 0 or self.row_highpass_px < 0 or self.column_highpass_px < 0:
            raise ValueError("tracker.bandpass: sigma and running-mean widths must not be negative")

    def at_scale(self, factor: float) -> BandpassConfig:
        return replace(self, lowpass_sigma_px=self.lowpass_sigma_px * factor,
                       row_highpass_px=_odd(self.row_highpass_px, factor),
                       column_highpass_px=_odd(self.column_highpass_px, factor))


@dataclass
class WindowConfig:
    """The match's Gaussian weight around the kernel's centre (0 = all kernel pixels alike).

    ``offset_y_px`` moves the weight's centre down from the kernel's centre and ``sigma_y_px`` sets its
    height; None for either = calibrated on the rig (``calibrate_window``, kernel=rig), else 0 and 14.
    """

    sigma_x_px: float = 20.0
    sigma_y_px: float | None = None
    offset_y_px: float | None = None

    def __post_init__(self) -> None:
        if self.sigma_x_px < 0 or (self.sigma_y_px is not None and self.sigma_y_px < 0):
            raise ValueError("tracker.window: sigmas must not be negative")

    def at_scale(self, factor: float) -> WindowConfig:
        scaled = {name: None if getattr(self, name) is None else getattr(self, name) * factor
                  for name in ("sigma_y_px", "offset_y_px")}
        return replace(self, sigma_x_px=self.sigma_x_px * factor, **scaled)


# The window without a calibration: centred on the kernel's centre, 20 x 14 px.
UNCALIBRATED_SIGMA_Y_PX = 14.0


@dataclass
class SearchConfig:
    """Where the match is searched and when it is accepted."""

    band_rows: int = 24             # search +- rows around the prediction (a swallow moves < 8 px/frame at 30 fps)
    band_cols: int = 8              # search +- columns
    max_jump_px: float = 10.0       # accepted distance from the prediction per frame since the last match (+ its speed)
    min_confidence: float = 0.2     # lowest accepted peak (weighted) NCC; the real HACK larynx under the jaw: 0.33+
    reacquire_after: int = 10       # consecutive rejections before searching the whole frame again
    subpixel: bool = True

    def __post_init__(self) -> None:
        if self.band_rows < 0 or self.band_cols < 0 or self.reacquire_after < 1:
            raise ValueError("tracker.search: band sizes must not be negative and reacquire_after must be >= 1")

    def at_scale(self, factor: float) -> SearchConfig:
        return replace(self, band_rows=max(2, round(self.band_rows * factor)),
                       band_cols=max(1, round(self.band_cols * factor)), max_jump_px=self.max_jump_px * factor)


@dataclass
class NeckConfig:
    """Patches of larynx-free skin below and beside the larynx, matched against the first frame.

    With ``follow`` the search band moves with the neck's estimated motion at the larynx (else it moves
    on by one frame of the larynx's own velocity); the estimate also gives the tracker's neck-relative
    ``tau_px`` (``compensate=true`` on the command line).
    """

    follow: bool = True
    patch_px: int = 25                  # square patch side
    search_px: int = 5                  # +- around the patch's last position moved on at its velocity
    jaw_search_px: int = 16             # ... for the patch on the chin, which moves with the jaw
    lowpass_sigma_px: float = 2.0       # the patches' own low-pass (pixel noise); no high-pass: the skin's relief
    min_confidence: float = 0.6         # a patch matched below this NCC is left out of the frame's estimate
    max_deviation_px: float = 6.0       # ... and one further than this from the patches' median displacement
    min_curvature: float = 0.0016       # ... and an axis along which the NCC peak is flatter (its second difference)
    min_patches: int = 3                # fewer patches measured vertically than this: the neck's estimate is held

    def __post_init__(self) -> None:
        if self.patch_px < 5 or self.search_px < 1 or self.lowpass_sigma_px < 0:
            raise ValueError("tracker.neck: patch_px >= 5, search_px >= 1 and a non-negative sigma expected")

    def at_scale(self, factor: float) -> NeckConfig:
        return replace(self, patch_px=max(5, round(self.patch_px * factor) // 2 * 2 + 1),
                       search_px=max(1, round(self.search_px * factor)),
                       jaw_search_px=max(1, round(self.jaw_search_px * factor)),
                       lowpass_sigma_px=self.lowpass_sigma_px * factor,
                       max_deviation_px=self.max_deviation_px * factor,
                       min_curvature=self.min_curvature / (factor * factor))


@dataclass
class TrackerConfig:
    """The tracker's settings (pixels at 0.08 cm/px, frames); see the module doc."""

    bandpass: BandpassConfig = field(default_factory=BandpassConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    neck: NeckConfig = field(default_factory=NeckConfig)
    smooth_frames: float = 0.0      # sigma (frames) of the confidence-weighted Gaussian smoothing; 0 = off

    def __post_init__(self) -> None:
        if self.smooth_frames < 0:
            raise ValueError(f"tracker.smooth_frames={self.smooth_frames}: expected >= 0")

    def at_scale(self, cm_per_px: float) -> TrackerConfig:
        """The same settings in pixels of a capture at ``cm_per_px`` (lengths scale by 0.08 / cm_per_px)."""
        factor = DEFAULT_CM_PER_PX / float(cm_per_px)
        return replace(self, bandpass=self.bandpass.at_scale(factor), window=self.window.at_scale(factor),
                       search=self.search.at_scale(factor), neck=self.neck.at_scale(factor))
