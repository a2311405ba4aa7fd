"""Pixels out: stream codecs (:mod:`.codecs`, JPEG/PNG/H.264 per frame for the service) and file writers
(:mod:`.files`, PNG/EXR images and video files for offline rendering)."""
