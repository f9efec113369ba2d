"""Fitting the HACK rig to captures: registered meshes (``fit_meshes``) and raw scans (``fit_scans``).

The optimisation (Levenberg-Marquardt over the whole sequence, temporal term, E_rot, coarse to fine, shape
offset) is described in ``models.fit.solver`` and ``models.fit.settings``; the application that reads
captures and writes ``params.npz`` is ``motion.fit``.  Units: cm; placement ``x_capture = root_rotation @
x_rig + root_translation``; theta in the rig's bone frames with theta[:, 0] (c7t1) held at zero, its rotation
folded into the placement.
"""
from models.fit.meshes import fit_meshes
from models.fit.scans import fit_scans
from models.fit.settings import FitResult, FitSettings

__all__ = ["FitResult", "FitSettings", "fit_meshes", "fit_scans"]
