"""Tracked-video datasets: the portable upload format (:mod:`.portable`, never executes anything) and the
metrical-tracker / INSTA folder reader and converter (:mod:`.metrical`, local trusted data)."""

from .portable import (
    FORMAT,
    VERSION,
    Dataset,
    Tracking,
    read_dataset,
    validate_dataset,
    write_dataset,
)

__all__ = ["FORMAT", "VERSION", "Dataset", "Tracking", "read_dataset", "validate_dataset", "write_dataset"]
