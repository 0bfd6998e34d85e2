"""Which light is the lasers' and which is the scene's: the detector's colour settings.

A setup's ``detection`` object (``slcv-setup/1``) names the lasers' colour and the spot threshold:

- ``laser_color``: ``red`` (the default), ``green`` or ``blue``: the lasers' light is in that
  channel of a colour camera, against a reference channel that the lasers do not reach (red
  against green; green against red; blue against green); or ``brightest``: a monochrome or infrared
  camera, where the spots are the small regions brighter than their surroundings (the grey level
  against its local median over :data:`BACKGROUND_PX` px);
- ``spot_threshold``: the contrast, in grey levels, above which a pixel is a spot's (default 25
  for a colour laser; 12 for ``brightest``, where a spot's excess over the wall is its share of the
  grey level: on the renders spots are found from 6 to 16 there, and none at 25).

The scene (the walls, the dots, the rim) is read in the reference channel (the grey image for
``brightest``): there the lasers' light is weakest.  Stripes of line and ring lasers are read in
red only.
"""

from dataclasses import dataclass

import cv2
import numpy as np

LASER_COLORS = ("red", "green", "blue", "brightest")
BGR = {"blue": 0, "green": 1, "red": 2}
REFERENCE = {"red": "green", "green": "red", "blue": "green"}  # a channel the laser does not reach
BACKGROUND_PX = 21  # the local median's window for a monochrome camera's spots (px, odd)


@dataclass(frozen=True)
class DetectionSettings:
    """The detector's light settings (see the module docstring)."""

    laser_color: str = "red"
    spot_threshold: float | None = None  # None: the colour's default

    @property
    def threshold(self) -> float:
        """The spot threshold in grey levels (the colour's default where none is given)."""
        if self.spot_threshold is not None:
            return float(self.spot_threshold)
        return 12.0 if self.laser_color == "brightest" else 25.0

    def to_json(self) -> dict:
        out = {"laser_color": self.laser_color}
        return out | ({} if self.spot_threshold is None else {"spot_threshold": float(self.spot_threshold)})

    @property
    def is_default(self) -> bool:
        return self == DetectionSettings()


DEFAULT_LIGHT = DetectionSettings()


def read_detection(ctx, doc: dict) -> DetectionSettings:
    """The setup's ``detection`` object (defaults where absent); ``FormatError`` through ``ctx``
    naming the field."""
    d = ctx.get(doc, "detection", "", dict, optional=True)
    if d is None:
        return DetectionSettings()
    color = ctx.get(d, "laser_color", "detection", str, optional=True) or "red"
    if color not in LASER_COLORS:
        ctx.fail("detection.laser_color", f"expected one of {', '.join(LASER_COLORS)}, got {color!r}")
    thr = ctx.get(d, "spot_threshold", "detection", optional=True)
    if thr is not None:
        thr = ctx.number(thr, "detection.spot_threshold")
        if not 0.0 < thr < 255.0:
            ctx.fail("detection.spot_threshold", f"expected grey levels in (0, 255), got {thr}")
        thr = float(thr)
    unknown = sorted(set(d) - {"laser_color", "spot_threshold"})
    if unknown:
        ctx.fail(f"detection.{unknown[0]}", "unknown field (known: laser_color, spot_threshold)")
    return DetectionSettings(color, thr)


def _grey(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(float) if bgr.ndim == 3 else bgr.astype(float)


def scene_channel(bgr: np.ndarray, color: str = "red") -> np.ndarray:
    """The image the scene (walls, dots, rim) is read in, as float grey levels (H, W): the
    reference channel of a colour laser, the grey image for ``brightest``."""
    if color == "brightest":
        return _grey(bgr)
    return bgr[:, :, BGR[REFERENCE[color]]].astype(float)


def laser_light(bgr: np.ndarray, color: str = "red") -> tuple[np.ndarray, np.ndarray]:
    """The lasers' light in an image (H, W each, float): its contrast in grey levels (the laser's
    channel less the reference channel; for ``brightest``, the grey level less its local median)
    and its relative excess (laser over reference, less 1), whose centroid places a spot."""
    if color == "brightest":
        grey = _grey(bgr)
        background = cv2.medianBlur(np.clip(grey, 0, 255).astype(np.uint8), BACKGROUND_PX).astype(float)
        return grey - background, grey / np.maximum(background, 4.0) - 1.0
    light = bgr[:, :, BGR[color]].astype(float)
    ref = bgr[:, :, BGR[REFERENCE[color]]].astype(float)
    return light - ref, light / np.maximum(ref, 4.0) - 1.0
