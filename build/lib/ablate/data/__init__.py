"""Sensor data: KITTI readers, LiDAR representations, conditions and the generated dataset."""


class DataError(ValueError):
    """Bad input data. The message names the file and says what is wrong."""


#: The generated default dataset (also conf/data/synth.yaml): frames, seed, image size and the generator's
#: version (a new version renders other frames, so it is part of the data's folder name and of every job's config).
GENERATOR_VERSION = 2
DEFAULT_SYNTH = {"frames": 1500, "seed": 0, "height": 128, "width": 416, "version": GENERATOR_VERSION}
