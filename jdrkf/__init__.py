"""jdrkf: JAX-accelerated, differentiable robust and distributionally robust state estimators."""

import importlib.metadata

from . import _cpu_pool as _cpu_pool  # first: sets PJRT_NPROC before any JAX computation (see its docstring)
from . import linalg as linalg, metrics as metrics, sets as sets, tuning as tuning
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
    STKF as STKF,
    STKF_AR1 as STKF_AR1,
    STKF_AR2 as STKF_AR2,
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
    predict as predict,
    theta_max as theta_max,
    update as update,
)


try:
    __version__ = importlib.metadata.version("jdrkf")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
