"""doseqslam-logs: the DOSeqSLAM loop-closure detector replayed over robot logs."""

__version__ = "0.1.0"
