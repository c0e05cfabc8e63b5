"""KITTI tracking evaluation: HOTA, CLEAR MOT, identity metrics and 3D MOT metrics.

* :mod:`.tracking_files`: label (``label_02/SSSS.txt``) and result files as flat arrays.
* :mod:`.seqmap`: the sequences to score and their lengths (``evaluate_tracking.seqmap.*``).
* :mod:`.kitti_rules`: the benchmark's per-class preprocessing (DontCare, distractors,
  occlusion / truncation / height filters) into matched-ready sequences.
* :mod:`.hota`, :mod:`.clear`, :mod:`.identity`: the metrics of TrackEval's KITTI evaluation.
* :mod:`.mot3d`: AB3DMOT's sAMOTA / AMOTA / AMOTP over score thresholds counted with the
  CLEAR code above, and the velocity error.
* :mod:`.ab3dmot_rules`: the same figures as AB3DMOT's own evaluation script counts them
  (the figures papers report).
* :mod:`.evaluator`: folders in, one result dict and the printed table out.
"""
