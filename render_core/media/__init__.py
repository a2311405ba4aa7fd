"""Pixels out: stream codecs (:mod:`.codecs`, JPEG/PNG/H.264 per frame for the service), file writers
(:mod:`.files`, PNG/JPEG/EXR images and video files) and the float -> 8-bit conversions both use (:mod:`.pixels`)."""
