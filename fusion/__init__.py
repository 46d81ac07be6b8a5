"""trifuse fusion core: TOF points into the colour and thermal images, pure functions on arrays.

Like ``calib``, nothing here reads files, prints, starts threads or knows about HTTP.
Imports point one way: ``fusion`` uses ``calib``, never the reverse.
"""
