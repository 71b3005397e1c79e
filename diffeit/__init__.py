"""diffeit: differentiable electrical impedance tomography in JAX.

Sheet conductivity in S/sq, lengths in metres, currents in amperes, voltages in volts, contact
impedance in ohm m. The forward model computes in float64: importing diffeit changes no JAX
setting, and building the first model (or the first memory computation on images) turns on
`jax_enable_x64` with a `PrecisionWarning` unless the program did so first
(`jax.config.update("jax_enable_x64", True)`). Pass float32 arrays to opt into single
precision.
"""

from . import calibration as calibration
from . import correction as correction
from . import inverse as inverse
from . import io as io
from . import linear_solve as linear_solve
from . import mesh as mesh
from . import metrics as metrics
from . import protocol as protocol
from . import readout as readout
from . import reconstruction as reconstruction
from . import render as render
from . import results as results
from . import scene as scene
from . import touch as touch
from ._precision import PrecisionWarning as PrecisionWarning
from .calibration import SkinCalibration as SkinCalibration
from .calibration import calibrate as calibrate
from .forward import ForwardModel as ForwardModel
from .forward import Potentials as Potentials
from .inverse import Solution as Solution
from .linear_solve import ConjugateGradient as ConjugateGradient
from .linear_solve import DenseCholesky as DenseCholesky
from .linear_solve import HostSparse as HostSparse
from .mesh import Mesh as Mesh
from .protocol import Protocol as Protocol
from .reconstruction import reconstruct as reconstruct
from .scene import Scene as Scene
from .scene import simulate as simulate
from .touch import Touches as Touches
from .touch import touches as touches

__version__ = "0.1.0"
