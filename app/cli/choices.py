"""The choices and defaults the commands' parsers offer that other modules own, copied here so
that building the parser (``trifuse --help``, ``trifuse COMMAND --help``, a refused
argument) imports none of those modules, nor numpy, OpenCV or SciPy behind them.

Each copy names its source; ``tests/app/cli/test_cli_startup.py`` checks that they agree.
"""

from __future__ import annotations

DISPLAY_MODES = ("color", "blend", "edges", "thermal", "threshold", "isotherm", "pip")
"""``fusion.compose.DISPLAY_MODES`` but its ``CONSOLE_ONLY_MODES``: ``fuse --mode``,
``record --video-mode``."""
SIM_SCENARIOS = ("inspection", "survey")
"""``app.recording.simrecord.SIM_SCENARIOS``: ``record --scenario``."""
SCENARIOS = ("inspection", "calibration", "survey")
"""``app.recording.open_source.SCENARIOS``: ``serve --scenario``."""
POSE_MODES = ("auto", "recording", "estimate")
"""``app.recording.map3d.POSE_MODES``: ``map --pose``."""
MODALITIES = ("color", "thermal", "tof")
"""``calib.rig.MODALITIES``: ``rig import --modalities``."""
RIG_FORMATS = ("ros", "kalibr", "opencv", "urdf")
"""``calib.rig_formats.RIG_FORMATS``: ``rig export --format``."""
IMPORT_FORMATS = ("ros", "kalibr", "opencv")
"""``calib.rig_formats.IMPORT_FORMATS``: ``rig import --format``."""
DEFAULT_CHUNK_S = 30.0
"""``app.recording.pieces.DEFAULT_CHUNK_S``: ``fuse --chunk-s``, ``map --chunk-s``, seconds."""
