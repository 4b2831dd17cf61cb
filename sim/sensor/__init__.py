"""A physically simulated Intel RealSense D455 (DESIGN §4 "The sensor as it is").

Depth comes from stereo matching, as on the sensor: the left and right IR images are rendered
(95 mm apart, the IR projector's dot pattern on or off, its light falling with the square of
range, over the renderer's textured, shaded scene; shot and read noise; one auto-exposure), and
matched by semi-global matching (OpenCV StereoSGBM) with a subpixel fit, at a resolution whose
disparity precision gives the D455's depth error.  Occlusion shadows, holes on low-texture
surfaces without the projector, error growing with z^2, thin objects lost and the minimum range
all come out of the matching; nothing is masked by hand.

- :mod:`.config`: :class:`StereoConfig` (every number, D455 defaults; ``D455``, ``D455_PROJECTOR_OFF``);
- :mod:`.projector`: the dot pattern and the light it throws (numba);
- :mod:`.ir`: the IR pair;
- :mod:`.matching`: SGBM, the subpixel fit, disparity to depth;
- :mod:`.stereo`: :class:`StereoDepthSensor`, the batched entry point, and :func:`decimate_depth`;
- :mod:`.gray`: :class:`GrayCamera`, the gray image's auto-exposure, gain, motion blur and noise.
"""

from .config import D455, D455_PROJECTOR_OFF, StereoConfig
from .gray import GrayCamera, GrayCameraConfig, GrayFrame, sample_brightness
from .ir import IrPair, render_ir_pair
from .matching import match_depth
from .stereo import StereoDepthSensor, StereoFrame, decimate_depth

__all__ = [
    "D455",
    "D455_PROJECTOR_OFF",
    "GrayCamera",
    "GrayCameraConfig",
    "GrayFrame",
    "IrPair",
    "StereoConfig",
    "StereoDepthSensor",
    "StereoFrame",
    "decimate_depth",
    "match_depth",
    "render_ir_pair",
    "sample_brightness",
]
