"""Face models: one interface (FaceModel) for FLAME and the open ARKit-52 head, and their file format."""

from .io import read_facemodel, write_facemodel
from .model import FaceModel

__all__ = ["FaceModel", "read_facemodel", "write_facemodel"]
