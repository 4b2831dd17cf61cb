"""Camera sources: the ``CameraSource`` protocol and its implementations."""

from .frame import CameraSource, Frame

__all__ = ["CameraSource", "Frame"]
