"""Paper reproductions, one module per paper, registered by name for `jdrkf reproduce`; those
with a `TuningProblem` also for `jdrkf tune`."""

from . import (
    chen_fusion as chen_fusion,
    jang as jang,
    li_convergence as li_convergence,
    li_variational as li_variational,
    wang_nonlinear as wang_nonlinear,
    wang_ye as wang_ye,
    wang_ye_sweeps as wang_ye_sweeps,
)
from ._registry import (
    EXPERIMENTS as EXPERIMENTS,
    MEASURED_ON as MEASURED_ON,
    TIMINGS as TIMINGS,
    Experiment as Experiment,
    Report as Report,
    Row as Row,
    Sweep as Sweep,
    Timing as Timing,
    get as get,
    register as register,
)
from ._tune import TuningProblem as TuningProblem
