"""What a real small camera does to the twin's clean renders: motion blur over the exposure,
auto-exposure with a lag, and sensor noise on the 8-bit output.

For every frame (:meth:`Exposure.image`), in the order a sensor applies them:

1. **Motion blur.** The exposure lasts ``exposure_s`` and is centred on the frame's time stamp.
   The camera's rotation during it (from the true trajectory: the angle turned over the half
   exposure before the stamp, assumed at a constant rate across the stamp) moves the image by
   the homography H(s) = K exp(-s [phi]) K^-1, s in -1..1; the blurred image is the mean of the
   render warped by H(s) at evenly spaced s, as many samples as the longest blur streak has
   pixels (up to ``blur_max_samples``), none below ``blur_min_px``. Translation's parallax is
   left out: at the head's speeds rotation gives nearly all the blur.
   The pinhole render is blurred before the lens model's remap.
2. **Exposure.** The signal in digital numbers (DN) is the render times the analog gain g. The
   auto-exposure meters the mean of the clipped output and moves g towards target / mean with
   a first-order lag (time constant ``ae_time_constant_s``, in log gain), the new gain applying
   from the next frame, as a camera's controller does; the first frame starts converged.
3. **Noise.** Shot noise (Poisson, as a Gaussian of variance signal / conversion gain) and read
   noise, both in electrons, scaled by the gain: var(DN) = g S / e_per_dn + (g read_e / e_per_dn)^2
   for a signal of S DN, e_per_dn the conversion gain at unit gain. Then clipped and rounded
   to 8 bits.

The render is taken as the sensor's linear response (MuJoCo's lighting is linear and applies
no gamma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .render import ImageFormation


@dataclass(frozen=True)
class CameraSensor:
    """A small colour camera's exposure, noise and auto-exposure (8-bit output).

    exposure_s : exposure time, s (the blur). e_per_dn : conversion gain at unit analog gain,
    electrons per DN (16: a full well of about 4000 e- over 255 DN). read_noise_e : electrons
    rms. target_mean_dn : what the auto-exposure aims the mean at. ae_time_constant_s : its
    lag. gain_range : the analog gain's limits. blur_* : when and how finely to blur."""

    exposure_s: float = 0.006
    e_per_dn: float = 16.0
    read_noise_e: float = 6.0
    target_mean_dn: float = 110.0
    ae_time_constant_s: float = 0.5
    gain_range: tuple[float, float] = (0.25, 8.0)
    blur_min_px: float = 0.5
    blur_sample_px: float = 1.5
    blur_max_samples: int = 7

    def noise_variance(self, signal_dn: np.ndarray, gain: float) -> np.ndarray:
        """DN^2: the variance of the output at a signal of ``signal_dn`` (before clipping)."""
        return gain * np.asarray(signal_dn) / self.e_per_dn + (gain * self.read_noise_e / self.e_per_dn) ** 2


CAMERA_SENSOR = CameraSensor()


def blur_homographies(K: np.ndarray, phi: np.ndarray, n: int) -> list[np.ndarray]:
    """(3, 3) homographies from the image at the stamp to the image at n instants evenly across
    the exposure: phi (3,) rad, the rotation vector of R_world_cam(t)^T R_world_cam(t - T/2)
    (the camera frame at the exposure's start in the frame at the stamp)."""
    Kinv = np.linalg.inv(K)
    return [K @ Rotation.from_rotvec(-s * np.asarray(phi)).as_matrix() @ Kinv for s in np.linspace(-1.0, 1.0, n)]


def blur_length_px(K: np.ndarray, phi: np.ndarray, width: int, height: int) -> float:
    """The longest streak, px, that the rotation ``phi`` over the exposure draws: the largest
    motion from start to end of the exposure of the image's corners and centre."""
    H0, H1 = blur_homographies(K, phi, 2)
    p = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1],
                  [(width - 1) / 2, (height - 1) / 2, 1]], float).T
    a, b = H0 @ p, H1 @ p
    return float(np.max(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0)))


def motion_blur(image: np.ndarray, K: np.ndarray, phi: np.ndarray, sensor: CameraSensor) -> tuple[np.ndarray, float]:
    """(image as float32, streak length px): ``image`` (H, W, 3) averaged along the rotation's
    image motion during the exposure, or unchanged if the streak is under ``blur_min_px``."""
    h, w = image.shape[:2]
    length = blur_length_px(K, phi, w, h)
    if length < sensor.blur_min_px:
        return image.astype(np.float32), length
    n = int(min(max(math.ceil(length / sensor.blur_sample_px) + 1, 2), sensor.blur_max_samples))
    acc = np.zeros(image.shape, np.float32)
    for H in blur_homographies(K, phi, n):
        cv2.accumulate(cv2.warpPerspective(image, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), acc)
    acc *= 1.0 / n
    return acc, length


def _standard_normal(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """float32 standard normal noise of ``shape``: OpenCV's generator (several times faster than
    numpy's for an image), seeded from ``rng`` so that a run is reproducible."""
    out = np.empty(shape, np.float32)
    cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
    cv2.randn(out.reshape(shape[0], -1), 0.0, 1.0)       # one channel: randn's mean and sigma are per channel
    return out


def _mean(image: np.ndarray) -> float:
    """The mean over pixels and channels (OpenCV's, several times faster than numpy's)."""
    m = cv2.mean(image)
    return float(np.mean(m[:image.shape[2]])) if image.ndim == 3 else float(m[0])


class Exposure:
    """One run of a camera: its auto-exposure's gain and its noise. ``gain`` is None until the
    first frame; ``log`` holds (gain, blur streak px) per frame (truth, for scoring)."""

    def __init__(self, sensor: CameraSensor, formation: ImageFormation, frame_dt: float, rng: np.random.Generator):
        self.sensor = sensor
        self.formation = formation
        self.frame_dt = float(frame_dt)
        self.rng = rng
        self.gain: float | None = None
        self.log: list[tuple[float, float]] = []
        rc = formation.render_camera
        self.K = np.array([[rc.fx, 0.0, rc.cx], [0.0, rc.fy, rc.cy], [0.0, 0.0, 1.0]])

    def image(self, rendered: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """The camera's 8-bit image from a pinhole render (H, W, 3) uint8 and the rotation phi
        (3,) rad over the exposure's first half (see :func:`blur_homographies`)."""
        s = self.sensor
        blurred, length = motion_blur(rendered, self.K, phi, s)
        signal = self.formation.form(blurred)
        if self.gain is None:
            self.gain = self._clip_gain(s.target_mean_dn / max(_mean(signal), 1e-3))
        g = self.gain
        # In place, on float32 buffers: this runs on every frame of a recording.
        signal *= g
        np.minimum(signal, 255.0, out=signal)           # the pixel's well is full at 255 DN
        sd = signal * np.float32(g / s.e_per_dn)
        sd += np.float32((g * s.read_noise_e / s.e_per_dn) ** 2)
        np.sqrt(sd, out=sd)
        noise = _standard_normal(signal.shape, self.rng)
        noise *= sd
        noise += signal
        np.rint(noise, out=noise)
        np.clip(noise, 0.0, 255.0, out=noise)
        self.log.append((g, length))
        self._meter(_mean(noise))
        return noise.astype(np.uint8)

    def _meter(self, mean_dn: float) -> None:
        """Move the gain towards the target for the next frame, with the controller's lag."""
        s = self.sensor
        wanted = self._clip_gain(self.gain * s.target_mean_dn / max(mean_dn, 1e-3))
        a = 1.0 - math.exp(-self.frame_dt / s.ae_time_constant_s)
        self.gain = self._clip_gain(math.exp((1 - a) * math.log(self.gain) + a * math.log(wanted)))

    def _clip_gain(self, g: float) -> float:
        lo, hi = self.sensor.gain_range
        return float(min(max(g, lo), hi))
