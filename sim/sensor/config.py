"""The simulated D455's numbers: geometry, projector, IR imagers and the matcher (one home for
every default of :mod:`sim.sensor`).

Geometry.  The D455 as mounted: two IR imagers 95 mm apart on the camera's y axis (the right
imager at -y_C, frame C of :mod:`sim.camera`), the IR dot projector between them, depth reported
in the left imager's frame, which is the gray camera's (the runtime aligns depth to colour).
The D455 streams 848 x 480 at HFOV 87 deg (fx = 446.8 px): a disparity of 42.4 px / z(m).

Resolution.  Matching runs at half the D455's size, 424 x 240 (fx = 223.4 px, disparity
21.2 px / z(m)): SGBM finds the whole-pixel disparity and a 9 x 9 parabola fit the fraction
(:mod:`sim.sensor.matching`).  On rendered walls with the projector on the disparity error is
about 0.05 px RMS here, i.e. 0.1 px of the D455's 848 px width (Intel quotes 0.08 px), and the
depth error 0.2 % at 1 m, 0.5 % at 2 m, 1.1 % at 4 m (``tests/sim/sensor``): z^2, within the
D455's specification of <= 2 % at 4 m.  Matching at 848 x 480 would cost 4x, and the encoder
sees 224 x 224 either way.

Range.  The D455's minimum range (0.52 m, Intel's datasheet at full resolution) comes from its
disparity search range, and so does ours: SGBM searches disparities -7..40 px at 424 px
(``num_disparities`` = 48 from ``min_disparity`` -7), so a surface nearer than
21.2 / 40 = 0.53 m cannot be matched at its true disparity.  Beyond ``max_range_m`` depth is
reported invalid, as the RealSense threshold filter does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from runtime.contract.constants import CAMERA_HFOV_RAD

from ..camera import CameraModel

D455_BASELINE_M = 0.095
D455_MIN_RANGE_M = 0.52


@dataclass(frozen=True)
class StereoConfig:
    """A D455-like active stereo depth camera.  Units in the names; levels are 8-bit IR image
    levels (0..255)."""

    # Geometry and resolution (see the module doc).
    baseline_m: float = D455_BASELINE_M
    width_px: int = 424
    height_px: int = 240
    hfov_rad: float = CAMERA_HFOV_RAD
    min_range_m: float = D455_MIN_RANGE_M  # sets the top of the disparity search
    max_range_m: float = 20.0  # farther depth is reported invalid (threshold filter)
    # Projector: on or off (the D455's emitter switch); offset from the left imager toward the
    # right one along -y_C; a pseudo-random dot per cell of a square grid in its image plane.
    projector_on: bool = True
    projector_offset_m: float = D455_BASELINE_M / 2.0
    projector_hfov_rad: float = math.radians(90.0)
    dot_pitch_px: float = 4.0  # grid cell, in left-imager pixels at the matching resolution
    dot_sigma_px: float = 0.45  # Gaussian dot radius, same pixels (before pixel integration)
    dot_fill: float = 0.8  # share of grid cells that hold a dot
    projector_electrons_at_1m: float = 240000.0  # a dot's peak on a reflectance-1 surface 1 m away; falls as 1/range^2
    # IR imagers: the room's own IR light (the passive image), in photo-electrons per exposure
    # of a reflectance-1 surface; shot noise (Poisson, as Gaussian) and read noise; auto-exposure
    # scales each image to a mean of ae_target_level (at most max_gain_levels_per_electron), then 8 bits.
    ambient_electrons: float = 4000.0
    read_noise_electrons: float = 5.0
    ae_target_level: float = 90.0
    max_gain_levels_per_electron: float = 1.0
    psf_sigma_px: float = 0.8  # lens blur and pixel integration (Gaussian, imager pixels)
    # Semi-global matching (OpenCV StereoSGBM) and its checks.
    block_size_px: int = 5
    p1_per_pixel: int = 8  # P1 = p1_per_pixel x block_size^2 (small disparity changes)
    p2_per_pixel: int = 32  # P2 = p2_per_pixel x block_size^2 (jumps)
    uniqueness_ratio_pct: int = 10  # best cost must beat the second best by this margin
    left_right_max_diff_px: int = 1  # left-right consistency check: occlusions fail it
    speckle_window_px: int = 60  # connected regions smaller than this are removed ...
    speckle_range_px: int = 2  # ... when their disparity varies by at most this
    pre_filter_cap: int = 31
    subpixel_window_px: int = 9  # the subpixel fit's window (sim.sensor.matching.refine_subpixel)
    # Texture check (the D455's ASIC has one): a match whose window has an RMS intensity gradient
    # along the baseline below this (levels per px) is left invalid.
    min_texture_levels_px: float = 2.0
    num_disparities: int = 48  # a multiple of 16; the search is min_disparity .. min_disparity + 47

    @property
    def camera(self) -> CameraModel:
        """The left imager at the matching resolution (the gray camera's pinhole, more pixels)."""
        return CameraModel(width_px=self.width_px, height_px=self.height_px, hfov_rad=self.hfov_rad)

    @property
    def focal_baseline_px_m(self) -> float:
        """fx x baseline (px m): disparity (px) = this / z (m)."""
        return self.camera.fx_px * self.baseline_m

    @property
    def max_disparity_px(self) -> int:
        """The largest disparity searched: the nearest surface matched lies at min_range_m or beyond."""
        return int(math.floor(self.focal_baseline_px_m / self.min_range_m))

    @property
    def min_disparity_px(self) -> int:
        """SGBM's minDisparity: the search ends at max_disparity_px."""
        return self.max_disparity_px - self.num_disparities + 1

    @property
    def projector_camera(self) -> CameraModel:
        """The projector as a pinhole (its shadow map is rendered with it); pixels as fine as the imager's."""
        fx = self.camera.fx_px
        width = 2 * int(math.ceil(fx * math.tan(self.projector_hfov_rad / 2.0)))
        height = 2 * int(math.ceil(width / 2.0 * self.height_px / self.width_px))
        # Same focal length in pixels as the imager (square pixels): pick the HFOV that gives it.
        return CameraModel(width_px=width, height_px=height, hfov_rad=2.0 * math.atan(width / 2.0 / fx))

    def validate(self) -> None:
        """Raise ValueError naming the field and its allowed range."""
        positive = ("baseline_m", "min_range_m", "dot_pitch_px", "dot_sigma_px", "projector_electrons_at_1m",
                    "ambient_electrons", "ae_target_level", "max_gain_levels_per_electron", "hfov_rad", "projector_hfov_rad")  # fmt: skip
        for key in positive:
            if not getattr(self, key) > 0.0:
                raise ValueError(f"StereoConfig.{key}={getattr(self, key)} must be > 0")
        if not self.max_range_m > self.min_range_m:
            raise ValueError(f"StereoConfig.max_range_m={self.max_range_m} must exceed min_range_m={self.min_range_m}")
        if self.width_px < 32 or self.height_px < 32:
            raise ValueError(f"StereoConfig resolution {self.width_px}x{self.height_px} must be at least 32x32 px")
        if self.num_disparities < 16 or self.num_disparities % 16:
            raise ValueError(f"StereoConfig.num_disparities={self.num_disparities} must be a positive multiple of 16 (SGBM)")
        for key in ("block_size_px", "subpixel_window_px"):
            if getattr(self, key) < 1 or getattr(self, key) % 2 == 0:
                raise ValueError(f"StereoConfig.{key}={getattr(self, key)} must be odd and >= 1")
        if not 0.0 < self.dot_fill <= 1.0:
            raise ValueError(f"StereoConfig.dot_fill={self.dot_fill} must lie in (0, 1]")
        if self.read_noise_electrons < 0.0 or self.psf_sigma_px < 0.0:
            raise ValueError("StereoConfig.read_noise_electrons and psf_sigma_px must be >= 0")
        if not 0.0 <= self.projector_offset_m <= self.baseline_m:
            raise ValueError(f"StereoConfig.projector_offset_m={self.projector_offset_m} must lie between the imagers "
                             f"(0..{self.baseline_m} m)")  # fmt: skip
        if self.max_disparity_px < 2:
            raise ValueError(f"StereoConfig: min_range_m={self.min_range_m} gives a disparity search that ends below 2 px")


D455 = StereoConfig()
D455_PROJECTOR_OFF = StereoConfig(projector_on=False)
