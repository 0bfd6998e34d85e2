"""An independent NumPy/SciPy/OpenCV implementation of the catadioptric geometry.

Written from the geometry alone, sharing no code with the package: OpenCV for
the camera, NumPy's polynomial roots for the ray-cone intersection, and SciPy's
least squares over the pixel for the projection through the mirror.
"""

import cv2
import numpy as np
from scipy.optimize import least_squares


class RefRig:
    def __init__(self, K, dist, apex, axis, radius, height):
        self.K = np.asarray(K, float)
        self.dist = np.asarray(dist, float)
        self.apex = np.asarray(apex, float)
        a = np.asarray(axis, float)
        self.axis = a / np.linalg.norm(a)
        self.r, self.h = float(radius), float(height)

    @staticmethod
    def from_package(cam, mirror):
        return RefRig(
            np.asarray(cam.K),
            np.asarray(cam.dist),
            np.asarray(mirror.apex),
            np.asarray(mirror.axis),
            float(mirror.radius),
            float(mirror.height),
        )

    def ray(self, uv):
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 300, 1e-16)
        xy = cv2.undistortPoints(np.asarray(uv, float).reshape(1, 1, 2), self.K, self.dist, None, None, None, crit)
        d = np.array([xy[0, 0, 0], xy[0, 0, 1], 1.0])
        return d / np.linalg.norm(d)

    def back_project(self, uv):
        """Mirror point and reflected unit direction of a pixel, or None."""
        d = self.ray(uv)
        a, k2 = self.axis, (self.r / self.h) ** 2
        w = -self.apex
        # |w + t d|^2 - (1 + k^2) ((w + t d).a)^2 as a polynomial in t
        c2 = d @ d - (1 + k2) * (d @ a) ** 2
        c1 = 2 * (w @ d) - 2 * (1 + k2) * (w @ a) * (d @ a)
        c0 = w @ w - (1 + k2) * (w @ a) ** 2
        roots = [t.real for t in np.roots([c2, c1, c0]) if abs(t.imag) < 1e-12 and t.real > 0]
        hits = sorted(t for t in roots if 0 <= (w + t * d) @ a <= self.h)
        if not hits:
            return None
        m = hits[0] * d
        q = m - self.apex
        n = q - (1 + k2) * (q @ a) * a
        n /= np.linalg.norm(n)
        return m, d - 2 * (d @ n) * n

    def project_direct(self, p):
        uv, _ = cv2.projectPoints(np.asarray(p, float).reshape(1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(2)

    def project_through_mirror(self, p, uv0):
        """Pixel whose reflected ray passes through p, by least squares from a starting pixel."""
        p = np.asarray(p, float)

        def resid(uv):
            bp = self.back_project(uv)
            if bp is None:
                return np.array([1e3, 1e3, 1e3])
            m, d = bp
            v = p - m
            return v - (v @ d) * d

        sol = least_squares(resid, np.asarray(uv0, float), xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
        return sol.x, float(np.linalg.norm(resid(sol.x)))
