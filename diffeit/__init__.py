"""diffeit: differentiable electrical impedance tomography in JAX.

Sheet conductivity in S/sq, lengths in metres, currents in amperes, voltages in volts, contact
impedance in ohm m. Importing diffeit turns on 64-bit floats in JAX: float64 is the default
for the forward model; pass float32 arrays to opt into single precision.
"""

import jax

# EIT voltages span several orders of magnitude and differences of them are the data:
# float64 is the default; float32 is an explicit opt-in by dtype.
jax.config.update("jax_enable_x64", True)

from . import correction as correction
from . import inverse as inverse
from . import io as io
from . import linear_solve as linear_solve
from . import mesh as mesh
from . import metrics as metrics
from . import protocol as protocol
from . import render as render
from . import scene as scene
from .forward import ForwardModel as ForwardModel
from .forward import Potentials as Potentials
from .forward import PrecisionWarning as PrecisionWarning
from .linear_solve import ConjugateGradient as ConjugateGradient
from .linear_solve import DenseCholesky as DenseCholesky
from .linear_solve import HostSparse as HostSparse
from .mesh import Mesh as Mesh
from .protocol import Protocol as Protocol
from .scene import Scene as Scene
from .scene import simulate as simulate

__version__ = "0.1.0"
