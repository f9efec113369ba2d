"""Formats, rig data and the generators that need no model: expressions, tau tracks, meshes, normal maps,
the HACK release and the built-in rig, params files, joint limits and the synthetic data sets.  Imports only
``base``."""
