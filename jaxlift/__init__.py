"""jaxlift: a differentiable digital twin of the hydraulic lift of an automated forklift.

The public surface. Enable float64 at the start of your program::

    import jax
    jax.config.update("jax_enable_x64", True)
    import jaxlift as jl

    log = jl.read_log("data/run_500kg.csv")
    sol = jl.simulate(jl.Plant(), jl.make_effects("hose_compliance"), jl.Inputs.from_log(log))
"""

from importlib.metadata import version as _version

from .analysis.laws import LIBRARY, Law, explain
from .calibrate.diagnose import (
    Diagnosis,
    EffectScreen,
    RemainingMisfit,
    diagnose,
    diagnose_iteratively,
    remaining_misfit,
    screen_effects,
    usable_heldout,
)
from .calibrate.experiment import PARAMETER_SETS
from .calibrate.fit import evaluate, fit
from .calibrate.result import FitResult
from .calibrate.shape import LogShape, MissingShape, MissingTerms, estimate_missing_shape
from .calibrate.solvers import LM, OptimistixLM
from .control.closed_loop import ClosedLoopSolution, SampledFilterWarning, simulate_closed_loop
from .control.controller import PID, AbstractController, ScheduledPID, load_gains, save_gains
from .control.cost import tuning_residuals
from .control.draws import parameter_draws
from .control.optimisers import LBFGS, Adam, LevenbergMarquardt
from .control.performance import CostWeights, Figures
from .control.performance import figures as closed_loop_figures
from .control.reference import Reference, thesis_reference
from .control.stability import (
    closed_loop_eigenvalues,
    sampled_closed_loop_eigenvalues,
    stability_table,
)
from .control.tune import TuneResult, tune_gains, tune_multistart
from .model.build import Model, all_param_infos, load_model, make_effects, model_params, with_params
from .model.constants import BETA_OIL
from .model.effects import (
    EFFECTS,
    AbstractEffect,
    AbstractStatelessEffect,
    Signals,
    load_effect_file,
    load_entry_point_effects,
    register_effect,
    unregister_effect,
)
from .model.effects.entrained_air import EntrainedAir
from .model.effects.hose_compliance import HoseCompliance
from .model.effects.input_delay import InputDelay
from .model.effects.leakage import Leakage
from .model.effects.mast_compliance import MastCompliance
from .model.effects.motor_droop import MotorDroop
from .model.effects.motor_inertia import MotorInertia
from .model.effects.stick_slip import StickSlip
from .model.inputs import Inputs, initial_height
from .model.log import Log, read_log, write_log
from .model.log_validation import LogError, UnusedColumnsWarning
from .model.measurement import MeasurementModel, measure, to_log
from .model.nudging import Nudging
from .model.params import (
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
from .model.plant import Plant
from .model.simulate import simulate
from .model.solution import AbstractSolution, SimulationError, Solution
from .model.vector_field import plant_signals_and_derivative
from .posterior.air import AIR_THRESHOLD, air_content, mean_working_pressure
from .posterior.likelihood import make_log_prob
from .posterior.moves import (
    AbstractMove,
    DEMove,
    DESnookerMove,
    KDEMove,
    LaplaceMove,
    StretchMove,
)
from .posterior.predictive import posterior_draws
from .posterior.priors import DEFAULT_PRIORS, LogNormal, Uniform
from .posterior.problem import PosteriorProblem, prepare_posterior
from .posterior.sampler import ChainFileLocked, SamplerRun, posterior_samples, sample_posterior
from .report.tuning import robustness_report
from .workflows.diagnose import run_diagnose
from .workflows.fit import model_vs_measurement, run_fit
from .workflows.posterior import PosteriorResult, run_posterior
from .workflows.report import ReportBudget, run_report
from .workflows.simulate import run_simulate
from .workflows.tune import TuneRun, calibrated_model, run_control_simulate, run_tune

__version__ = _version("jaxlift")

__all__ = [
    "run_simulate",
    "Model",
    "AbstractSolution",
    "LM",
    "OptimistixLM",
    "LBFGS",
    "Adam",
    "LevenbergMarquardt",
    "AbstractMove",
    "DEMove",
    "DESnookerMove",
    "KDEMove",
    "LaplaceMove",
    "StretchMove",
    "TuneRun",
    "calibrated_model",
    "run_control_simulate",
    "run_tune",
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
    "PosteriorResult",
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
    "sampled_closed_loop_eigenvalues",
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
    "estimate_missing_shape",
    "MissingShape",
    "LogShape",
    "MissingTerms",
    "Law",
    "LIBRARY",
    "explain",
    "plant_signals_and_derivative",
    "run_diagnose",
    "run_fit",
    "model_vs_measurement",
    "run_report",
    "ReportBudget",
    "screen_effects",
    "AbstractEffect",
    "AbstractStatelessEffect",
    "ChainFileLocked",
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
    "RemainingMisfit",
    "remaining_misfit",
    "usable_heldout",
    "register_effect",
    "unregister_effect",
    "load_effect_file",
    "load_entry_point_effects",
    "replace_params",
    "save_params_json",
    "Nudging",
    "simulate",
    "to_log",
    "to_unconstrained",
    "with_params",
    "write_log",
]
