"""Vision: dynamic two-light photometric stereo of planed wood, pure numpy functions.

No file, camera or bus I/O happens in this package: arrays in, arrays out.
"""
