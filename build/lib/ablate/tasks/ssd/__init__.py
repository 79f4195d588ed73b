"""SSD-style 2D detection pieces: head, the DGFN two-branch network, loss, decoding, figures and the task
(DGFN, seed 002 §III-IV, on SSD: Liu et al., ECCV 2016, DGFN ref. [3])."""

#: Classes of DGFN §IV-A ("car, pedestrian, and cyclist"): the data's ``boxes2d`` labels 0, 1, 2.
CLASSES = ("Car", "Pedestrian", "Cyclist")
