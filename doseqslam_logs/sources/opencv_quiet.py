"""OpenCV with its own log lines off, for every module of the package that decodes images.

OpenCV logs a failed decode itself ("[ERROR:0@0.06] global loadsave.cpp:612 imread_ ... can't
read data: ... Unexpected end of input stream") on the process's stderr, on top of the error
it returns: that line would break the promise of one line per error. Importing this module
sets the level once, before the first decode; the decoders still say what is wrong in our
words (the libjpeg and libpng messages images.py captures are not OpenCV's log).

The decoders import OpenCV from here, in the functions that decode (`from
doseqslam_logs.sources.opencv_quiet import cv2`): reading a log's channels and messages, and
every command that only does that, does not pay OpenCV's import.
"""

from __future__ import annotations

import cv2 as cv2  # re-exported: OpenCV with its log off

cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_FATAL)
