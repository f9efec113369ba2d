"""A posed rig made visible: rasterising, characters built from the rig, glTF export, preview videos and
rendered normal-map sequences.  Sits above ``models`` (it poses the rig) and beside ``tasks``."""
