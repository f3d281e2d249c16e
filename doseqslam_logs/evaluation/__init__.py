"""Scoring runs: ground truth (matrices or poses), precision-recall metrics, verified figures,
the comparison of two runs (`diff`) and the pictures (`plots`)."""
