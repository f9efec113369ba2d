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
- :mod:`motion.swallow.baseline`: the five-landmark registration templates are measured against;
- :mod:`motion.swallow.cli`: ``python -m motion.swallow`` (``configs/swallow.yaml``).

Conventions: tau units and sign ``data.tau_track``; a template is the displacement from rest
(0 at rest), time 0 at its onset, uniform at ``RegistrationConfig.template_fps``.
"""
from motion.swallow.detect import analyse_track, detect_swallows, uniform_track
from motion.swallow.events import LANDMARK_NAMES, DetectionConfig, SwallowEvent, TrackAnalysis
from motion.swallow.files import read_template, read_tracks, write_template
from motion.swallow.play import PlaybackConfig, insert_swallows
from motion.swallow.register import (
                                   ClipReport,
                                   RegistrationConfig,
                                   SwallowTemplate,
                                   TemplateBuild,
                                   build_template,
                                   chained_target,
                                   landmark_warps,
                                   nan_mean_std,
                                   register_curves,
                                   select_landmarks,
                                   template_error,
)

__all__ = [
    "LANDMARK_NAMES", "ClipReport", "DetectionConfig", "PlaybackConfig", "RegistrationConfig", "SwallowEvent",
    "SwallowTemplate", "TemplateBuild", "TrackAnalysis", "analyse_track", "build_template", "chained_target",
    "detect_swallows", "insert_swallows", "landmark_warps", "nan_mean_std", "read_template", "read_tracks",
    "register_curves", "select_landmarks", "template_error", "uniform_track", "write_template",
]
