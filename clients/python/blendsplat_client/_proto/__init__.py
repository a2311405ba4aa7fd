"""The wire contract's stubs, generated from proto/blendsplat/v1/render.proto (generate_proto.py; checked in)."""
