"""The models: the HACK rig in torch (``rig``), expressions -> larynx (``larynx``), head -> neck
(``head2neck``), checkpoints and the shipped models.  Imports ``data`` and ``base``."""
