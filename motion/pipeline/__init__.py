"""Inference: a facial capture (or a folder of them) through the larynx and neck models into a folder of
animation parameters, plots, meshes and exports; ``python infer.py`` (its docstring lists the outputs).

Modules, in the order a take goes through them: ``config`` (the settings), ``models`` (loading the
chosen models and rig), ``animate`` (capture -> ``data.params.AnimationParams``), ``outputs`` (the
files of a take), ``take`` (one take into its folder, whole or not at all), ``folder`` (a folder of
takes and its summary), ``cli`` (the command).
"""
