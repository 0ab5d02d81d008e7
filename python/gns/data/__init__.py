"""Dataset readers, validation, statistics and conversion.

    open_dataset(path, split)   -> Dataset of Trajectory (positions (T, N, D) float32, ...)
    training_windows / pack_batches -> shuffled windows and particle-budget batches
    compute_statistics          -> per-frame velocity / acceleration statistics
    validate_dataset            -> every problem found in a dataset
    convert                     -> the dataset in another layout, written atomically
    write_dataset               -> a dataset folder from one's own arrays, written atomically
    frame_stride, at_frame_stride
                                -> a model's frame spacing on finer data: every k-th frame

Nothing here imports gns._core: the readers are plain Python + numpy + h5py.
"""

from gns.data.convert import convert
from gns.data.crc32c import crc32c, masked_crc32c
from gns.data.dataset import Dataset, available_splits, open_dataset
from gns.data.errors import DatasetError
from gns.data.metadata import Metadata
from gns.data.stats import Statistics, StatisticsAccumulator, compute_statistics
from gns.data.stride import at_frame_stride, describe_frame_stride, frame_stride
from gns.data.trajectory import Trajectory
from gns.data.validate import Problem, validate_dataset
from gns.data.windows import (
    INPUT_SEQUENCE_LENGTH,
    Batch,
    Window,
    collate,
    pack_batches,
    shuffle_buffer,
    training_windows,
    trajectory_windows,
)
from gns.data.write import write_dataset

__all__ = [
    "INPUT_SEQUENCE_LENGTH",
    "Batch",
    "Dataset",
    "DatasetError",
    "Metadata",
    "Problem",
    "Statistics",
    "StatisticsAccumulator",
    "Trajectory",
    "Window",
    "at_frame_stride",
    "available_splits",
    "collate",
    "compute_statistics",
    "convert",
    "crc32c",
    "describe_frame_stride",
    "frame_stride",
    "masked_crc32c",
    "open_dataset",
    "pack_batches",
    "shuffle_buffer",
    "trajectory_windows",
    "training_windows",
    "validate_dataset",
    "write_dataset",
]
