"""The run: decode a log's images into frames, replay the detector over them, verify its
candidates by re-reading the frames they need, and write the annotated log.

`annotate.annotate_log` is the whole job; `decode`, `replay` and `reread` are its stages.
"""
