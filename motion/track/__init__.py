"""Larynx tracking in photometric normal maps (the paper's tau_bar(j) = argmax_x [k * N_j](x) - tau0).

A kernel ``k`` holding the generic larynx shape as normals is matched against each normal map ``N_j``
by normalised correlation; the match's position, minus the rest position, is the larynx's rise in
pixels, and with a calibration in tau units.  The neck's own image motion, measured on patches of
larynx-free skin, moves the search band with the head and the jaw and, on request, is taken out of
the rise.  One module per part:

- ``sources``: normal-map frames (image folders, videos, ``.npy`` stacks), decoding and validation;
- ``config``: the settings (:class:`TrackerConfig`);
- ``kernel``: the larynx kernel (from the rig, a frame or a file) and its band-pass and match window;
- ``neck``: the neck's own motion at the larynx (:class:`NeckPatches`, :class:`NeckModel`);
- ``match``: the frame-by-frame matcher and :func:`track_sequence`, the API;
- ``calibration``: what the rig tells the tracker (pixels per tau unit, the match window);
- ``scale``: the capture's pixel scale estimated from the frames, when it is not given;
- ``cli``: ``python -m motion.track`` (:func:`run`, the CSV columns, the plot).

Encoding and image files: ``data.normals``; camera, image convention and the larynx point (the
tracker's ground truth): ``scene.render``.  Positions are (x, y) = (col, row) pixels, rows down.
Figures: ``benchmarks/README.md``, section "Tracker and renderer".

Example::

    rig = HeadNeckModel.load("hack_rig.npz")
    kernel = calibrate_window(rig_kernel(rig), rig)
    track = track_sequence(frames, kernel, neck=NeckModel.from_rig(rig))
    rise_px = track.y[0] - track.y                                   # raw image rise
    slide_px = rise_px + (track.neck[:, 1] - track.neck[0, 1])      # relative to the neck
"""
from motion.track.calibration import calibrate_window, rig_px_per_tau
from motion.track.cli import CSV_COLUMNS, run, track_columns
from motion.track.config import BandpassConfig, SearchConfig, TrackerConfig
from motion.track.kernel import kernel_from_file, kernel_from_frame, rescale_kernel, rig_kernel
from motion.track.match import LarynxTracker, Track, smooth_track, track_sequence
from motion.track.neck import NeckModel, NeckPatches
from motion.track.scale import check_scale, estimate_scale, sample_frames
from motion.track.sources import check_normal_map, decode_frame, open_source

__all__ = [
    "BandpassConfig", "CSV_COLUMNS", "LarynxTracker", "NeckModel", "NeckPatches", "SearchConfig", "Track",
    "TrackerConfig", "calibrate_window", "check_normal_map", "check_scale", "decode_frame", "estimate_scale",
    "kernel_from_file", "kernel_from_frame", "open_source", "rescale_kernel", "rig_kernel", "rig_px_per_tau", "run",
    "sample_frames", "smooth_track", "track_columns", "track_sequence",
]
