"""Numerical conventions shared by every rasteriser backend (3DGS / gsplat "classic" mode).

Both the CPU backend and the tests' brute-force reference read these constants, so a change
here changes what "correct" means everywhere at once.
"""

from __future__ import annotations

import math

#: Added to the diagonal of every projected 2D covariance (px^2): the screen-space low-pass
#: filter that keeps sub-pixel Gaussians at least about one pixel wide.
LOWPASS_EPS2D = 0.3

#: A Gaussian reaches a pixel only inside this many standard deviations (Mahalanobis radius).
SIGMA_CUTOFF = 3.0

#: Per-Gaussian alpha is clamped to this value, so one Gaussian never makes a pixel opaque.
ALPHA_MAX = 0.99

#: Contributions with alpha below this are skipped (as in the reference CUDA rasterisers).
ALPHA_MIN = 1.0 / 255.0

#: Compositing front to back stops before the Gaussian that would take transmittance below this.
TRANSMITTANCE_MIN = 1e-4

#: log(TRANSMITTANCE_MIN): compositing works with log-transmittance.
LOG_TRANSMITTANCE_MIN = math.log(TRANSMITTANCE_MIN)

#: Scales are clamped to this many metres before squaring, so covariances stay finite in float32.
SCALE_MAX = 1e4

#: A quaternion shorter than this is treated as the identity rotation.
QUAT_EPS = 1e-12
