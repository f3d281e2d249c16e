"""OpenCV with its own log lines off, for every module of the package that decodes images.

OpenCV logs a failed decode itself ("[ERROR:0@0.06] global loadsave.cpp:612 imread_ ... can't
read data: ... Unexpected end of input stream") on the process's stderr, on top of the error
it returns: that line would break the promise of one line per error. Importing this module
sets the level once, before the first decode; the decoders still say what is wrong in our
words (the libjpeg and libpng messages images.py captures are not OpenCV's log).
"""

from __future__ import annotations

import cv2

cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_FATAL)
