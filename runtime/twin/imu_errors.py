"""A real MEMS IMU's errors for the twin: a datasheet's error budget (:class:`ImuSpec`) and one
run's draw of it (:class:`ImuErrors`).

Model, per axis, for a sample k taken at rate f_s::

    w_k = M_g w_true(t_k - dt) + b_g,k + n_g,k        b_g,k+1 = b_g,k + sigma_rw_g sqrt(1/f_s) xi
    a_k = M_a f_true(t_k - dt) + b_a,k + n_a,k        b_a,k+1 = b_a,k + sigma_rw_a sqrt(1/f_s) xi

- the constant part of the bias b_0, drawn once per run (the part a factory trim leaves, after
  soldering);
- a bias random walk (rate random walk for the gyro, acceleration random walk for the
  accelerometer) of density sigma_rw;
- white noise n of the datasheet's noise density N: standard deviation N sqrt(f_s) per sample
  (the output band-limited at the Nyquist rate, the convention of Kalibr and most VIO tools);
- M = (I + S)(I + C): scale-factor errors S (diagonal) and cross-axis sensitivity C (off the
  diagonal), drawn once per run;
- dt: the IMU's clock against the camera's. A sample stamped t_k was taken at t_k - dt.

The truth of a run (the drawn biases, their walk, M and dt) is for scoring estimators
(``imu_truth.toml`` and ``imu_bias.txt`` in a recording); nothing on the runtime path reads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

_DEG = math.pi / 180.0
_G = 9.80665
_UG = 1e-6 * _G


@dataclass(frozen=True)
class ImuSpec:
    """A MEMS IMU's error budget, SI units. Offsets, scale and cross-axis terms are standard
    deviations per axis of the run-to-run draw."""

    name: str
    source: str
    gyro_noise_density: float       # rad/s/sqrt(Hz)
    accel_noise_density: float      # m/s^2/sqrt(Hz)
    gyro_offset: float              # rad/s, 1 sigma of the constant bias
    accel_offset: float             # m/s^2, 1 sigma of the constant bias
    gyro_random_walk: float         # rad/s^2/sqrt(Hz), the bias's random walk
    accel_random_walk: float        # m/s^3/sqrt(Hz)
    gyro_scale: float = 0.0         # 1 sigma, fraction
    accel_scale: float = 0.0
    gyro_cross_axis: float = 0.0    # 1 sigma of each off-diagonal term, fraction
    accel_cross_axis: float = 0.0
    time_offset_s: float = 0.0      # the IMU's clock offset is drawn uniformly in +-this, s

    def without_scale_and_misalignment(self) -> "ImuSpec":
        return replace(self, gyro_scale=0.0, accel_scale=0.0, gyro_cross_axis=0.0, accel_cross_axis=0.0)


#: Bosch Sensortec BMI088 (data sheet BST-BMI088-DS001, revision 1.x, typical values at 25 C):
#:
#: - gyroscope: output noise density 0.014 deg/s/sqrt(Hz); zero-rate offset +-1 deg/s; bias
#:   stability 2 deg/h; sensitivity tolerance +-1 %; cross-axis sensitivity +-1 %.
#: - accelerometer: output noise density 175 ug/sqrt(Hz); zero-g offset +-20 mg; cross-axis
#:   sensitivity +-0.5 %; sensitivity tolerance +-0.5 % (our reading; check your revision).
#:
#: How the numbers become a draw: the data sheet's typical offsets (which Bosch gives for
#: soldered parts, after its factory trim) are taken as 3-sigma bounds of the population, so a
#: run's constant bias is N(0, (1 deg/s / 3)^2) per gyro axis = 5.8 mrad/s and N(0, (20 mg / 3)^2)
#: per accelerometer axis = 6.5 cm/s^2; the tolerances likewise give sigma = tolerance / 3. The
#: gyro's bias random walk is the density whose walk reaches the bias stability in 100 s
#: (2 deg/h / sqrt(100 s) = 9.7e-7 rad/s^2/sqrt(Hz)); the data sheet gives no accelerometer bias
#: stability, so 40 ug (a consumer MEMS accelerometer's usual Allan floor) in 100 s: 3.9e-5
#: m/s^3/sqrt(Hz). Over a 12 s recording both walks are small beside the constant bias. The
#: clock offset between the IMU and the camera is not the part's but the system's: uniform in
#: +-5 ms (timestamps taken by a host on arrival, no hardware sync).
BMI088 = ImuSpec(
    name="Bosch BMI088",
    source="Bosch Sensortec BMI088 data sheet BST-BMI088-DS001 (typical values); draws as documented in "
           "runtime/twin/imu_errors.py",
    gyro_noise_density=0.014 * _DEG,
    accel_noise_density=175.0 * _UG,
    gyro_offset=1.0 * _DEG / 3.0,
    accel_offset=20e-3 * _G / 3.0,
    gyro_random_walk=2.0 * _DEG / 3600.0 / math.sqrt(100.0),
    accel_random_walk=40.0 * _UG / math.sqrt(100.0),
    gyro_scale=0.01 / 3.0,
    accel_scale=0.005 / 3.0,
    gyro_cross_axis=0.01 / 3.0,
    accel_cross_axis=0.005 / 3.0,
    time_offset_s=0.005,
)


def _misalignment(rng: np.random.Generator, scale_sigma: float, cross_sigma: float) -> np.ndarray:
    """(3, 3) M = (I + S)(I + C): S diagonal scale errors, C off-diagonal cross-axis terms."""
    S = np.diag(rng.normal(0.0, scale_sigma, 3)) if scale_sigma > 0 else np.zeros((3, 3))
    C = rng.normal(0.0, cross_sigma, (3, 3)) if cross_sigma > 0 else np.zeros((3, 3))
    np.fill_diagonal(C, 0.0)
    return (np.eye(3) + S) @ (np.eye(3) + C)


@dataclass
class ImuErrors:
    """One run's errors of an :class:`ImuSpec` sampled at ``rate_hz``, and the state of their
    random walks. ``bias_log`` holds (stamp, gyro bias (3,), accel bias (3,)) of every sample
    measured, for the truth files."""

    spec: ImuSpec
    rate_hz: float
    gyro_bias0: np.ndarray
    accel_bias0: np.ndarray
    M_gyro: np.ndarray
    M_accel: np.ndarray
    time_offset_s: float
    rng: np.random.Generator = field(repr=False)
    gyro_bias: np.ndarray = field(init=False)
    accel_bias: np.ndarray = field(init=False)
    bias_log: list = field(init=False, default_factory=list, repr=False)

    def __post_init__(self):
        self.gyro_bias = np.array(self.gyro_bias0, float)
        self.accel_bias = np.array(self.accel_bias0, float)

    @classmethod
    def draw(cls, spec: ImuSpec, rate_hz: float, rng: np.random.Generator) -> "ImuErrors":
        """A run's constant biases, scale and cross-axis terms and clock offset, from ``rng``."""
        b_g = rng.normal(0.0, spec.gyro_offset, 3)
        b_a = rng.normal(0.0, spec.accel_offset, 3)
        M_g = _misalignment(rng, spec.gyro_scale, spec.gyro_cross_axis)
        M_a = _misalignment(rng, spec.accel_scale, spec.accel_cross_axis)
        dt = float(rng.uniform(-spec.time_offset_s, spec.time_offset_s)) if spec.time_offset_s > 0 else 0.0
        return cls(spec, float(rate_hz), b_g, b_a, M_g, M_a, dt, rng)

    @property
    def gyro_sigma(self) -> float:
        """rad/s: the white noise's standard deviation per sample."""
        return self.spec.gyro_noise_density * math.sqrt(self.rate_hz)

    @property
    def accel_sigma(self) -> float:
        return self.spec.accel_noise_density * math.sqrt(self.rate_hz)

    def measure(self, stamps: np.ndarray, gyro_true: np.ndarray, accel_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the IMU reports for consecutive samples at its rate: stamps (n,) s, true angular
        rate (n, 3) rad/s and specific force (n, 3) m/s^2 (sensor frame, at the instants the
        samples were taken) -> (gyro (n, 3), accel (n, 3)). Advances the bias random walks."""
        w = np.atleast_2d(np.asarray(gyro_true, float))
        f = np.atleast_2d(np.asarray(accel_true, float))
        n = len(w)
        step = math.sqrt(1.0 / self.rate_hz)
        out_w, out_a = np.empty((n, 3)), np.empty((n, 3))
        for i in range(n):
            out_w[i] = self.M_gyro @ w[i] + self.gyro_bias + self.rng.normal(0.0, self.gyro_sigma, 3)
            out_a[i] = self.M_accel @ f[i] + self.accel_bias + self.rng.normal(0.0, self.accel_sigma, 3)
            self.bias_log.append((float(stamps[i]), self.gyro_bias.copy(), self.accel_bias.copy()))
            self.gyro_bias = self.gyro_bias + self.spec.gyro_random_walk * step * self.rng.standard_normal(3)
            self.accel_bias = self.accel_bias + self.spec.accel_random_walk * step * self.rng.standard_normal(3)
        return out_w, out_a

    def truth(self) -> dict:
        """The run's errors as a TOML-ready table (SI units), for imu_truth.toml."""
        s = self.spec
        last = self.bias_log[-1] if self.bias_log else (None, self.gyro_bias, self.accel_bias)
        return {
            "model": {"name": s.name, "source": s.source, "rate_hz": self.rate_hz,
                      "frame": "camera optical frame (as imu.txt)",
                      "equation": "w = M_gyro w_true(t - time_offset_s) + gyro_bias(t) + white; "
                                  "a = M_accel f_true(t - time_offset_s) + accel_bias(t) + white"},
            "noise": {"gyro_density_rad_s_sqrt_hz": s.gyro_noise_density,
                      "accel_density_m_s2_sqrt_hz": s.accel_noise_density,
                      "gyro_sigma_per_sample_rad_s": self.gyro_sigma, "accel_sigma_per_sample_m_s2": self.accel_sigma,
                      "gyro_random_walk_rad_s2_sqrt_hz": s.gyro_random_walk,
                      "accel_random_walk_m_s3_sqrt_hz": s.accel_random_walk},
            "bias": {"gyro_initial_rad_s": [float(x) for x in self.gyro_bias0],
                     "accel_initial_m_s2": [float(x) for x in self.accel_bias0],
                     "gyro_final_rad_s": [float(x) for x in last[1]],
                     "accel_final_m_s2": [float(x) for x in last[2]],
                     "series": "imu_bias.txt (every sample's biases)"},
            "scale_and_misalignment": {"M_gyro": [[float(x) for x in r] for r in self.M_gyro],
                                       "M_accel": [[float(x) for x in r] for r in self.M_accel]},
            "clock": {"time_offset_s": self.time_offset_s,
                      "meaning": "a sample stamped t in imu.txt was taken at camera-clock time t - time_offset_s"},
        }
