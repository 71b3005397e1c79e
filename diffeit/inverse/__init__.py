"""Reconstruction: conductivity images from boundary voltages.

Every method is a solver object (`OneStep`, `GREIT`, `GaussNewton`, `AbsoluteGaussNewton`,
`TotalVariation`, and the joint fit's `diffeit.fit.JointImaging`) holding its settings, with one
call `solver.solve(data, throw=True)` that returns a `Solution` (`value`, `result`, `stats`).
"""

from .gauss_newton import AbsoluteGaussNewton as AbsoluteGaussNewton
from .gauss_newton import GaussNewton as GaussNewton
from .greit import GREIT as GREIT
from .hyperparameter import HyperparameterSelection as HyperparameterSelection
from .hyperparameter import from_external_hyperparameter as from_external_hyperparameter
from .hyperparameter import select_hyperparameter as select_hyperparameter
from .hyperparameter import to_external_hyperparameter as to_external_hyperparameter
from .linearised import CONTACT_IMPEDANCE_SPREAD as CONTACT_IMPEDANCE_SPREAD
from .linearised import LinearisedProblem as LinearisedProblem
from .one_step import OneStep as OneStep
from .priors import Laplace as Laplace
from .priors import Matern as Matern
from .priors import Noser as Noser
from .priors import Tikhonov as Tikhonov
from .solution import AbstractSolver as AbstractSolver
from .solution import Solution as Solution
from .total_variation import TotalVariation as TotalVariation
