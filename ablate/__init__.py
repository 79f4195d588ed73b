"""ablate: ablation studies of camera + LiDAR sensor-fusion networks."""

__version__ = "0.1.0"
