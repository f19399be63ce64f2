"""Every tunable number of the SLAM, in two places: the filter's (:class:`SlamConfig`) and the
map management's and start-up's (:class:`MapSettings`). The values were chosen on training
seeds of the twin's scenes; benchmarks/README.md records how and on which, and the figures on
held-out seeds.

Both are frozen dataclasses of frozen groups, one a part of the SLAM reads (``settings.imu``,
``cfg.impulses``). Compatibility: each old flat name maps to one (group, field) in
:data:`MAP_FLAT` / :data:`SLAM_FLAT`; it is accepted as a keyword by the constructor and by
``dataclasses.replace`` (``replace(MapSettings(), use_imu=False)``, or :func:`with_overrides`),
so TOML files and overrides keep working; :meth:`_Grouped.flat` gives every value by its flat
name (records, comparisons). A flat name is not an attribute: ``settings.use_imu`` is refused
with its new place, ``settings.imu.use_imu``. A keyword in neither is refused with the list of
groups."""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields, replace

FEATURE_TYPES = ("inverse-depth", "particles")
WARP_MODES = ("known", "neighbours", "all")


def _check_numbers(obj, skip=(), owner: str | None = None) -> None:
    for f in fields(obj):
        v = getattr(obj, f.name)
        if f.name in skip or isinstance(v, (bool, str)):
            continue
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"{owner or type(obj).__name__}.{f.name} = {v!r} must be a finite number >= 0")


def _flat_map(groups: dict[str, type], renames: dict[str, str] = {}) -> dict[str, tuple[str, str]]:
    """Old flat name -> (group, field): a group's fields keep their flat names but for ``renames``
    (field -> old flat name)."""
    out = {}
    for g, cls in groups.items():
        for f in fields(cls):
            out[renames.get(f"{g}.{f.name}", f.name)] = (g, f.name)
    return out


class _Grouped:
    """Construction from groups and old flat names (see the module's docstring)."""

    _GROUPS: dict[str, type] = {}
    _FLAT: dict[str, tuple[str, str]] = {}

    def __init__(self, **kw):
        cls = type(self)
        own = {f.name: f for f in fields(cls)}
        values, flat = {}, {}
        for k, v in kw.items():
            if k in own:
                values[k] = v
            elif k in cls._FLAT:
                flat.setdefault(cls._FLAT[k][0], {})[cls._FLAT[k][1]] = v
            else:
                raise TypeError(f"{cls.__name__} has no setting {k!r}: give a group ({', '.join(cls._GROUPS)}) or one "
                                f"of its fields' flat names (runtime/slam/config.py)")
        for name, f in own.items():
            if name in values:
                v = values[name]
            else:
                v = f.default_factory() if f.default_factory is not MISSING else f.default
            if name in flat:
                v = replace(v, **flat[name])
            object.__setattr__(self, name, v)
        self.__post_init__()

    def flat(self) -> dict:
        """Every setting by its old flat name (for records and comparisons)."""
        out = {k: getattr(getattr(self, g), f) for k, (g, f) in type(self)._FLAT.items()}
        out.update({f.name: getattr(self, f.name) for f in fields(self) if f.name not in type(self)._GROUPS})
        return out

    def __getattr__(self, name):
        # Python calls this only for a name the object lacks, so group reads cost nothing.
        where = type(self)._FLAT.get(name)
        if where is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        raise AttributeError(f"{type(self).__name__}.{name} moved: read settings.{where[0]}.{where[1]}")


def with_overrides(settings, **flat):
    """``settings`` with some values changed, given by group (``imu=ImuSettings(...)``) or by old
    flat name (``use_imu=False``): ``dataclasses.replace`` with the flat names mapped."""
    return replace(settings, **flat)


@dataclass(frozen=True)
class MotionNoise:
    """The constant-velocity model's impulses (SlamConfig's docstring: sigma_a, sigma_alpha,
    motion_noise_interval)."""

    sigma_a: float = 4.0
    sigma_alpha: float = 6.0
    motion_noise_interval: float = 0.033

    def __post_init__(self):
        _check_numbers(self, owner="SlamConfig")


@dataclass(frozen=True)
class ImpulseAdaptation:
    """Each track's impulses adapted to its own motion (SlamConfig's docstring: adapt_*)."""

    adapt_sigma_a: bool = True
    adapt_after: float = 2.0
    adapt_turn_rate: float = 1.0
    sigma_a_min: float = 1.0
    adapt_margin: float = 4.0
    adapt_window: float = 1.0
    adapt_lag: float = 0.15
    adapt_sigma_alpha: bool = True
    adapt_onset: bool = True
    adapt_alpha_lag: float = 0.1
    adapt_alpha_margin: float = 2.0
    sigma_alpha_max: float = 30.0

    def __post_init__(self):
        _check_numbers(self, owner="SlamConfig")


@dataclass(frozen=True)
class ImuNoise:
    """The inertial prediction's noises, biases and clock offset (SlamConfig's docstring: imu_*,
    *_bias_*, time_offset*)."""

    imu_accel_noise: float = 0.004
    imu_gyro_noise: float = 0.0005
    imu_hold_rate_sigma: float = 0.5
    imu_hold_accel_sigma: float = 2.0
    gyro_bias_walk: float = 2e-4
    accel_bias_walk: float = 2e-3
    gyro_bias_sigma0: float = 0.01
    accel_bias_sigma0: float = 0.1
    time_offset0: float = 0.0
    time_offset_sigma0: float = 0.005
    time_offset_walk: float = 1e-4

    def __post_init__(self):
        _check_numbers(self, skip=("time_offset0",), owner="SlamConfig")
        if not math.isfinite(self.time_offset0):
            raise ValueError(f"SlamConfig.time_offset0 = {self.time_offset0!r} must be a finite number of seconds")


@dataclass(frozen=True)
class CovarianceGuard:
    """The covariance guard (SlamConfig's docstring: psd_rel_tol, psd_check_every)."""

    psd_rel_tol: float = 1e-9
    psd_check_every: int = 10

    def __post_init__(self):
        _check_numbers(self, owner="SlamConfig")


@dataclass(frozen=True, init=False)
class SlamConfig(_Grouped):
    """The filter's parameters, in groups: ``motion`` (:class:`MotionNoise`), ``impulses``
    (:class:`ImpulseAdaptation`), ``imu`` (:class:`ImuNoise`), ``guard``
    (:class:`CovarianceGuard`), and ``sigma_pixel``. Each is described below by its flat name.

    sigma_a, sigma_alpha : constant-velocity impulses' standard deviations, m/s^2 and rad/s^2
        (MonoSLAM's hand-held values are 4 and 6), over a step of ``motion_noise_interval``.
    motion_noise_interval : the step, s, those are stated for (MonoSLAM's 30 Hz frame, as the
        twin records it). A step of ``dt`` takes impulses of variance ``sigma^2 dt
        motion_noise_interval``, as white accelerations would: a frame dropped or skipped
        lengthens a step without making it harder (``(sigma dt)^2`` would take a 3-frame gap as
        9 frames' worth of variance and grow the search ellipses past searching).
    adapt_sigma_a : whether each track scales its linear impulse to the accelerations its own
        velocity estimates show (motion.impulse_sigma, covariance matching) while the camera
        turns faster than ``adapt_turn_rate`` rad/s: ``adapt_margin`` times the estimate over
        the last ``adapt_window`` s, from velocity changes ``adapt_lag`` s apart, within
        ``[sigma_a_min, sigma_a]``, from ``adapt_after`` s after the start (the start's velocity
        is a guess its first second corrects). ``sigma_a`` is a prior for any hand-held motion;
        a camera held over a desk accelerates at about 0.2 m/s^2 rms, a walker's head at about
        1, and with 4 the filter takes a fast turn's unpredicted part partly as an orbit about
        the new features' depth prior. Not turning, the prior is kept: a pose the views hold
        weakly (a far, frontal target) stays correctable (benchmarks/NOTES.md).
    adapt_sigma_alpha : whether each track raises its angular impulse while its own rate
        estimates show a manoeuvre (motion.adapted_sigma_alpha, an adjustable-level process noise
        as in Bar-Shalom, Li and Kirubarajan's manoeuvring-target tracking): the angular
        acceleration over the last ``adapt_alpha_lag`` s, times ``adapt_alpha_margin``, within
        ``[sigma_alpha, sigma_alpha_max]``, while the camera turns faster than
        ``adapt_turn_rate`` and from ``adapt_after`` s after the start. A head
        turning at 400 degrees/s starts and stops at 20-30 rad/s^2; predicted with 6, the turn's
        rotation is missed, the matches fall to a handful and their innovations are taken partly
        as translation (benchmarks/NOTES.md).
    adapt_onset : whether a frame whose update starts a turn (the posterior's impulses, as
        above, are no longer the priors) is measured again from the prediction with the turn's
        impulses: the prior impulses it was first measured with take the turn's unforeseen
        start partly as translation, and the turn's smaller linear impulse then holds that
        velocity error (benchmarks/NOTES.md).
    sigma_pixel : a feature measurement's standard deviation per axis, px.
    imu_accel_noise, imu_gyro_noise : white-noise densities of the IMU's specific force
        (m/s^2/sqrt(Hz)) and rate (rad/s/sqrt(Hz)) as the inertial prediction models them.
    imu_hold_rate_sigma, imu_hold_accel_sigma : how far the rate (rad/s) and the specific force
        (m/s^2) may have moved from the last sample while it is held past the samples' cover (a
        frame that arrives before the samples describing its end: inertial.predict_imu).
    gyro_bias_walk, accel_bias_walk : the bias states' random walks, rad/s/sqrt(s) and
        m/s^2/sqrt(s).
    gyro_bias_sigma0, accel_bias_sigma0 : the biases' prior standard deviations before any
        still period (a MEMS part's offsets after factory trim), rad/s and m/s^2.
    time_offset0, time_offset_sigma0, time_offset_walk : the IMU's clock offset against the
        camera's (stamps taken by a host on arrival): its prior mean and standard deviation, s
        (learnt from zero up to about 20 ms; give a rig's measured latency beyond), and its
        random walk, s/sqrt(s).
    psd_rel_tol : the covariance guard's tolerance for negative eigenvalues (relative).
    psd_check_every : frames between full positive-semi-definiteness checks (a Cholesky of P);
        finiteness, symmetry and non-negative variances are checked at every step.
    """

    motion: MotionNoise = field(default_factory=MotionNoise)
    impulses: ImpulseAdaptation = field(default_factory=ImpulseAdaptation)
    sigma_pixel: float = 1.0
    imu: ImuNoise = field(default_factory=ImuNoise)
    guard: CovarianceGuard = field(default_factory=CovarianceGuard)

    _GROUPS = {"motion": MotionNoise, "impulses": ImpulseAdaptation, "imu": ImuNoise, "guard": CovarianceGuard}
    _FLAT = _flat_map(_GROUPS)

    def __post_init__(self):
        if not (isinstance(self.sigma_pixel, (int, float)) and math.isfinite(self.sigma_pixel) and self.sigma_pixel >= 0):
            raise ValueError(f"SlamConfig.sigma_pixel = {self.sigma_pixel!r} must be a finite number >= 0")


SLAM_FLAT = SlamConfig._FLAT
DEFAULT_CONFIG = SlamConfig()


@dataclass(frozen=True)
class RansacSettings:
    """1-point RANSAC's settings (Civera, Grasa, Davison, Montiel 2010; ransac.one_point_ransac).

    threshold_px : a low-innovation inlier lies within this of a hypothesis' prediction, px.
    max_hypotheses : hypotheses tried at most. confidence : the chance of drawing an all-inlier
    hypothesis at which the trials stop. rescue_chi2 : a high-innovation match is rescued if its
    ``nu^T S^-1 nu`` after the first update is below this (chi-square, 2 dof). known_vote : a
    target corner placed by its sides: its vote for a hypothesis (a natural feature's: <= 1)."""

    threshold_px: float = 2.0            # flat: ransac_threshold_px
    max_hypotheses: int = 60             # flat: ransac_max_hypotheses
    confidence: float = 0.99             # flat: ransac_confidence
    rescue_chi2: float = 4.61            # rescued if nu^T S^-1 nu below this (chi2, 2 dof, 90%)
    known_vote: float = 5.0

    def __post_init__(self):
        _check_numbers(self)
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"RansacSettings.confidence = {self.confidence}: give a probability between 0 and 1")
        if not self.known_vote > 0:
            raise ValueError(f"MapSettings.known_vote = {self.known_vote}: a target corner's vote must be positive")


def _checked(cls):
    """A MapSettings group whose numbers are all finite and >= 0."""
    cls.__post_init__ = lambda self: _check_numbers(self, owner="MapSettings")
    return cls


@dataclass(frozen=True)
@_checked
class MeasureSettings:
    """Features measured and started each frame (measure.py, mapping.py)."""

    measure_max: int = 60                # features measured per frame, at most
    visible_min: int = 48                # add features when fewer were matched (inliers)
    new_per_frame: int = 4               # new features started in one frame, at most
    min_distance_px: float = 24.0        # between a new feature and any other, at 640 px width
    template_px: int = 15                # the appearance template's side (odd), at 640 px width
    noise_every: int = 15                # frames between estimates of the image noise (new features' contrast)
    guide_first: int = 12                # features searched first to guide the rest (guided.py); 0: off
    guide_area_px: float = 2_000.0       # guide when their 3-sigma ellipses average more, px^2 at 640 px width
    guide_floor_px: float = 1.0          # added in quadrature to a guided ellipse's axes (linearisation), px
    rescue_area_px: float = 200_000.0    # fewer than guide_first ellipses under the search cap: the smallest up
                                         # to this (px^2 at 640 px width) are searched to guide the rest


@dataclass(frozen=True)
@_checked
class InverseDepthSettings:
    """New features' inverse depth (Civera et al.)."""

    rho0: float = 1.0                    # initial inverse depth, 1/m, until the map has depths
    sigma_rho: float = 0.5               # so rho0 +- 2 sigma spans 0.5 m to infinity
    scene_depth_prior: bool = True       # rho0: the median of the frame's matches (inverse_depth.scene_prior)
    scene_depth_spread: bool = True      # sigma_rho at least the spread of their inverse depths (a deep scene)
    scene_relative_width: float = 0.5    # sigma_rho / rho0 about that median (a target, map or depth holds the scale)
    two_view_relative_width: float = 2.0  # the same after a two-view start (scale held loosely): 95% down to a fifth
    linearity_threshold: float = 0.02    # convert to a point below this linearity index (Civera et al.: 0.1),
    linearity_threshold_narrow: float = 0.1  # or this one below NARROW_WIDTH_PX, where speed decides (NOTES)


@dataclass(frozen=True)
@_checked
class DriftSettings:
    """A natural feature's persistent residual (MapFeature.drift) and a match's noise shape."""

    drift_memory: float = 0.1            # the newest residual's weight in its exponential mean
    drift_gain: float = 4.0              # variance x (1 + gain |drift|^2 / sigma_pixel^2); 0: off
    aperture_noise: bool = True          # a match's noise shaped by its template's gradients (templates.match_noise_shape)


@dataclass(frozen=True)
@_checked
class ParticleSettings:
    """The paper's factored sampling of a new feature's depth (features/particles.py)."""

    particles: int = 100
    depth_near_m: float = 0.5
    depth_far_m: float = 5.0
    gauss_ratio: float = 0.15
    prune: float = 0.001
    max_init_frames: int = 30
    min_init_frames: int = 5
    promote_std_gain: float = 2.0
    outlier: float = 0.1
    max_initialising: int = 6


@dataclass(frozen=True)
@_checked
class DeletionSettings:
    """Features deleted, and the map's size."""

    delete_min_attempts: int = 10
    delete_ratio: float = 0.5
    delete_young_attempts: int = 4       # a feature matched at most a quarter of its first 4+ searches goes
    max_features: int = 150              # the map's size cap (the EKF's cost grows as its square)
    consistency_window: int = 8          # a feature's last inlier innovations tested together:
    consistency_confidence: float = 0.999  # deleted when their NIS sum exceeds this chi-square quantile


@dataclass(frozen=True)
@_checked
class ViewSettings:
    """Visibility from a feature's first view, and matching (views.py)."""

    max_view_angle_deg: float = 60.0
    max_range_ratio: float = 2.0
    max_view_angle_known_deg: float = 60.0
    max_range_ratio_known: float = 2.5
    view_noise_angle_deg: float = 30.0   # a natural feature's measurement variance doubles this far
    view_noise_scale: float = 1.5        # (angle, range ratio) from its first view
    margin_px: float = 12.0
    match_score: float = 0.25            # zero-mean normalised SSD 2 (1 - ZNCC): ZNCC >= 0.875
    # The search cap (px^2 at 640 px width, in proportion to the image's area above it). A feature
    # is chosen while its 3-sigma ellipse's area is within it, and searched while the box around
    # the ellipse is (what the search costs); one chosen whose box is over is not searched and
    # counts as a failed search (FrameStats.outgrown), which prunes a feature whose region outgrows
    # the search (choosing by the box instead measured worse: benchmarks/NOTES.md).
    max_search_area_px: int = 40_000


@dataclass(frozen=True)
@_checked
class RelocalisationSettings:
    """Lost track and re-localisation (relocalisation.py), and the retry with larger impulses."""

    lost_after: int = 10                 # frames with fewer than 3 inliers before "lost"
    lost_noise_gain: float = 2.0
    reloc_candidates: int = 40
    reloc_every: int = 3
    reloc_min_inliers: int = 5
    reloc_min_confirmed: int = 6
    reloc_confirm_fraction: float = 0.25  # and this fraction of the features searched at the found pose
    reloc_sigma_m: float = 0.02
    reloc_sigma_rad: float = 0.02
    retry_found_fraction: float = 0.5    # fewer of the searched found: searched again with larger impulses
    retry_min_searched: int = 10
    retry_noise_gain: float = 4.0        # those impulses' scale (1: no retry; camera-only predictions)


@dataclass(frozen=True)
@_checked
class ReacquireSettings:
    """The target re-acquired near its prediction, and the loop closed by a whole-image search
    (reacquire.py)."""

    reacquire_after: int = 3             # frames the whole target is predicted in view and missed before it is sought (0: never)
    reacquire_search: float = 0.5        # sought this far from its prediction, a fraction of its diagonal
    reacquire_chi2: float = 26.1         # found farther than this from the prediction (chi2, 8 dof, 99.9%): the pose had drifted
    loop_after: int = 15                 # frames without the target matched before the whole image is searched for it (0: never)
    loop_every: int = 5                  # and then every this many frames
    loop_min_area_px: float = 150.0      # its smallest quadrilateral, px^2
    loop_max_turn_rad: float = 0.8       # its pose's rotation this near the filter's (and not the half-turn)
    loop_trials: int = 2                 # candidate poses checked against the map (the most rectangle-like first)
    loop_min_old: int = 4                # natural features from before the target was lost matched at its pose,
    loop_window_px: float = 8.0          # and half of those in view, each this near its projection (the median a third)


@dataclass(frozen=True)
@_checked
class StartupSettings:
    """Start-up from the known target (startup.py)."""

    target_sigma_m: float = 0.0001       # the printed target's geometry (0.1 mm): it holds the world's scale
    known_sigma_px: float = 0.25         # a target corner's measurement, px (its sides: 0.04-0.26 px off)
    known_edges: bool = True             # a printed rectangle's corners placed each frame by its fitted sides
    click_search_px: float = 6.0         # a clicked corner is sought this far from the click
    start_pixel_sigma: float = 0.5       # a refined corner's standard deviation, px
    start_max_rms_px: float = 1.5        # the refined corners must fit one pose this well
    ambiguity_ratio: float = 4.0         # keep the second planar PnP pose if its error is within this
    ambiguity_frames: int = 60           # frames to decide between the two, at most
    ambiguity_gate_chi2: float = 9.21    # evidence (the target's points): a miss or outlier costs this (chi2 2 dof 99%)
    init_sigma_v: float = 0.3
    init_sigma_w: float = 0.5


@dataclass(frozen=True)
@_checked
class NormalSettings:
    """Template warping's planes and fitted normals (plane-induced homographies; MapSettings.warp
    chooses which features are warped)."""

    plane_radius_m: float = 0.25
    plane_tol_m: float = 0.01
    normals_every: int = 10
    normals_per_frame: int = 4           # matched features whose normal is fitted to their looks, a frame, at most
    normal_step_deg: float = 10.0        # each time its view has turned this much further from the first
    normal_margin: float = 0.02          # and kept when it scores this much better than the current one


@dataclass(frozen=True)
@_checked
class ImuSettings:
    """The IMU's use and its samples' checks (inertial.py)."""

    use_imu: bool = True
    imu_biases: bool = True              # bias states in the filter (the camera block of 19)
    imu_time_offset: bool = True         # and the IMU's clock offset (20), with the biases only
    still_gyro_rad_s: float = 0.02       # an IMU stretch is still below this RMS rate spread
    still_min_s: float = 0.3
    imu_max_gap_s: float = 0.05          # a longer gap between samples falls back to vision only
    imu_max_rate_rad_s: float = 35.0     # samples beyond a MEMS part's range are spikes
    imu_max_accel_m_s2: float = 160.0
    # A natural start's map is handed to the IMU (imu_handover.py) once the IMU's estimate of its
    # scale over at least handover_min_s is this well observed; k's prior is then at least
    # handover_scale_sigma (relative), since a camera-only filter's short-term motion is not its
    # map's scale to the percent.
    imu_handover: bool = True
    handover_min_s: float = 1.0
    handover_max_sigma: float = 0.03
    handover_scale_sigma: float = 0.05
    handover_gravity_sigma: float = 0.05   # rad: gravity's direction in the map, at the hand-over (3 deg)


@dataclass(frozen=True, init=False)
class MapSettings(_Grouped):
    """Map management, matching, start-up and re-localisation (paper, sections 4.1 to 4.3), in
    groups a part each; ``features`` (how new features start: FEATURE_TYPES) and ``warp`` (which
    templates are warped: WARP_MODES) are the two modes. Old flat names: see the module's
    docstring and :data:`MAP_FLAT`."""

    features: str = "inverse-depth"
    measure: MeasureSettings = field(default_factory=MeasureSettings)
    inverse_depth: InverseDepthSettings = field(default_factory=InverseDepthSettings)
    drift: DriftSettings = field(default_factory=DriftSettings)
    depth_init: ParticleSettings = field(default_factory=ParticleSettings)
    ransac: RansacSettings = field(default_factory=RansacSettings)
    deletion: DeletionSettings = field(default_factory=DeletionSettings)
    views: ViewSettings = field(default_factory=ViewSettings)
    relocalisation: RelocalisationSettings = field(default_factory=RelocalisationSettings)
    reacquire: ReacquireSettings = field(default_factory=ReacquireSettings)
    startup: StartupSettings = field(default_factory=StartupSettings)
    warp: str = "all"
    normals: NormalSettings = field(default_factory=NormalSettings)
    imu: ImuSettings = field(default_factory=ImuSettings)

    _GROUPS = {"measure": MeasureSettings, "inverse_depth": InverseDepthSettings, "drift": DriftSettings,
               "depth_init": ParticleSettings, "ransac": RansacSettings, "deletion": DeletionSettings,
               "views": ViewSettings, "relocalisation": RelocalisationSettings, "reacquire": ReacquireSettings,
               "startup": StartupSettings, "normals": NormalSettings, "imu": ImuSettings}
    _FLAT = _flat_map(_GROUPS, {"ransac.threshold_px": "ransac_threshold_px",
                                "ransac.max_hypotheses": "ransac_max_hypotheses",
                                "ransac.confidence": "ransac_confidence"})

    def with_measure(self, n: int) -> "MapSettings":
        """These settings measuring at most ``n`` features a frame, adding new ones below the
        same fraction of ``n`` as the defaults do (48 of 60)."""
        fraction = MeasureSettings.visible_min / MeasureSettings.measure_max
        return replace(self, measure_max=int(n), visible_min=max(3, min(int(n), int(round(n * fraction)))))

    def __post_init__(self):
        if self.features not in FEATURE_TYPES:
            raise ValueError(f"MapSettings.features = {self.features!r}: give one of {', '.join(FEATURE_TYPES)}")
        if self.warp not in WARP_MODES:
            raise ValueError(f"MapSettings.warp = {self.warp!r}: give one of {', '.join(WARP_MODES)}")
        m = self.measure
        if m.measure_max < 3:
            raise ValueError(f"MapSettings.measure_max = {m.measure_max}: measure at least 3 features a frame")
        if m.visible_min > m.measure_max:
            raise ValueError(f"MapSettings.visible_min = {m.visible_min} exceeds measure_max = {m.measure_max}: "
                             "new features would start every frame; give at most measure_max (see with_measure)")
        if m.template_px % 2 == 0 or m.template_px < 5:
            raise ValueError(f"MapSettings.template_px = {m.template_px}: give an odd size of at least 5")


MAP_FLAT = MapSettings._FLAT
