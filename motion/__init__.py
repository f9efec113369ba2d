"""The applications: inference on captures (``pipeline``), head -> neck on orientations, retargeting,
larynx tracking in normal maps, swallow templates.  The top layer: imports every package below."""
