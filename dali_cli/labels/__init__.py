"""Pseudo labels: running a detector over target frames at a scale and turning its raw
detections into a box table (NMS, score cut, plausibility rule, size correction, box fit).

May import: ``dali_cli.store``, ``dali_cli.runtime``, ``dali_cli.geometry``, ``dali_cli.ptsn``,
``dali_cli.executors``; the detector and PPCG build on this layer, never the other way.
"""

# The default score cut of a box table's `score` column: a box scored at least this counts as a
# car (the pseudo labels, the PTSN sweep's E_pred, the size correction, the mean predicted sizes
# eval reports). A constant with no import, so the commands' --score-min can show it cheaply.
SCORE_MIN = 0.3
