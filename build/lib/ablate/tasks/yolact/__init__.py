"""YOLACT-style instance segmentation pieces: anchors, head, loss and inference (SMoE, seed 000 §4)."""

#: Classes of the SMoE annotation (§3.1): label 0 car, label 1 pedestrian.
CLASSES = ("car", "pedestrian")
