"""The lowest layer: what every other package uses and that knows nothing of heads or necks.

Errors and atomic files, tables and time axes, the command-line shell, progress lines, stage timings,
plots, thread pools, rotation conventions and signal filters.  Imports nothing from the project.
"""
