"""jdrkf: JAX-accelerated, differentiable robust and distributionally robust state estimators.

The public names are imported on first use (PEP 562), so `import jdrkf` and `jdrkf --help` load
no JAX; `from jdrkf import KalmanFilter` and `jdrkf.KalmanFilter` work as usual.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ._cpu_pool import use_large_cpu_pool as use_large_cpu_pool
from ._version import __version__ as __version__

_SUBMODULES = ("experiments", "filters", "linalg", "metrics", "plotting", "sets", "tuning")

# public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    "Gaussian": "._gaussian",
    "LinearModel": "._models",
    "MultiSensorModel": "._multisensor",
    "NonlinearModel": "._nonlinear",
    "EMResult": "._em",
    "em_noise_covariances": "._em",
    "ClosedLoopResult": "._closed_loop",
    "LQRController": "._closed_loop",
    "closed_loop": "._closed_loop",
    "Clairvoyant": "._montecarlo",
    "montecarlo": "._montecarlo",
    "AbstractNoise": "._noise",
    "GaussianNoise": "._noise",
    "MixtureNoise": "._noise",
    "OutlierNoise": "._noise",
    "ScaledNoise": "._noise",
    "StudentTNoise": "._noise",
    "UniformPerturbation": "._noise",
    "UQuadraticNoise": "._noise",
    "Trajectories": "._simulate",
    "simulate": "._simulate",
    "AbstractFilter": ".filters",
    "BCOTKF": ".filters",
    "BootstrapPF": ".filters",
    "CKF": ".filters",
    "CovarianceIntersection": ".filters",
    "CovarianceRecursion": ".filters",
    "DRKF": ".filters",
    "DRParticleFilter": ".filters",
    "DropOutliers": ".filters",
    "EnsembleKF": ".filters",
    "ExtendedKF": ".filters",
    "FilterResult": ".filters",
    "HuberKF": ".filters",
    "KalmanFilter": ".filters",
    "MarginalDRKF": ".filters",
    "NearestOutliers": ".filters",
    "ParallelKalmanFilter": ".filters",
    "RBKF": ".filters",
    "RESULTS": ".filters",
    "RiskSensitiveKF": ".filters",
    "RTSSmoother": ".filters",
    "STKF": ".filters",
    "STKF_AR1": ".filters",
    "STKF_AR2": ".filters",
    "SmootherResult": ".filters",
    "SteadyStateDR": ".sets",
    "SteadyStateDRKF": ".filters",
    "SteadyStateGain": ".filters",
    "SteadyStateKalmanFilter": ".filters",
    "StepOutput": ".filters",
    "TauKF": ".filters",
    "UnscentedKF": ".filters",
    "ThetaMax": ".sets",
    "VBKF": ".filters",
    "WassersteinDRKF": ".filters",
    "WassersteinKF": ".filters",
    "irls_update": ".filters",
    "rts_backward": ".filters",
    "smooth": ".filters",
    "parallel_smooth": ".filters",
    "predict": ".filters",
    "theta_max": ".sets",
    "update": ".filters",
}

__all__ = sorted([*_EXPORTS, *_SUBMODULES, "use_large_cpu_pool", "__version__"])


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        value: Any = importlib.import_module(f".{name}", __name__)
    elif name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from ._gaussian import (
        Gaussian as Gaussian,
    )
    from ._models import (
        LinearModel as LinearModel,
    )
    from ._multisensor import (
        MultiSensorModel as MultiSensorModel,
    )
    from ._nonlinear import (
        NonlinearModel as NonlinearModel,
    )
    from ._em import (
        EMResult as EMResult,
        em_noise_covariances as em_noise_covariances,
    )
    from ._closed_loop import (
        ClosedLoopResult as ClosedLoopResult,
        LQRController as LQRController,
        closed_loop as closed_loop,
    )
    from ._montecarlo import (
        Clairvoyant as Clairvoyant,
        montecarlo as montecarlo,
    )
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
    from ._simulate import (
        Trajectories as Trajectories,
        simulate as simulate,
    )
    from .filters import (
        AbstractFilter as AbstractFilter,
        BCOTKF as BCOTKF,
        BootstrapPF as BootstrapPF,
        CKF as CKF,
        CovarianceIntersection as CovarianceIntersection,
        CovarianceRecursion as CovarianceRecursion,
        DRKF as DRKF,
        DRParticleFilter as DRParticleFilter,
        DropOutliers as DropOutliers,
        EnsembleKF as EnsembleKF,
        ExtendedKF as ExtendedKF,
        FilterResult as FilterResult,
        HuberKF as HuberKF,
        KalmanFilter as KalmanFilter,
        MarginalDRKF as MarginalDRKF,
        NearestOutliers as NearestOutliers,
        ParallelKalmanFilter as ParallelKalmanFilter,
        RBKF as RBKF,
        RESULTS as RESULTS,
        RiskSensitiveKF as RiskSensitiveKF,
        RTSSmoother as RTSSmoother,
        STKF as STKF,
        STKF_AR1 as STKF_AR1,
        STKF_AR2 as STKF_AR2,
        SmootherResult as SmootherResult,
        SteadyStateDRKF as SteadyStateDRKF,
        SteadyStateGain as SteadyStateGain,
        SteadyStateKalmanFilter as SteadyStateKalmanFilter,
        StepOutput as StepOutput,
        TauKF as TauKF,
        UnscentedKF as UnscentedKF,
        VBKF as VBKF,
        WassersteinDRKF as WassersteinDRKF,
        WassersteinKF as WassersteinKF,
        irls_update as irls_update,
        rts_backward as rts_backward,
        smooth as smooth,
        parallel_smooth as parallel_smooth,
        predict as predict,
        update as update,
    )
    from .sets import (
        SteadyStateDR as SteadyStateDR,
        ThetaMax as ThetaMax,
        theta_max as theta_max,
    )
    from . import experiments, filters, linalg, metrics, plotting, sets, tuning
