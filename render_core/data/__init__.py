"""Tracked-video datasets: the portable upload format (:mod:`.portable`, never executes anything) and the
metrical-tracker / INSTA folder reader and converter (:mod:`.metrical`, local trusted data)."""

from .metrical import convert_metrical, load_frame_file, read_metrical, split_indices
from .portable import (
    FORMAT,
    VERSION,
    Dataset,
    Tracking,
    read_dataset,
    validate_dataset,
    write_dataset,
)

__all__ = ["FORMAT", "VERSION", "Dataset", "Tracking", "convert_metrical", "load_frame_file", "read_dataset",
           "read_metrical", "split_indices", "validate_dataset", "write_dataset"]
