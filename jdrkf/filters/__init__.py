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
