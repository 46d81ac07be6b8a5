"""trifuse calibration core: camera and rig models, pure functions on arrays.

Nothing in this package reads files, prints, starts threads or knows about HTTP; see
docs/CONVENTIONS.md for frames, units and array shapes.
"""
