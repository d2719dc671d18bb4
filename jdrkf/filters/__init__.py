"""Filters: each an `eqx.Module` with `init`/`step`, scanned by `__call__`."""

from ._base import (
    AbstractFilter as AbstractFilter,
    FilterResult as FilterResult,
    RESULTS as RESULTS,
    StepOutput as StepOutput,
)
from ._kalman import (
    KalmanFilter as KalmanFilter,
    SteadyStateGain as SteadyStateGain,
    SteadyStateKalmanFilter as SteadyStateKalmanFilter,
    predict as predict,
    update as update,
)
from ._dr import DRKF as DRKF, HuberKF as HuberKF, WassersteinKF as WassersteinKF
from ._divergence import RiskSensitiveKF as RiskSensitiveKF, TauKF as TauKF
from ._reweighted import (
    IRLSResult as IRLSResult,
    RBKF as RBKF,
    STKF as STKF,
    STKF_AR1 as STKF_AR1,
    STKF_AR2 as STKF_AR2,
    VBKF as VBKF,
    irls_update as irls_update,
)
from ._bcot import BCOTKF as BCOTKF
from ._wasserstein_dr import (
    CovarianceRecursion as CovarianceRecursion,
    SteadyStateDRKF as SteadyStateDRKF,
    WassersteinDRKF as WassersteinDRKF,
)
from ._unscented import EnsembleKF as EnsembleKF, UnscentedKF as UnscentedKF, sigma_points as sigma_points
from ._extended import ExtendedKF as ExtendedKF
from ._particle import BootstrapPF as BootstrapPF, ParticleState as ParticleState, particle_moments as particle_moments
from . import _resampling as resampling  # noqa: F401 (public namespace: resampling.systematic, .stratified, .residual, .multinomial, .ess)
from ._dr_particle import (
    DRParticleFilter as DRParticleFilter,
    DropOutliers as DropOutliers,
    NearestOutliers as NearestOutliers,
)
from ._smoother import RTSSmoother as RTSSmoother, SmootherResult as SmootherResult, rts_backward as rts_backward, smooth as smooth
from ._parallel import ParallelKalmanFilter as ParallelKalmanFilter, parallel_smooth as parallel_smooth
from ._fusion import CKF as CKF, CovarianceIntersection as CovarianceIntersection, MarginalDRKF as MarginalDRKF

# Worst-case problems that moved to `jdrkf.sets`; the old names here are deprecated
# aliases for one release.
_MOVED_TO_SETS = ("BCOTWorstCase", "bcot_worst_case", "CIWeights", "ci_weights", "covariance_intersection",
                  "SteadyStateDR", "ThetaMax", "theta_max")


def __getattr__(name: str):
    if name in _MOVED_TO_SETS:
        import warnings

        from .. import sets

        warnings.warn(f"jdrkf.filters.{name} is deprecated; use jdrkf.sets.{name}", DeprecationWarning, stacklevel=2)
        return getattr(sets, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
