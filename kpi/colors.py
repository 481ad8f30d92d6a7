"""Colour convention shared by rendered draw-down images and the KPI measurements.

Contract: the renderer paints every front-view image with the four flat BGR colours below
(OpenCV channel order, 8-bit), and the default thresholds in :mod:`kpi.angles` and
:mod:`kpi.segregation` separate exactly these colours, with margin for shading and noise.
Real lab photos use the same code with thresholds tuned in the config dataclasses.

=====================  ===============  =====================================================
name                   BGR              CIE L*, a*, b* (D65, sRGB) and why
=====================  ===============  =====================================================
``BACKGROUND_BGR``     (0, 255, 0)      87.7, -86.2, +83.2. Chroma-key green: the colour
                                        farthest in Lab from both pellet blue (b* < 0) and
                                        sinter grey (neutral). Pure white was rejected
                                        because the lab first painted pellets white (paper,
                                        footnote 1), so white must stay available to pellets.
``WALL_BGR``           (60, 140, 200)   62.8, +15.2, +50.3. Tan: neither blue, nor neutral
                                        grey, nor green, so walls are never counted as
                                        pellets or sinter. Crop boxes should still lie inside
                                        the walls (angles treat every non-background pixel as
                                        material).
``PELLET_BGR``         (200, 110, 30)   46.3, +10.1, -53.4. Painted-pellet blue (the lab's
                                        final paint, chosen because it separates well in Lab).
``SINTER_BGR``         (70, 70, 70)     29.6, 0.0, 0.0. Dark grey, neutral.
``SHADOW_BGR``         (25, 25, 25)     8.7, 0.0, 0.0. Near black, neutral: what a photo shows
                                        through the gaps of the front layer, where the lamps do not
                                        reach (``torchdem.render``'s ``shadow_depth``). Dark and
                                        neutral, so the default thresholds class it as sinter, as
                                        a threshold on dark grey classes a lab photo's shadows.
=====================  ===============  =====================================================

:func:`bgr_to_lab` converts 8-bit BGR images to CIE L*a*b* in the field's own units
(L* in [0, 100], a* and b* roughly in [-128, 127]) instead of OpenCV's 8-bit rescaled Lab, so
thresholds read like the colour-science literature.
"""
from __future__ import annotations

import cv2
import numpy as np

BACKGROUND_BGR: tuple[int, int, int] = (0, 255, 0)
WALL_BGR: tuple[int, int, int] = (60, 140, 200)
PELLET_BGR: tuple[int, int, int] = (200, 110, 30)
SINTER_BGR: tuple[int, int, int] = (70, 70, 70)
SHADOW_BGR: tuple[int, int, int] = (25, 25, 25)


def bgr_to_lab(image_bgr: np.ndarray) -> np.ndarray:
    """Convert an 8-bit BGR image ``[H, W, 3]`` to float32 CIE L*a*b* ``[H, W, 3]``.

    L* is in [0, 100]; a* and b* are signed (0 for neutral greys).
    """
    return cv2.cvtColor(np.asarray(image_bgr, dtype=np.float32) / 255.0, cv2.COLOR_BGR2Lab)


def bgr_colour_to_lab(colour_bgr: tuple[int, int, int]) -> np.ndarray:
    """CIE L*a*b* ``[3]`` of a single 8-bit BGR colour."""
    return bgr_to_lab(np.asarray(colour_bgr, dtype=np.uint8).reshape(1, 1, 3))[0, 0]


def delta_e(lab_image: np.ndarray, reference_lab: np.ndarray) -> np.ndarray:
    """CIE76 colour difference ``[H, W]`` between every pixel and one reference colour."""
    return np.linalg.norm(lab_image - np.asarray(reference_lab, dtype=np.float32), axis=-1)
