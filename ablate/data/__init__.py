"""Sensor data: KITTI readers, LiDAR representations, conditions and the generated dataset."""


class DataError(ValueError):
    """Bad input data. The message names the file and says what is wrong."""


#: The generated default dataset (also conf/data/synth.yaml): frames, seed and image size.
DEFAULT_SYNTH = {"frames": 600, "seed": 0, "height": 128, "width": 416}
