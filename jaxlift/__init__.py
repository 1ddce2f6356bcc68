"""jaxlift: a differentiable digital twin of the hydraulic lift of an automated forklift.

The public surface. Enable float64 at the start of your program::

    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxlift as jl

    log = jl.read_log("data/run_500kg.csv")
    sol = jl.simulate(jl.Plant(), jl.make_effects("hose_compliance"), jl.Inputs.from_log(log))
"""

from ._closed_loop import (
    ClosedLoopSolution,
    Reference,
    SampledFilterWarning,
    simulate_closed_loop,
    thesis_reference,
)
from ._control import PID, AbstractController, ScheduledPID, load_gains, save_gains
from ._diagnose import (
    Diagnosis,
    EffectScreen,
    diagnose,
    diagnose_iteratively,
    screen_effects,
)
from ._effects import EFFECTS, AbstractEffect, AbstractStatelessEffect, Signals
from ._effects.entrained_air import EntrainedAir
from ._effects.hose_compliance import HoseCompliance
from ._effects.input_delay import InputDelay
from ._effects.leakage import Leakage
from ._effects.mast_compliance import MastCompliance
from ._effects.motor_droop import MotorDroop
from ._effects.motor_inertia import MotorInertia
from ._effects.stick_slip import StickSlip
from ._fit import PARAMETER_SETS, FitResult, evaluate, fit
from ._log import Log, LogError, UnusedColumnsWarning, read_log, write_log
from ._measurement import MeasurementModel, measure, to_log
from ._model import all_param_infos, load_model, model_params, with_params
from ._params import (
    ParameterError,
    ParamInfo,
    from_unconstrained,
    get_params,
    load_params_json,
    param,
    param_infos,
    replace_params,
    save_params_json,
    to_unconstrained,
)
from ._performance import CostWeights, Figures
from ._performance import figures as closed_loop_figures
from ._plant import Plant
from ._posterior import (
    AIR_THRESHOLD,
    BETA_OIL,
    DEFAULT_PRIORS,
    LogNormal,
    PosteriorProblem,
    SamplerRun,
    Uniform,
    air_content,
    make_log_prob,
    mean_working_pressure,
    posterior_draws,
    posterior_samples,
    prepare_posterior,
    run_posterior,
    sample_posterior,
)
from ._simulate import (
    Inputs,
    SimulationError,
    Solution,
    initial_height,
    make_effects,
    plant_signals_and_derivative,
    simulate,
)
from ._tuning import (
    TuneResult,
    closed_loop_eigenvalues,
    parameter_draws,
    robustness_report,
    stability_table,
    tune_gains,
    tune_multistart,
    tuning_residuals,
)
from ._workflows import run_diagnose, run_fit

__version__ = "0.1.0"

__all__ = [
    "AIR_THRESHOLD",
    "BETA_OIL",
    "DEFAULT_PRIORS",
    "LogNormal",
    "PosteriorProblem",
    "SamplerRun",
    "Uniform",
    "air_content",
    "make_log_prob",
    "mean_working_pressure",
    "posterior_draws",
    "posterior_samples",
    "prepare_posterior",
    "run_posterior",
    "sample_posterior",
    "PID",
    "AbstractController",
    "ClosedLoopSolution",
    "CostWeights",
    "Figures",
    "Reference",
    "SampledFilterWarning",
    "ScheduledPID",
    "TuneResult",
    "closed_loop_eigenvalues",
    "closed_loop_figures",
    "load_gains",
    "parameter_draws",
    "robustness_report",
    "save_gains",
    "simulate_closed_loop",
    "stability_table",
    "thesis_reference",
    "tune_gains",
    "tune_multistart",
    "tuning_residuals",
    "EFFECTS",
    "PARAMETER_SETS",
    "Diagnosis",
    "EffectScreen",
    "FitResult",
    "diagnose",
    "diagnose_iteratively",
    "evaluate",
    "fit",
    "plant_signals_and_derivative",
    "run_diagnose",
    "run_fit",
    "screen_effects",
    "AbstractEffect",
    "AbstractStatelessEffect",
    "EntrainedAir",
    "HoseCompliance",
    "InputDelay",
    "Inputs",
    "Leakage",
    "Log",
    "LogError",
    "MastCompliance",
    "MeasurementModel",
    "MotorDroop",
    "MotorInertia",
    "ParamInfo",
    "ParameterError",
    "Plant",
    "Signals",
    "SimulationError",
    "Solution",
    "StickSlip",
    "UnusedColumnsWarning",
    "all_param_infos",
    "from_unconstrained",
    "get_params",
    "initial_height",
    "load_model",
    "load_params_json",
    "make_effects",
    "measure",
    "model_params",
    "param",
    "param_infos",
    "read_log",
    "replace_params",
    "save_params_json",
    "simulate",
    "to_log",
    "to_unconstrained",
    "with_params",
    "write_log",
]
