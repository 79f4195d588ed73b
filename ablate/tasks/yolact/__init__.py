"""YOLACT-style instance segmentation pieces: anchors, head, loss and inference (SMoE, seed 000 §4)."""
