"""Ambiguity sets, outlier models and their worst-case solvers."""

from ._base import AbstractAmbiguitySet as AbstractAmbiguitySet
from ._bcot import BCOT as BCOT, BCOTWorstCase as BCOTWorstCase, bcot_worst_case as bcot_worst_case
from ._divergence import KL as KL
from ._intersection import CIWeights as CIWeights, ci_weights as ci_weights, covariance_intersection as covariance_intersection
from ._marginal import (
    AbstractMarginalSet as AbstractMarginalSet,
    MarginalKL as MarginalKL,
    MarginalMoment as MarginalMoment,
    MarginalWorstCase as MarginalWorstCase,
    marginal_mmse as marginal_mmse,
)
from ._maxent import (
    MaxEntContinuous as MaxEntContinuous,
    MaxEntResult as MaxEntResult,
    maxent_kl as maxent_kl,
    maxent_kl_solve as maxent_kl_solve,
    maxent_transport as maxent_transport,
    maxent_transport_solve as maxent_transport_solve,
    maxent_wasserstein as maxent_wasserstein,
    maxent_wasserstein_continuous as maxent_wasserstein_continuous,
    maxent_wasserstein_solve as maxent_wasserstein_solve,
)
from ._moment import Moment as Moment
from ._outliers import (
    AbstractOutlierModel as AbstractOutlierModel,
    EpsContamination as EpsContamination,
    EpsNormal as EpsNormal,
)
from ._particle import (
    AbstractParticleLikelihood as AbstractParticleLikelihood,
    AbstractParticlePrior as AbstractParticlePrior,
    AugmentedWassersteinLikelihood as AugmentedWassersteinLikelihood,
    InflatedLikelihood as InflatedLikelihood,
    ParticleKL as ParticleKL,
    ParticleWasserstein as ParticleWasserstein,
    ParticleWassersteinSample as ParticleWassersteinSample,
    WassersteinLikelihood as WassersteinLikelihood,
)
from ._solve import (
    JointWorstCase as JointWorstCase,
    WorstCase as WorstCase,
    wasserstein_mmse as wasserstein_mmse,
    wasserstein_mmse_joint as wasserstein_mmse_joint,
    worst_case as worst_case,
    worst_case_joint as worst_case_joint,
)
from ._steady_state import SteadyStateDR as SteadyStateDR, steady_state_worst_case as steady_state_worst_case
from ._theta_max import ThetaMax as ThetaMax, theta_max as theta_max
from ._wasserstein import Wasserstein as Wasserstein
from ._weights import (
    AbstractWeight as AbstractWeight,
    Barron as Barron,
    GaussianKernel as GaussianKernel,
    Huber as Huber,
    PseudoHuber as PseudoHuber,
    StudentT as StudentT,
)
