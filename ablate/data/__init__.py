"""Sensor data: KITTI readers, LiDAR representations, conditions and the generated dataset."""


class DataError(ValueError):
    """Bad input data. The message names the file and says what is wrong."""
