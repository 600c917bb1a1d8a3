"""Stages: classes that allocate their device buffers once and run per frame."""
