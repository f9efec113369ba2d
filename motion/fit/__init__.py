"""Fitting the rig to captures: ``python -m motion.fit`` (the command: :mod:`motion.fit.cli`).

- :mod:`motion.fit.inputs`: the capture's frames (OBJ / PLY in name order, an .npz of vertices) in cm,
  checked (vertex count, size against the rig, empty / NaN / unreadable files);
- :mod:`motion.fit.outputs`: the fit as ``params.npz``, ``plot.png``, ``report.json`` and the log's summary;
- the optimisation itself is ``models.fit`` (``fit_meshes``, ``fit_scans``).
"""
from motion.fit.cli import run
from motion.fit.inputs import read_capture

__all__ = ["read_capture", "run"]
