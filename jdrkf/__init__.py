"""jdrkf: JAX-accelerated, differentiable robust and distributionally robust state estimators."""

from . import linalg as linalg, metrics as metrics, sets as sets, tuning as tuning
from ._cpu_pool import use_large_cpu_pool as use_large_cpu_pool
from ._gaussian import Gaussian as Gaussian
from ._models import LinearModel as LinearModel
from ._multisensor import MultiSensorModel as MultiSensorModel
from ._nonlinear import NonlinearModel as NonlinearModel
from ._em import EMResult as EMResult, em_noise_covariances as em_noise_covariances
from ._closed_loop import ClosedLoopResult as ClosedLoopResult, LQRController as LQRController, closed_loop as closed_loop
from ._montecarlo import Clairvoyant as Clairvoyant, montecarlo as montecarlo
from ._noise import (
    AbstractNoise as AbstractNoise,
    GaussianNoise as GaussianNoise,
    MixtureNoise as MixtureNoise,
    OutlierNoise as OutlierNoise,
    ScaledNoise as ScaledNoise,
    StudentTNoise as StudentTNoise,
    UniformPerturbation as UniformPerturbation,
    UQuadraticNoise as UQuadraticNoise,
)
from ._simulate import Trajectories as Trajectories, simulate as simulate
from ._version import __version__ as __version__
from .filters import (
    AbstractFilter as AbstractFilter,
    BCOTKF as BCOTKF,
    BootstrapPF as BootstrapPF,
    CKF as CKF,
    CovarianceIntersection as CovarianceIntersection,
    CovarianceRecursion as CovarianceRecursion,
    DRKF as DRKF,
    DRParticleFilter as DRParticleFilter,
    EnsembleKF as EnsembleKF,
    FilterResult as FilterResult,
    HuberKF as HuberKF,
    KalmanFilter as KalmanFilter,
    MarginalDRKF as MarginalDRKF,
    RBKF as RBKF,
    RESULTS as RESULTS,
    RiskSensitiveKF as RiskSensitiveKF,
    RTSSmoother as RTSSmoother,
    STKF as STKF,
    STKF_AR1 as STKF_AR1,
    STKF_AR2 as STKF_AR2,
    SmootherResult as SmootherResult,
    SteadyStateDR as SteadyStateDR,
    SteadyStateDRKF as SteadyStateDRKF,
    SteadyStateGain as SteadyStateGain,
    SteadyStateKalmanFilter as SteadyStateKalmanFilter,
    StepOutput as StepOutput,
    TauKF as TauKF,
    UnscentedKF as UnscentedKF,
    ThetaMax as ThetaMax,
    VBKF as VBKF,
    WassersteinDRKF as WassersteinDRKF,
    WassersteinKF as WassersteinKF,
    irls_update as irls_update,
    rts_backward as rts_backward,
    smooth as smooth,
    predict as predict,
    theta_max as theta_max,
    update as update,
)
