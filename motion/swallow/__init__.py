"""Swallow templates from tau clips, and their playback on any HACK character.

The paper's swallowing control curve is the average of several captured swallows aligned in time
by their peaks and valleys; the curve then drives the larynx slide ``tau`` of any character
(``HeadNeckModel(...)(theta, tau=...)``).  One responsibility per module:

- :mod:`motion.swallow.events`: detection's thresholds and results (``DetectionConfig``,
  ``SwallowEvent``, ``TrackAnalysis``, ``LANDMARK_NAMES``);
- :mod:`motion.swallow.detect`: swallows in a tau track, found by their main elevation
  (``analyse_track``, ``detect_swallows``, ``uniform_track``);
- :mod:`motion.swallow.landmarks`: the landmarks one swallow has either side of its peak;
- :mod:`motion.swallow.register`: landmark registration of the swallows of several clips and
  their average, the template (``RegistrationConfig``, ``build_template``, ``SwallowTemplate``,
  ``template_error``);
- :mod:`motion.swallow.play`: inserting a template into tau tracks (``PlaybackConfig``,
  ``insert_swallows``);
- :mod:`motion.swallow.files`: template files, the tracks they are built from, plots
  (``read_template``, ``write_template``, ``read_tracks``);
- :mod:`motion.swallow.cli`: ``python -m motion.swallow`` (``configs/swallow.yaml``).

Conventions: tau units and sign ``data.tau_track``; a template is the displacement from rest
(0 at rest), time 0 at its onset, uniform at ``RegistrationConfig.template_fps``.  The five-landmark
registration templates are measured against is ``benchmarks/swallow_baseline.py``.
"""
from motion.swallow.detect import analyse_track, detect_swallows
from motion.swallow.events import DetectionConfig, SwallowEvent
from motion.swallow.files import read_template, read_tracks, write_template
from motion.swallow.play import PlaybackConfig, insert_swallows
from motion.swallow.register import (
    RegistrationConfig,
    SwallowTemplate,
    build_template,
    landmark_warps,
    select_landmarks,
    template_error,
)

__all__ = [
    "DetectionConfig", "PlaybackConfig", "RegistrationConfig", "SwallowEvent", "SwallowTemplate", "analyse_track",
    "build_template", "detect_swallows", "insert_swallows", "landmark_warps", "read_template", "read_tracks",
    "select_landmarks", "template_error", "write_template",
]
